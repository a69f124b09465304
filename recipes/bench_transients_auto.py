"""`--transients auto` on real video: how much of the hands, arms and people the proposed layer finds, with nothing
painted, and what each cue costs.

Data: ../shared/data/laptop/laptop_orbit.mp4 (240 frames, 1072x608: a hand reaches in from the top edge to move the
lid; a person stands at the right edge at the start and the end) and careful polygons of five of its frames,
tests/fixtures/laptop/transients.json ('hand' = the hand that moves the lid and its forearm to the image edge,
'person' = someone standing in view). Per frame: IoU of the layer against the hand-and-arm polygons (frames that
have them) and against everything transient, and the share of the static pixels (neither) the layer takes. Per cue: seconds over the video
and what it finds (the hand model's tracking pass, its static pass on the frames tracking missed, the interpolated
gaps, the GrabCut growth). Worst frame first.

`--synth SEEDS`: the same on simulated captures with an arm in front of the parts (`--hard` as `bench_motions.py`
makes them, 960x720, 90 frames, no person walking: every occluder pixel is the hand or its sleeve), against the
simulator's exact occluder masks over every frame the arm shows in, over those where the hand model found a hand
(what growing makes of a found hand, apart from finding it) and over those it carried the layer to by the flow (the
masks stage's `carry`). Per seed, worst first.

    python recipes/bench_transients_auto.py --out bench/
    python recipes/bench_transients_auto.py --synth 1,2,3 --out bench/
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np

from benchlib import REPO, bench_args, print_table, write_results

from interreal.masks.carry import carry_layer
from interreal.paths import require_shared
from interreal.synth.config import SynthConfig
from interreal.synth.render import OCCLUDER
from interreal.synth.scene import build_scene
from interreal.transients.auto import propose, seeds, work_size
from interreal.transients.hands import model_problem, shares

MIN_ARM_PX = 50  # work-size pixels: a frame the arm shows in (a sliver at the edge is not scored)
FIXTURE = REPO / "tests" / "fixtures" / "laptop" / "transients.json"


def truth_masks(fixture: dict, fid: str, size: tuple[int, int]) -> dict[str, np.ndarray]:
    """{'hand', 'person', 'all'} -> (h, w) bool masks of one fixture frame, drawn at `size` (w, h)."""
    sx, sy = size[0] / fixture["size"][0], size[1] / fixture["size"][1]
    out = {}
    for kind in ("hand", "person"):
        m = np.zeros((size[1], size[0]), np.uint8)
        polys = [np.round(np.array(p, float) * [sx, sy]).astype(np.int32) for p in fixture["frames"][fid].get(kind, [])]
        if polys:
            cv2.fillPoly(m, polys, 1)
        out[kind] = m > 0
    out["all"] = out["hand"] | out["person"]
    return out


def iou(a: np.ndarray, b: np.ndarray) -> float | None:
    u = int((a | b).sum())
    return None if u == 0 else float((a & b).sum()) / u


def read_video(path: Path, size: tuple[int, int]) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, bgr = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(cv2.resize(bgr, size, interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB))
    return frames


SYNTH = {"width": 960, "height": 720, "frames": 90, "furniture": "plain", "exposure_drift": 0.2, "noise": 3.0,
         "occluder": 0.0, "arm": True}  # bench_motions' --hard, at a phone's size, without the walking person


def main() -> None:
    args = bench_args("transients_auto", __doc__.splitlines()[0], lambda p: p.add_argument(
        "--synth", metavar="SEEDS", help="simulated captures with an arm (comma-separated seeds) instead of the laptop"))
    problem = model_problem()
    if problem:
        raise SystemExit(problem)
    if args.synth:
        return synth(args, [int(v) for v in args.synth.split(",")])
    video = require_shared("laptop/laptop_orbit.mp4")
    fixture = json.loads(FIXTURE.read_text())
    full = tuple(fixture["size"])
    wsize = work_size(full)
    t0 = time.perf_counter()
    frames = read_video(video, full)
    decode_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    layer = carry_layer(propose(lambda p: frames[p], len(frames), full, progress=True), lambda p: frames[p],
                        len(frames))
    total_s = time.perf_counter() - t0
    runs, tiles = [], []
    for fid in fixture["frames"]:
        pos = int(fid)
        truth = truth_masks(fixture, fid, wsize)
        got = layer.masks.get(pos, np.zeros((wsize[1], wsize[0]), bool))
        hands = layer.track.hands[pos]
        hull = seeds(hands, (wsize[1], wsize[0]))[1] if len(hands) else np.zeros_like(got)
        static = ~truth["all"]
        tiles.append(overlay(cv2.resize(frames[pos], wsize, interpolation=cv2.INTER_AREA), got, truth["all"], fid))
        runs.append({"frame": fid, "found_by": layer.track.how[pos] or "-",
                     "iou_hand_arm": iou(got, truth["hand"]) if truth["hand"].any() else None, "iou_all": iou(got, truth["all"]),
                     "iou_reach_all": iou(hull, truth["all"]),
                     "static_taken": round(float((got & static).sum() / static.sum()), 5),
                     "layer_share": round(float(got.mean()), 4)})
    runs.sort(key=lambda r: (r["iou_all"] is None, r["iou_all"] or 0.0))
    for r in runs:
        for k in ("iou_hand_arm", "iou_all", "iou_reach_all"):
            r[k] = None if r[k] is None else round(r[k], 3)
    summary = {
        "frames": len(frames), "work_size": list(layer.work_size), "hands_found": round(layer.track.found_share(), 4),
        **{f"found_{k}": v for k, v in shares(layer.track).items()},
        "mean_iou_hand_arm": _mean(r["iou_hand_arm"] for r in runs),
        "mean_iou_all": _mean(r["iou_all"] for r in runs),
        "worst_iou_all": min((r["iou_all"] or 0.0) for r in runs),
        "max_static_taken": max(r["static_taken"] for r in runs),
        "layer_frames": len(layer.masks), "carried_frames": len(layer.carried), "leaked_frames": len(layer.leaked),
        "seconds": {**layer.seconds, "decode": round(decode_s, 3), "total": round(total_s, 3)},
        "ms_per_frame": round(1000 * total_s / max(len(frames), 1), 1)}
    write_results(args.out, "transients_auto", runs, summary=summary)
    cv2.imwrite(str(args.out / "transients_auto.png"), cv2.cvtColor(np.vstack(tiles), cv2.COLOR_RGB2BGR))
    print_table(runs, ["frame", "found_by", "iou_hand_arm", "iou_all", "iou_reach_all", "static_taken",
                       "layer_share"], title="auto transient layer vs careful polygons, worst first")
    print(json.dumps(summary, indent=1))


def synth(args, seeds: list[int]) -> None:
    """The auto layer on simulated captures against the simulator's occluder truth, one row per seed."""
    runs = []
    for seed in seeds:
        scene = build_scene(SynthConfig(seed=seed, **SYNTH))
        frames = [scene.render_frame(t) for t in range(scene.cfg.frames)]
        size = (scene.cfg.width, scene.cfg.height)
        t0 = time.perf_counter()
        layer = carry_layer(propose(lambda p: frames[p].rgb, len(frames), size, progress=True),
                            lambda p: frames[p].rgb, len(frames))
        total_s = time.perf_counter() - t0
        ious, taken, found, carried = [], [], [], []
        for pos, f in enumerate(frames):
            inst = cv2.resize(f.instance, layer.work_size, interpolation=cv2.INTER_NEAREST)
            arm, static = inst == OCCLUDER, inst == 0
            got = layer.masks.get(pos, np.zeros(arm.shape, bool)) & (arm | static)  # objects are cut when written
            taken.append(float((got & static).sum() / static.sum()))
            if arm.sum() >= MIN_ARM_PX:
                ious.append(iou(got, arm) or 0.0)
                if len(layer.track.hands[pos]):
                    found.append(ious[-1])
                elif pos in layer.carried:
                    carried.append(ious[-1])
        runs.append({"seed": seed, "arm_frames": len(ious), "hands_found": round(layer.track.found_share(), 3),
                     "carried": round(len(layer.carried) / len(frames), 3),
                     "mean_iou_hand_arm": _mean(ious), "iou_where_found": _mean(found),
                     "iou_where_carried": _mean(carried),
                     "worst_decile_iou": round(float(np.percentile(ious, 10)), 3),
                     "mean_static_taken": round(float(np.mean(taken)), 5), "max_static_taken": round(max(taken), 5),
                     "seconds": round(total_s, 1)})
    runs.sort(key=lambda r: r["mean_iou_hand_arm"] or 0.0)
    summary = {"capture": SYNTH, "mean_iou_hand_arm": _mean(r["mean_iou_hand_arm"] for r in runs),
               "mean_iou_where_found": _mean(r["iou_where_found"] for r in runs),
               "max_static_taken": max(r["max_static_taken"] for r in runs)}
    write_results(args.out, "transients_auto_synth", runs, summary=summary)
    print_table(runs, list(runs[0]), title="auto transient layer vs the simulator's arm, worst seed first")
    print(json.dumps(summary, indent=1))


def overlay(img: np.ndarray, got: np.ndarray, truth: np.ndarray, caption: str) -> np.ndarray:
    """The layer in red over the frame, the truth's outline in green."""
    out = img.copy()
    out[got] = (0.5 * out[got] + [127, 0, 0]).astype(np.uint8)
    contours, _ = cv2.findContours(truth.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(out, contours, -1, (0, 255, 0), 1)
    cv2.putText(out, caption, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 0), 2)
    return out


def _mean(values) -> float | None:
    v = [x for x in values if x is not None]
    return round(float(np.mean(v)), 3) if v else None


if __name__ == "__main__":
    main()
