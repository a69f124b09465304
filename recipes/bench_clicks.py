"""Annotation effort in clicks (`bench_masks.py --clicks`): a simulated user clicks until a frame's mask is right.

The user is the one interactive-segmentation papers use (Xu et al. 2016, and RITM / SAM after them): the next click
is at the centre (the maximum of the distance transform) of the largest error region, positive on a region the mask
misses, negative on one it wrongly holds; at most MAX_CLICKS a frame. Each click's answer is
`interreal.masks.clicks.segment(image, clicks so far, prior = the previous answer)`, exactly what the annotation
app runs on a click. NoC@85 / NoC@90: the clicks until IoU >= 0.85 / 0.90 (MAX_CLICKS when never reached).
Data: every 10th frame of each shared DAVIS sequence, and the laptop fixtures' LabelMe keyframes (each object).
"""

from __future__ import annotations

import json
import shutil
import statistics
import sys
import time
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from benchlib import print_table, scatter_chart, write_results

from interreal import atomic
from interreal.conventions import fid_of_index, frame_name
from interreal.masks.clicks import Click, segment
from interreal.masks.labelme import rasterise
from interreal.paths import require_shared, shared_data
from interreal.transients import IGNORE

MAX_CLICKS = 20
LEVELS = (0.85, 0.90)
FRAME_STEP = 10
CHAIN = True  # the prior of each click: the previous answer, as in the app (False: the frame's own prior each time)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)


def next_click(pred: np.ndarray, gt: np.ndarray) -> Click | None:
    """The simulated user's next click: the centre of the largest error region (None when there is no error)."""
    best = None
    for positive, err in ((True, gt & ~pred), (False, pred & ~gt)):
        if not err.any():
            continue
        n, comp, stats, _ = cv2.connectedComponentsWithStats(err.astype(np.uint8), connectivity=8)
        k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        area = int(stats[k, cv2.CC_STAT_AREA])
        if best is None or area > best[0]:
            best = (area, positive, comp == k)
    if best is None:
        return None
    _, positive, region = best
    # the image border counts as the region's edge too: pad with zeros before the distance transform
    dist = cv2.distanceTransform(np.pad(region, 1).astype(np.uint8), cv2.DIST_L2, 5)[1:-1, 1:-1]
    y, x = np.unravel_index(int(np.argmax(dist)), dist.shape)
    return Click(float(x), float(y), positive)


def click_frame(rgb: np.ndarray, gt: np.ndarray, max_clicks: int = MAX_CLICKS,
                prior: np.ndarray | None = None, stop_at: float | None = None, chain: bool | None = None) -> dict:
    """Clicks on one frame until stop_at (or max_clicks): IoU after each click, seconds per click, NoC at LEVELS."""
    gt = gt.astype(bool)
    chain = CHAIN if chain is None else chain
    pred = np.zeros_like(gt) if prior is None else prior.astype(bool)
    clicks: list[Click] = []
    ious, secs = [], []
    for _ in range(max_clicks):
        c = next_click(pred, gt)
        if c is None:
            break
        clicks.append(c)
        t = time.perf_counter()
        pred = segment(rgb, clicks, prior=(pred if pred.any() else None) if chain else prior)
        secs.append(time.perf_counter() - t)
        ious.append(iou(pred, gt))
        if stop_at is not None and ious[-1] >= stop_at:
            break
    noc = {f"noc{round(100 * lv)}": next((i + 1 for i, v in enumerate(ious) if v >= lv), max_clicks) for lv in LEVELS}
    return {"ious": [round(v, 4) for v in ious], "seconds": secs, "mask": pred, "clicks": clicks, **noc}


def davis_frames(root: Path, seq: str, step: int = FRAME_STEP) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, rgb, truth) of every step-th frame of a DAVIS sequence; frames whose truth is empty are left out."""
    jpgs = sorted((root / seq / "images").glob("*.jpg"))
    pngs = sorted((root / seq / "masks").glob("*.png"))
    out = []
    for j, p in list(zip(jpgs, pngs))[::step]:
        gt = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 127
        if gt.any():
            out.append((j.stem, cv2.cvtColor(cv2.imread(str(j)), cv2.COLOR_BGR2RGB), gt))
    return out


def laptop_frames(fixtures: Path, video: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, rgb, truth) of each laptop fixture keyframe (LabelMe polygons on frames of the video, named by their
    frame number): the lid, and the ignore class (hand, person) as the click tool's second target. The truth is a
    polygon of 4-8 corners: coarse at the edges, so NoC@90 here measures agreement with a quick polygon."""
    keys = sorted(fixtures.glob("*.json"))
    want = {int(p.stem): p for p in keys}
    out = []
    cap = cv2.VideoCapture(str(video))
    i = 0
    while want and i <= max(want):
        ok, bgr = cap.read()
        if not ok:
            break
        if i in want:
            rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            index = rasterise(want[i], (rgb.shape[1], rgb.shape[0]), ["laptop lid"], lambda: rgb, strict=False)
            for name, gt in (("lid", index == 1), ("ignore", index == IGNORE)):
                if gt.sum() > 100:
                    out.append((f"{want[i].stem}:{name}", rgb, gt))
        i += 1
    cap.release()
    return out


def run_clicks(sets: dict[str, list[tuple[str, np.ndarray, np.ndarray]]], max_clicks: int = MAX_CLICKS) -> dict:
    """NoC per frame and per sequence, and the means over every frame scored (the `clicks` object)."""
    frames, per_seq = [], []
    for seq, items in sets.items():
        rows = []
        for name, rgb, gt in items:
            r = click_frame(rgb, gt, max_clicks, stop_at=max(LEVELS))
            r.pop("mask"), r.pop("clicks")
            rows.append({"data": seq, "frame": name, "noc85": r["noc85"], "noc90": r["noc90"], "ious": r["ious"],
                         "s_per_click": statistics.mean(r["seconds"]) if r["seconds"] else 0.0,
                         "iou_1": r["ious"][0] if r["ious"] else None, "size": list(rgb.shape[:2])})
        if not rows:
            continue
        frames += rows
        per_seq.append({"data": seq, "frames": len(rows), "noc85": statistics.mean(r["noc85"] for r in rows),
                        "noc90": statistics.mean(r["noc90"] for r in rows),
                        "iou_1": statistics.mean(r["iou_1"] for r in rows),
                        "s_per_click": statistics.mean(r["s_per_click"] for r in rows)})
        s = per_seq[-1]
        print(f"  clicks {seq}: NoC@85 {s['noc85']:.1f}, NoC@90 {s['noc90']:.1f}, IoU after 1 click {s['iou_1']:.2f}, "
              f"{s['s_per_click']:.3f} s/click ({len(rows)} frames)", file=sys.stderr)
    per_seq.sort(key=lambda s: -s["noc90"])
    curve = [statistics.mean(r["ious"][min(k, len(r["ious"])) - 1] if r["ious"] else 0.0 for r in frames)
             for k in range(1, max_clicks + 1)] if frames else []
    summary = {"noc85": statistics.mean(r["noc85"] for r in frames) if frames else None,
               "noc90": statistics.mean(r["noc90"] for r in frames) if frames else None,
               "s_per_click": statistics.mean(r["s_per_click"] for r in frames) if frames else None,
               "frames": len(frames), "max_clicks": max_clicks, "iou_by_clicks": [round(v, 4) for v in curve],
               "per_sequence": per_seq}
    return {"clicks": summary, "frames": frames}


def video_loop(seq: str, ds: Path, gts: list[np.ndarray], kdir: Path, propagate: Callable[..., float],
               frame_j: Callable[..., np.ndarray], rounds: int, budget: int) -> dict:
    """Clicks to a whole video: the user clicks the frame the stage suggests (the first frame first; the stage's
    propagated mask of that frame is the prior) until it is at IoU 0.9 (or MAX_CLICKS), the keyframe is saved,
    propagation re-runs (`interreal masks`, the whole command, which re-makes the gaps the new keyframe touched: the
    time the user waits), and so on, until every frame is at J >= 0.9, or `rounds` keyframes or `budget` clicks are
    spent. Reports, per level 0.8 / 0.9, the clicks per 100 frames when every frame first reached it (None: not
    within the budget)."""
    n = len(gts)
    keys: dict[int, np.ndarray] = {}
    target, prior, total, wait = 0, None, 0, 0.0
    history, reached = [], {0.8: None, 0.9: None}
    for _ in range(rounds):
        rgb = cv2.cvtColor(cv2.imread(str(ds / "images" / f"{frame_name(target)}.png")), cv2.COLOR_BGR2RGB)
        r = click_frame(rgb, gts[target] > 0, prior=prior, stop_at=max(LEVELS))
        total += len(r["ious"])
        keys[target] = r["mask"]
        shutil.rmtree(kdir, ignore_errors=True)
        for k, m in keys.items():
            atomic.write_image(kdir / f"{fid_of_index(k)}.png", m.astype(np.uint8))
        atomic.write_yaml(kdir / "mapping.yaml", {0: seq})
        seconds = propagate(ds, kdir, [], 3, reuse=bool(history))  # a new round re-makes what it changed
        wait += seconds
        j = frame_j(ds, gts, 1)[:, 0]
        history.append({"keyframe": target, "clicks": len(r["ious"]), "clicks_total": total,
                        "j_mean": round(float(j.mean()), 4), "j_min": round(float(j.min()), 4),
                        "share_j90": round(float((j >= 0.9).mean()), 4), "wait_s": round(seconds, 2)})
        for lv in reached:
            if reached[lv] is None and j.min() >= lv:
                reached[lv] = round(100 * total / n, 1)
        if j.min() >= max(reached) or total >= budget:
            break
        rep = json.loads((ds / "reports" / "masks.json").read_text())
        suggested = [int(f) for f in rep["figures"].get("suggested_frames", []) if int(f) not in keys]
        target = suggested[0] if suggested else _widest_gap(sorted(keys), n)
        if target in keys:
            break
        onehot = np.load(ds / "masks" / f"{fid_of_index(target)}.npy")
        prior = onehot[..., 0] if onehot[..., 0].any() else None
    print(f"  clicks video {seq}: {total} clicks ({100 * total / n:.0f} per 100 frames), {len(keys)} keyframes, "
          f"J mean {history[-1]['j_mean']:.3f} min {history[-1]['j_min']:.3f}; every frame J >= 0.8 at "
          f"{reached[0.8]}, >= 0.9 at {reached[0.9]} clicks per 100 frames; waited {wait:.0f} s", file=sys.stderr)
    return {"data": seq, "frames": n, "keyframes": len(keys), "clicks": total,
            "clicks_per_100": round(100 * total / n, 1), "per100_to_j80": reached[0.8], "per100_to_j90": reached[0.9],
            "j_mean": history[-1]["j_mean"], "j_min": history[-1]["j_min"], "wait_s": round(wait, 1),
            "wait_s_per_round": round(wait / len(history), 2), "rounds": history}


def _widest_gap(keys: list[int], n: int) -> int:
    """The frame in the middle of the longest stretch without a keyframe."""
    edges = [-1] + keys + [n]
    a, b = max(zip(edges, edges[1:]), key=lambda g: g[1] - g[0])
    return (a + b) // 2  # frames a+1 .. b-1; a keyframe itself when there is no gap left


def curve(frames: list[dict], max_clicks: int = MAX_CLICKS) -> list[float]:
    """Mean IoU after k = 1 .. max_clicks clicks (a frame that stopped at IoU 0.9 keeps its last IoU)."""
    return [round(statistics.mean(r["ious"][min(k, len(r["ious"])) - 1] if r["ious"] else 0.0 for r in frames), 4)
            for k in range(1, max_clicks + 1)] if frames else []


def main_clicks(args, davis_sequences: Callable, davis_dataset: Callable, propagate: Callable, frame_j: Callable,
                fixtures: Path) -> int:
    """`bench_masks.py --clicks`: NoC on single frames (DAVIS every 10th frame, the laptop fixtures), then, with
    --video-rounds N, the clicks to a whole video; DIR/masks_clicks.json (top-level `clicks`) and its charts."""
    root = require_shared("davis2016")
    seqs = args.only.split(",") if args.only else davis_sequences(args.quick)
    sets = {s: davis_frames(root, s, FRAME_STEP * (2 if args.quick else 1)) for s in seqs}
    video = shared_data() / "laptop" / "laptop_orbit.mp4"
    if video.is_file() and not args.quick:
        sets["laptop"] = laptop_frames(fixtures, video)
    res = run_clicks(sets)
    summary, frames = res["clicks"], res["frames"]
    davis = [r for r in frames if r["data"] != "laptop"]
    summary["davis"] = {"frames": len(davis), "noc85": statistics.mean(r["noc85"] for r in davis),
                        "noc90": statistics.mean(r["noc90"] for r in davis),
                        "s_per_click": statistics.mean(r["s_per_click"] for r in davis),
                        "iou_by_clicks": curve(davis)}
    lap = [r for r in frames if r["data"] == "laptop"]
    if lap:
        summary["laptop"] = {"frames": len(lap), "noc85": statistics.mean(r["noc85"] for r in lap),
                             "noc90": statistics.mean(r["noc90"] for r in lap),
                             "s_per_click": statistics.mean(r["s_per_click"] for r in lap), "iou_by_clicks": curve(lap),
                             "note": "truth: the fixtures' LabelMe polygons (4-8 corners), coarse at the edges"}
    videos = []
    for seq in (seqs if args.video_rounds > 0 else []):
        ds, gts, _ = davis_dataset(seq, args.out / "_masks_work", 20 if args.quick else None)
        videos.append(video_loop(seq, ds, gts, args.out / "_masks_work" / f"clickkeys-{seq}", propagate, frame_j,
                                 args.video_rounds, args.video_budget))
    if videos:
        summary["video"] = video_summary(videos)
    runs = [{"kind": "frames", **s} for s in summary["per_sequence"]] + [
        {"kind": "video", **{k: v for k, v in r.items() if k != "rounds"}} for r in videos]
    # the mean IoU after each click per set, with its seconds (the README's chart: recipes/charts.py)
    curve_rows = [{"kind": "curve", "set": name, "clicks": k + 1, "iou": v, "s_per_click": round(sub["s_per_click"], 3)}
                  for name, sub in (("DAVIS", summary["davis"]), ("laptop", summary.get("laptop"))) if sub
                  for k, v in enumerate(sub["iou_by_clicks"])]
    runs += curve_rows
    write_results(args.out, "masks_clicks", runs, quick=args.quick, clicks=summary, frames=frames,
                  videos=videos, targets={"davis noc90": 10, "davis noc85": 6, "s per click": 0.5,
                                          "video clicks per 100 frames to J >= 0.9": 40},
                  note="NoC: clicks of the simulated user until IoU >= 0.85 / 0.90 (20 when never); seconds per "
                       "click: interreal.masks.clicks.segment on a shared 2-core machine")
    points = [{**r, "seconds": round(r["clicks"] * r["s_per_click"], 3)} for r in curve_rows]
    for x, xlabel in (("clicks", "clicks"), ("seconds", "seconds of computation (clicks x mean s per click)")):
        scatter_chart(args.out / f"masks_clicks{'' if x == 'clicks' else '_seconds'}.png", points, x, "iou",
                      label=lambda r: "", lines_by=lambda r: r["set"], xlabel=xlabel, ylabel="IoU (mean over frames)",
                      title="click to segment: IoU against " + x)
    print_table([r for r in runs if r["kind"] != "curve"],
                ["kind", "data", "frames", "noc85", "noc90", "iou_1", "s_per_click", "clicks_per_100", "per100_to_j80",
                 "per100_to_j90", "j_min", "wait_s_per_round"], title="clicks (worst first)")
    print(json.dumps({k: v for k, v in summary.items() if k != "per_sequence"}, indent=1))
    return 0


def video_summary(videos: list[dict]) -> dict:
    """Means over the videos: clicks per 100 frames to every frame at J >= 0.8 / 0.9 (over those that got there)."""
    out = {"videos": len(videos), "clicks_per_100": statistics.mean(v["clicks_per_100"] for v in videos),
           "wait_s_per_round": statistics.mean(v["wait_s_per_round"] for v in videos)}
    for key in ("per100_to_j80", "per100_to_j90"):
        got = [v[key] for v in videos if v[key] is not None]
        out[key] = statistics.mean(got) if got else None
        out[key.replace("per100", "reached")] = f"{len(got)} of {len(videos)}"
    return out
