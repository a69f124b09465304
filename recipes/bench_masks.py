"""Mask propagation benchmark: IoU against truth and speed, ours vs a plain Farneback baseline.

Data: DAVIS 2016 `blackswan` and `car-shadow` (../shared/data/davis2016, first frame only and a keyframe every
10 frames) and the default simulated capture (`interreal synth`, keyframes every 60 frames + first + last).
Each record: data, variant, keyframe_every (0 = first frame only), iou_mean (Jaccard, mean over the frames
that were not given, per object, then over objects), iou_worst_object, fps (frames/s of the propagation
itself, image decoding included, writing excluded; 2 threads; wall clock, so slowed by other load), cpu_fps
(frames per CPU-second over all threads = one dedicated core; load-independent), frames, objects,
worst_frames (per object, its five worst (frame, IoU) pairs: where propagation fails).

    python recipes/bench_masks.py --quick --out bench/
    python recipes/bench_masks.py --out bench/
"""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from benchlib import bench_args, print_table, scatter_chart, write_results

from interreal import atomic
from interreal.conventions import fid_of_index, frame_name
from interreal.masks import propagate
from interreal.masks.appearance import AppearanceConfig
from interreal.masks.flow import FlowConfig
from interreal.masks.track import TrackConfig
from interreal.paths import require_shared

DAVIS = ("blackswan", "car-shadow")
THREADS = 2


def variants(quick: bool) -> dict[str, TrackConfig | None]:
    """None = the stage's defaults ('ours')."""
    out: dict[str, TrackConfig | None] = {
        "ours": None,
        "baseline": TrackConfig(flow=FlowConfig(method="farneback", boundary_tol=0.0),
                                appearance=AppearanceConfig(weight=0.0), work_long_side=0, fill_radius=0,
                                refine_radius=0, out_radius=0, sharpen=1.0, fusion=False, rigid=0.0),
    }
    if not quick:
        out["ours-fast"] = TrackConfig(flow=FlowConfig(preset="ultrafast"), work_long_side=320)
        out["ours-full"] = TrackConfig(flow=FlowConfig(preset="medium"), work_long_side=0)
    return out


def davis_dataset(seq: str, root: Path, limit: int | None) -> tuple[Path, list[np.ndarray], list[str]]:
    """images/frame_%05d.png from the JPEGs (once), plus the truth as index maps."""
    src = require_shared("davis2016", seq)
    jpgs = sorted((src / "images").glob("*.jpg"))[:limit]
    pngs = sorted((src / "masks").glob("*.png"))[:limit]
    ds = root / f"davis-{seq}-{len(jpgs)}"
    if not (ds / "images").is_dir() or len(list((ds / "images").iterdir())) != len(jpgs):
        shutil.rmtree(ds, ignore_errors=True)
        for i, j in enumerate(jpgs):
            atomic.write_bytes(ds / "images" / f"{frame_name(i)}.png", cv2.imencode(".png", cv2.imread(str(j)))[1].tobytes())
    gts = [(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 127).astype(np.uint8) for p in pngs]
    return ds, gts, [seq]


def synth_dataset(root: Path, quick: bool) -> tuple[Path, list[np.ndarray], list[str], list[int]]:
    """The default simulated capture (smaller with --quick), decoded frame by frame from its H.264 video."""
    import av

    from interreal.synth import Capture, SynthConfig, write_capture

    cfg = SynthConfig(frames=90, width=320, height=240) if quick else SynthConfig()
    cap_dir = root / f"synth-{cfg.frames}-{cfg.width}"
    if not (cap_dir / "video.mp4").exists():
        write_capture(cfg, cap_dir, progress=True)
    cap = Capture.open(cap_dir)
    ds = root / f"synth-ds-{cfg.frames}-{cfg.width}"
    if not (ds / "images").is_dir() or len(list((ds / "images").iterdir())) != cfg.frames:
        shutil.rmtree(ds, ignore_errors=True)
        with av.open(str(cap_dir / "video.mp4")) as c:
            for i, fr in enumerate(c.decode(video=0)):
                atomic.write_image(ds / "images" / f"{frame_name(i)}.png", fr.to_ndarray(format="rgb24"))
    gts = [cv2.imread(str(cap_dir / "gt" / "instance" / f"{fid_of_index(i)}.png"), cv2.IMREAD_GRAYSCALE)
           for i in range(cfg.frames)]
    return ds, gts, list(cap.names), list(cap.keyframes)


def write_keyframes(folder: Path, gts: list[np.ndarray], keys: list[int], names: list[str]) -> None:
    shutil.rmtree(folder, ignore_errors=True)
    for k in keys:
        m = gts[k].copy()
        m[m == 255] = 0  # an occluder is background to the annotator
        atomic.write_image(folder / f"{fid_of_index(k)}.png", m)
    atomic.write_yaml(folder / "mapping.yaml", dict(enumerate(names)))


def score(ds: Path, gts: list[np.ndarray], keys: list[int], n_obj: int) -> tuple[list[float], list[list[tuple]]]:
    """Per object: mean Jaccard over the frames that were not given (both empty counts as 1), and its five worst
    (frame, IoU) pairs: where propagation fails."""
    per: list[list[tuple[int, float]]] = [[] for _ in range(n_obj)]
    for i, gt in enumerate(gts):
        if i in keys:
            continue
        pred = np.load(ds / "masks" / f"{fid_of_index(i)}.npy")
        valid = gt != 255
        for k in range(n_obj):
            p, g = pred[..., k] & valid, (gt == k + 1)
            u = (p | g).sum()
            per[k].append((i, float((p & g).sum() / u) if u else 1.0))
    means = [float(np.mean([v for _, v in x])) if x else float("nan") for x in per]
    worst = [[(i, round(v, 3)) for i, v in sorted(x, key=lambda iv: iv[1])[:5]] for x in per]
    return means, worst


def run_one(data: str, ds: Path, gts, names, keys: list[int], every: int, variant: str, cfg, work: Path) -> dict:
    kdir = work / f"keys-{data}-{every}"
    write_keyframes(kdir, gts, keys, names)
    shutil.rmtree(ds / "masks", ignore_errors=True)
    (ds / "mapping.yaml").unlink(missing_ok=True)
    t0 = time.perf_counter()
    fig = propagate(ds, kdir, config=cfg, preview="none", suggest=3, progress=False)
    wall = time.perf_counter() - t0
    ious, worst = score(ds, gts, keys, len(names))
    conf = fig["confidence_mean"]
    return {"data": data, "variant": variant, "keyframe_every": every, "iou_mean": round(float(np.mean(ious)), 4),
            "iou_worst_object": round(min(ious), 4), "fps": fig["fps"], "cpu_fps": fig["cpu_fps"], "wall_s": round(wall, 2),
            "frames": len(gts), "objects": len(names), "width": int(gts[0].shape[1]), "height": int(gts[0].shape[0]),
            "confidence_mean": round(float(np.mean(list(conf.values()))), 4),
            "suggested": " ".join(fig["suggested_frames"]),
            "per_object": "; ".join(f"{n}={v:.3f}" for n, v in zip(names, ious)),
            "worst_frames": {n: w for n, w in zip(names, worst)}}


def main() -> int:
    def extra(p):
        p.add_argument("--no-synth", action="store_true", help="DAVIS only")
        p.add_argument("--variants", default="", help="comma-separated subset of variants to run (default: all), "
                       "e.g. 'ours' to skip the slow baseline rows while iterating")
    args = bench_args("masks", __doc__.splitlines()[0], extra)
    cv2.setNumThreads(THREADS)
    work = args.out / "_masks_work"
    limit = 20 if args.quick else None
    runs: list[dict] = []
    vs = variants(args.quick)
    if args.variants:
        unknown = set(args.variants.split(",")) - set(vs)
        if unknown:
            raise SystemExit(f"unknown variant(s) {sorted(unknown)}; choose from {sorted(vs)}")
        vs = {k: v for k, v in vs.items() if k in args.variants.split(",")}
    for seq in DAVIS:
        ds, gts, names = davis_dataset(seq, work, limit)
        for every in (0, 10):
            keys = [0] if every == 0 else list(range(0, len(gts), every))
            for vname, cfg in vs.items():
                runs.append(run_one(seq, ds, gts, names, keys, every, vname, cfg, work))
                print(f"  {seq} every={every} {vname}: iou {runs[-1]['iou_mean']:.3f} fps {runs[-1]['fps']:.1f}",
                      file=sys.stderr)
    if not args.no_synth:
        ds, gts, names, keys = synth_dataset(work, args.quick)
        for vname, cfg in vs.items():
            if vname == "ours-full":
                continue  # full-size medium flow on 300 frames of 640x480: too slow for this machine's budget
            runs.append(run_one("synth", ds, gts, names, keys, 60, vname, cfg, work))
            print(f"  synth {vname}: iou {runs[-1]['iou_mean']:.3f} ({runs[-1]['per_object']})", file=sys.stderr)
    targets = {"davis first frame only iou_mean": 0.80, "davis keyframe every 10 iou_mean": 0.92,
               "davis fps at 854x480": 20, "synth keyframes every 60, each moving part": 0.93}
    write_results(args.out, "masks", runs, quick=args.quick, threads=THREADS, targets=targets,
                  note="fps measured on a shared 2-core machine: pessimistic")
    scatter_chart(args.out / "masks.png", runs, "fps", "iou_mean",
                  label=lambda r: f"{r['data']} k={r['keyframe_every']}",
                  lines_by=lambda r: r["variant"], logx=True, xlabel="frames / s (log)", ylabel="IoU (mean)",
                  title="mask propagation: speed vs accuracy")
    print_table(runs, ["data", "variant", "keyframe_every", "iou_mean", "iou_worst_object", "fps", "cpu_fps", "frames",
                       "per_object"],
                title="masks")
    return 0


if __name__ == "__main__":
    sys.exit(main())
