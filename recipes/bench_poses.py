"""Benchmark `interreal frames` + `interreal poses` against ns-process-data's recipe (reproduced with pycolmap).

    python recipes/bench_poses.py --out bench            # fox + synth (300 frames, 640x480), ~20-30 min on 2 cores
    python recipes/bench_poses.py --quick --out bench    # synth 60 frames, no fox baseline: a few minutes

Records (DIR/poses.json, {"runs": [...]}): data, variant, registered, total, rot_err_deg_median,
center_err_pct_median (after a similarity alignment of camera centres, % of the reference path's bbox diagonal),
rot_err_deg_median_rotation_gauge (the rotation part of that alignment fitted to the rotations instead, as
rotation-averaging benchmarks do: the centre fit tilts every camera by what centre noise turns the path),
gauge_gap_deg (the angle between the two fits: on the simulator's narrow path, sub-millimetre bends of the centres
swing the centre fit by up to 0.07 deg about the path's long axis), wall_s (frames + poses), plus step times. Variants:
- ours-masks / ours-nomasks: `extract_frames` + `estimate_poses` with defaults (synth: with and without the truth
  object masks as DS/sfm_masks); fox has no moving parts, so only `ours`. ours-masks-fine (>= 150 frames): SIFT's
  upsampled octave on every frame instead of every 3rd (the default for long captures), all frames mapped at once
  (the default maps every 3rd first, its tracks extended afterwards): the speed/accuracy trade.
- baseline: ns-process-data's recipe: frames at full size picked uniformly (all of them here), OPENCV camera, SIFT at
  COLMAP defaults, sequential matching (overlap 10, quadratic, no loop detection), incremental mapping with
  ba_global_function_tolerance=1e-6, sparse/0 taken as is, then a principal-point bundle adjustment
  (ns `refine_intrinsics`), no masks.
fox's reference poses come with the data (COLMAP on the full-size photos), so its error is a disagreement, not an error.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from interreal import atomic
from interreal.conventions import frame_id, frame_index, opencv_to_opengl
from interreal.dataset import load_dataset, load_transforms
from interreal.frames import extract_frames
from interreal.paths import require_shared
from interreal.scoring import compare_poses
from interreal.sfm import (
    KEY_STRIDE_MIN,
    SfMConfig,
    estimate_poses,
    rec_poses,
    refine_intrinsics,
)


# ----------------------------------------------------------------------------------------------------------------
# data
# ----------------------------------------------------------------------------------------------------------------
def synth_capture(out: Path, frames: int, size: tuple[int, int], seed: int = 0) -> Path:
    """A simulated capture (video.mp4, gt/cameras.json, gt/instance/, annotations/)."""
    from interreal.synth import SynthConfig, write_capture

    write_capture(SynthConfig(frames=frames, width=size[0], height=size[1], seed=seed), out, progress=False)
    return out


def gt_poses(capture: Path) -> dict[int, np.ndarray]:
    meta = json.loads((capture / "gt" / "cameras.json").read_text())
    return {int(f["index"]): np.asarray(f["transform_matrix"], dtype=np.float64) for f in meta["frames"]}


def write_truth_sfm_masks(capture: Path, ds: Path) -> None:
    """DS/sfm_masks/<image>.png from the simulator's instance maps: 255 = static scene, 0 = object or occluder."""
    import cv2

    for img in sorted((ds / "images").glob("*.png")):
        fid = frame_id(img)
        inst = cv2.imread(str(capture / "gt" / "instance" / f"{fid}.png"), cv2.IMREAD_UNCHANGED)
        h, w = cv2.imread(str(img), cv2.IMREAD_REDUCED_GRAYSCALE_2).shape[:2]
        use = ((inst == 0).astype(np.uint8) * 255)
        if use.shape != (h * 2, w * 2):
            use = cv2.resize(use, (w * 2, h * 2), interpolation=cv2.INTER_NEAREST)
        atomic.write_image(ds / "sfm_masks" / f"{img.name}.png", use)


# ----------------------------------------------------------------------------------------------------------------
# runs
# ----------------------------------------------------------------------------------------------------------------
def run_ours(source: Path, ds: Path, masks_from: Path | None = None, sfm: dict | None = None,
             **frames_kw) -> tuple[dict, float, dict]:
    t0 = time.perf_counter()
    extract_frames(source, ds, **frames_kw)
    t_frames = time.perf_counter() - t0
    if masks_from is not None:
        write_truth_sfm_masks(masks_from, ds)
    fig = estimate_poses(ds, use_masks=masks_from is not None, **(sfm or {}))
    wall = time.perf_counter() - t0
    d = load_dataset(ds)
    est = {f.index: f.c2w for f in d.frames}
    return est, wall, {"images": len(list((ds / "images").glob("*.png"))), "frames_s": round(t_frames, 2), **{f"{k}_s": v for k, v in (fig.get("steps") or {}).items()},
                       "reproj_px": fig.get("mean_reproj_error_px")}


def run_baseline(source: Path, work: Path, long_side: int | None = None) -> tuple[dict, float, dict]:
    """ns-process-data's recipe with pycolmap (see the module docstring)."""
    import pycolmap as pc

    pc.logging.minloglevel = 2
    t0 = time.perf_counter()
    extract_frames(source, work, long_side=long_side or 100_000, report=False, every=1)
    t_frames = time.perf_counter() - t0
    names = sorted(p.name for p in (work / "images").glob("*.png"))
    db = work / "baseline.db"
    steps = {}
    t = time.perf_counter()
    pc.extract_features(str(db), str(work / "images"), image_names=names, camera_mode=pc.CameraMode.SINGLE,
                        reader_options=pc.ImageReaderOptions(camera_model="OPENCV"),
                        extraction_options=pc.FeatureExtractionOptions(num_threads=-1), device=pc.Device.cpu)
    steps["features_s"] = round(time.perf_counter() - t, 2)
    t = time.perf_counter()
    pc.match_sequential(str(db), pairing_options=pc.SequentialPairingOptions(overlap=10, quadratic_overlap=True,
                                                                             loop_detection=False),
                        device=pc.Device.cpu)
    steps["match_s"] = round(time.perf_counter() - t, 2)
    t = time.perf_counter()
    out = work / "sparse"
    out.mkdir(parents=True, exist_ok=True)
    opt = pc.IncrementalPipelineOptions(num_threads=-1, ba_global_function_tolerance=1e-6)
    recs = pc.incremental_mapping(str(db), str(work / "images"), str(out), options=opt)
    steps["map_s"] = round(time.perf_counter() - t, 2)
    est: dict[int, np.ndarray] = {}
    if 0 in recs:
        rec = recs[0]
        t = time.perf_counter()
        refine_intrinsics(pc, rec, SfMConfig(ba_loss="trivial"), "refine")  # ns: refine_intrinsics=True
        steps["refine_s"] = round(time.perf_counter() - t, 2)
        rnames, c2w, _ = rec_poses(rec)
        for n, m in zip(rnames, opencv_to_opengl(c2w)):
            est[frame_index(n)] = m
        steps["reproj_px"] = rec.compute_mean_reprojection_error()
        steps["models"] = sorted((r.num_reg_images() for r in recs.values()), reverse=True)
    steps["frames_s"] = round(t_frames, 2)
    steps["images"] = len(names)
    return est, time.perf_counter() - t0, steps


def record(data: str, variant: str, est: dict[int, np.ndarray], ref: dict[int, np.ndarray], total: int,
           wall: float, extra: dict) -> dict:
    common = sorted(set(est) & set(ref))
    total = int(extra.pop("images", total))  # frames given to SfM
    rec = {"data": data, "variant": variant, "registered": len(est), "total": total, "source_frames": len(ref),
           "wall_s": round(wall, 2)}
    if len(common) >= 3:
        err = compare_poses(np.stack([est[i] for i in common]), np.stack([ref[i] for i in common]))
        rec.update({k: round(v, 5) for k, v in err.items()})
    else:
        rec.update(rot_err_deg_median=float("nan"), center_err_pct_median=float("nan"))
    rec.update(extra)
    print(f"  {data:6s} {variant:13s} {rec['registered']:4d}/{total:<4d} rot {rec['rot_err_deg_median']:.4f} deg  "
          f"centre {rec['center_err_pct_median']:.4f} %  wall {rec['wall_s']:.1f} s", flush=True)
    return rec


def bench_fox(work: Path, baseline: bool) -> list[dict]:
    fox = require_shared("fox")
    _, ref_frames, _, _ = load_transforms(fox)
    ref_sorted = sorted(ref_frames, key=lambda f: f.file_path)
    ref = {i: f.c2w for i, f in enumerate(ref_sorted)}
    runs = []
    est, wall, extra = run_ours(fox / "images", work / "fox_ours")
    runs.append(record("fox", "ours", est, ref, len(ref), wall, extra))
    if baseline:
        est, wall, extra = run_baseline(fox / "images", work / "fox_baseline")
        runs.append(record("fox", "baseline", est, ref, len(ref), wall, extra))
    return runs


def bench_synth(work: Path, frames: int, baseline: bool) -> list[dict]:
    cap = work / "synth_capture"
    if not (cap / "gt" / "cameras.json").exists():
        t = time.perf_counter()
        synth_capture(cap, frames, (640, 480))
        print(f"  synth capture: {frames} frames rendered in {time.perf_counter() - t:.0f} s", flush=True)
    ref = gt_poses(cap)
    runs = []
    variants = [("ours-masks", cap, {}), ("ours-nomasks", None, {})]
    if frames >= KEY_STRIDE_MIN:  # the default gives SIFT's upsampled octave to every 3rd frame; this one to all
        variants.append(("ours-masks-fine", cap, {"fine_octave_stride": 1, "key_stride": 1}))
    for variant, masks, sfm in variants:
        est, wall, extra = run_ours(cap / "video.mp4", work / f"synth_{variant}", masks_from=masks, sfm=sfm,
                                    target=frames)
        runs.append(record("synth", variant, est, ref, len(ref), wall, extra))
    if baseline:
        est, wall, extra = run_baseline(cap / "video.mp4", work / "synth_baseline")
        runs.append(record("synth", "baseline", est, ref, len(ref), wall, extra))
    return runs


def plot(runs: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for r in runs:
        x, y = r["wall_s"], max(r["rot_err_deg_median"], 1e-4)
        mk = "o" if r["data"] == "fox" else "s"
        ax.scatter([x], [y], marker=mk, s=50, color="tab:red" if r["variant"].startswith("baseline") else "tab:blue")
        ax.annotate(f"{r['data']}/{r['variant']} ({r['registered']}/{r['total']})", (x, y), fontsize=7,
                    xytext=(4, 4), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time, frames + poses [s] (2 shared CPU cores)")
    ax.set_ylabel("median rotation error [deg]")
    ax.set_title("interreal poses vs ns-process-data recipe")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    buf = path.with_suffix(".tmp.png")
    fig.savefig(buf, dpi=120)
    plt.close(fig)
    buf.replace(path)


def ratios(runs: list[dict]) -> list[dict]:
    out = []
    for data in sorted({r["data"] for r in runs}):
        base = next((r for r in runs if r["data"] == data and r["variant"] == "baseline"), None)
        if base is None:
            continue
        for r in runs:
            if r["data"] == data and r["variant"] != "baseline":
                out.append({"data": data, "variant": r["variant"], "speedup": round(base["wall_s"] / r["wall_s"], 2),
                            "rot_err_ratio": round(r["rot_err_deg_median"] / max(base["rot_err_deg_median"], 1e-9), 3),
                            "center_err_ratio": round(r["center_err_pct_median"]
                                                      / max(base["center_err_pct_median"], 1e-9), 3)})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("bench"))
    ap.add_argument("--quick", action="store_true", help="synth with 60 frames, no fox baseline")
    ap.add_argument("--frames", type=int, help="synth frames (default 300, quick 60)")
    ap.add_argument("--only", choices=("fox", "synth"), help="run one data set")
    ap.add_argument("--no-baseline", action="store_true",
                    help="skip the baseline runs (its code is fixed: merge an earlier run's records with --merge)")
    ap.add_argument("--work", type=Path, help="keep the work folder here (default: a temp folder, removed)")
    ap.add_argument("--merge", type=Path, nargs="+", help="combine poses.json files of separate runs (e.g. --only fox "
                                                          "and --only synth on a busy machine) into --out")
    args = ap.parse_args(argv)
    if args.merge:
        parts = [json.loads(p.read_text()) for p in args.merge]
        runs = [r for part in parts for r in part["runs"]]
        return report(args.out, runs, {"merged_from": [str(p) for p in args.merge],
                                       "synth_frames": [part.get("synth_frames") for part in parts],
                                       "quick": [part.get("quick") for part in parts]})
    frames = args.frames or (60 if args.quick else 300)
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_poses_"))
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    runs: list[dict] = []
    try:
        if args.only in (None, "fox"):
            runs += bench_fox(work, baseline=not (args.quick or args.no_baseline))
        if args.only in (None, "synth"):
            runs += bench_synth(work, frames, baseline=not args.no_baseline)
    finally:
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    return report(args.out, runs, {"quick": args.quick, "synth_frames": frames,
                                   "wall_s": round(time.perf_counter() - t0, 1)})


def report(out: Path, runs: list[dict], meta: dict) -> int:
    """Write DIR/poses.json and DIR/poses.png, print the table and the speed / error ratios."""
    out.mkdir(parents=True, exist_ok=True)
    result = {"runs": runs, "ratios": ratios(runs), **meta,
              "note": "2 CPU cores shared with other jobs: timings are pessimistic and noisy"}
    atomic.write_json(out / "poses.json", result)
    plot(runs, out / "poses.png")
    print(f"\n{'data':6s} {'variant':16s} {'reg':>9s} {'rot_med_deg':>11s} {'rot_med_rg':>10s} {'gap_deg':>7s} "
          f"{'ctr_med_%':>9s} {'wall_s':>7s}")
    for r in runs:
        print(f"{r['data']:6s} {r['variant']:16s} {r['registered']:4d}/{r['total']:<4d} "
              f"{r['rot_err_deg_median']:11.4f} {r.get('rot_err_deg_median_rotation_gauge', float('nan')):10.4f} "
              f"{r.get('gauge_gap_deg', float('nan')):7.4f} "
              f"{r['center_err_pct_median']:9.4f} {r['wall_s']:7.1f}")
    for q in result["ratios"]:
        print(f"{q['data']}/{q['variant']}: {q['speedup']}x faster than baseline, rotation error x{q['rot_err_ratio']}, "
              f"centre error x{q['center_err_ratio']}")
    print(f"-> {out / 'poses.json'}, {out / 'poses.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
