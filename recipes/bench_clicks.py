"""Annotation effort in clicks (`bench_masks.py --clicks`): a simulated user clicks until a frame's mask is right.

The user is the one interactive-segmentation papers use (Xu et al. 2016, and RITM / SAM after them): the next click
is at the centre (the maximum of the distance transform) of the largest error region, positive on a region the mask
misses, negative on one it wrongly holds; at most MAX_CLICKS a frame. Each click's answer is
`interreal.masks.clicks.segment(image, clicks so far, prior = the previous answer)`, exactly what the annotation
app runs on a click. NoC@85 / NoC@90: the clicks until IoU >= 0.85 / 0.90 (MAX_CLICKS when never reached).
Data: every 10th frame of each shared DAVIS sequence, and the laptop fixtures' LabelMe keyframes (each object).
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from interreal.masks.clicks import Click, segment

MAX_CLICKS = 20
LEVELS = (0.85, 0.90)
FRAME_STEP = 10
CHAIN = False  # the prior of each click: the previous answer (True) or the frame's own prior (False)


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
    return {"ious": [round(v, 4) for v in ious], "seconds": secs, "mask": pred, **noc}


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


def laptop_frames(fixtures: Path, images: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, rgb, truth) per object of each laptop keyframe (LabelMe JSON rasterised, ignore left out)."""
    import json

    from interreal.masks.labelme import rasterise

    out = []
    for js in sorted((fixtures / "keyframes").glob("*.json")):
        doc = json.loads(js.read_text())
        img = next((p for p in images.glob(f"*{js.stem}*") if p.suffix.lower() in (".png", ".jpg", ".jpeg")), None)
        if img is None:
            continue
        rgb = cv2.cvtColor(cv2.imread(str(img)), cv2.COLOR_BGR2RGB)
        names = sorted({s["label"] for s in doc.get("shapes", []) if s.get("label") not in ("ignore", "hand", "person", "arm")})
        index = rasterise(js, (rgb.shape[1], rgb.shape[0]), names, lambda: rgb, strict=False)
        for k, name in enumerate(names):
            gt = index == k + 1
            if gt.sum() > 100:
                out.append((f"{js.stem}:{name}", rgb, gt))
    return out


def run_clicks(sets: dict[str, list[tuple[str, np.ndarray, np.ndarray]]], max_clicks: int = MAX_CLICKS) -> dict:
    """NoC per frame and per sequence, and the means over every frame scored (the `clicks` object)."""
    frames, per_seq = [], []
    for seq, items in sets.items():
        rows = []
        for name, rgb, gt in items:
            r = click_frame(rgb, gt, max_clicks, stop_at=max(LEVELS))
            r.pop("mask")
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
