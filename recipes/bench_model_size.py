"""Model size against scene size: held-out PSNR against parameter count for small / medium / large simulated rooms.

Why: the model should be no bigger than the scene needs (`livescene.config.resolve_sizes` picks plane resolutions
from image size, focal length, scene extent and frame count). This sweep checks that the auto size (capacity x1)
sits at the knee of PSNR against parameters, for three room sizes.

For each room (`interreal synth --room-scale` 0.7 / 1.0 / 1.6; furniture keeps its size, the room and the camera's
distance grow): simulate a capture, make its truth dataset at 320x240, train the cpu preset at capacities
x0.5, x1, x2 (`model.capacity` multiplies the auto plane resolutions; x1 = auto) for the same number of steps
(`--budget minutes` for equal wall time instead), and evaluate held-out PSNR (every 8th frame, never trained on).
The knee of a curve is its smallest model within KNEE_DB of its best PSNR. A run that diverges is recorded
(no PSNR, `error`) and left out of the knee.

Records (DIR/model_size.json "runs"): data, variant, room_scale, capacity, auto, params, resolution, psnr, ssim,
steps, minutes, extent, distance. Chart: DIR/model_size.png (PSNR against parameters, log x, one line per room,
the auto size marked). Re-running with the same settings reuses finished runs (`--fresh` to redo them).
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import bench_args, print_table, scatter_chart, write_results  # noqa: E402

SCENES = {"small": 0.7, "medium": 1.0, "large": 1.6}  # room_scale of each simulated room
CAPACITIES = [0.5, 1.0, 2.0]  # around the auto size; 1000-step budgets favour small models, so few but long runs
QUICK_CAPACITIES = [0.25, 1.0, 2.0]
KNEE_DB = 0.5
EVAL_SCALE = 0.5  # held-out frames rendered at 160x120 (the 320x240 truth downscaled): rendering dominates on CPU
COLUMNS = ["data", "variant", "room_scale", "params", "resolution", "steps", "minutes", "psnr", "ssim", "auto"]


def extra_args(p) -> None:
    p.add_argument("--scenes", default=",".join(SCENES), help="comma list of rooms to run (default all three)")
    p.add_argument("--capacities", default=None,
                   help=f"comma list of capacities (default {CAPACITIES}; --quick {QUICK_CAPACITIES})")
    p.add_argument("--budget", choices=("steps", "minutes"), default="steps",
                   help="equal training steps (default: fair on a shared machine) or equal wall time per run")
    p.add_argument("--steps", type=int, default=None, help="steps per run (default 2500, --quick 150)")
    p.add_argument("--minutes", type=float, default=None, help="minutes per run with --budget minutes (default 4, --quick 0.5)")
    p.add_argument("--frames", type=int, default=None, help="frames per capture (default 150 at 640x480, --quick 48 at 320x240)")
    p.add_argument("--eval-frames", type=int, default=None, help="held-out frames evaluated, evenly spread (default 8; 0 = all)")
    p.add_argument("--threads", type=int, default=0, help="CPU threads (0 = auto: 1 on a busy machine)")
    p.add_argument("--device", default="auto")
    p.add_argument("--fresh", action="store_true", help="redo runs already in DIR/model_size.json")
    p.epilog = ("examples:\n  python recipes/bench_model_size.py --quick --out bench/\n"
                "  python recipes/bench_model_size.py --out bench/ --steps 3000\n"
                "  python recipes/bench_model_size.py --out bench/ --budget minutes --minutes 5 --scenes small,large")


def make_room(out: Path, name: str, room_scale: float, quick: bool, frames: int) -> tuple[Path, Path]:
    """(capture, truth dataset at 320x240) of one room; reused when already there."""
    from interreal.synth import SynthConfig, truth_dataset, write_capture

    size = (320, 240) if quick else (640, 480)
    n = frames
    cap, ds = out / "data" / f"cap_{name}", out / "data" / f"ds_{name}"
    cfg = SynthConfig(frames=n, width=size[0], height=size[1], seed=0, room_scale=room_scale,
                      keyframe_every=max(1, min(60, n // 4)))
    meta = cap / "gt" / "meta.json"
    if meta.exists() and json.loads(meta.read_text())["config"] != cfg.to_dict():
        shutil.rmtree(cap)
        shutil.rmtree(ds, ignore_errors=True)
    if not meta.exists():
        print(f"simulating the {name} room (room_scale {room_scale:g}, {n} frames at {size[0]}x{size[1]}) ...", flush=True)
        write_capture(cfg, cap, progress=False)
    if not (ds / "transforms.json").exists():
        truth_dataset(cap, ds, size=(320, 240))
    return cap, ds


def scene_figures(ds: Path, box: list[float]) -> dict[str, float]:
    """The scene figures the auto sizes follow (extent of the box, median camera distance)."""
    from livescene.config import load_preset
    from livescene.data import load_views

    cfg = load_preset("cpu")
    cfg.scene_box = box
    info = load_views(ds, cfg).scene_info()
    return {"extent": round(info.extent, 3), "distance": round(info.distance, 3)}


def train_and_eval(ds: Path, cap: Path, run_dir: Path, capacity: float, box: list[float], args) -> dict[str, Any]:
    from livescene.config import load_preset
    from interreal.synth.evaltruth import CaptureTruth
    from livescene.evaluate import evaluate
    from livescene.trainer import load_run, train

    if run_dir.exists():
        shutil.rmtree(run_dir)
    cfg = load_preset("cpu")
    cfg.scene_box = box
    cfg.model.capacity = capacity
    cfg.steps = args.steps if args.budget == "steps" else 1_000_000
    cfg.eval_every = 0  # the held-out evaluation below is the figure; no periodic renders inside the budget
    minutes = args.minutes if args.budget == "minutes" else 0.0
    summary = train(ds, run_dir, cfg, device=args.device, max_minutes=minutes, show_progress=False)
    run = load_run(run_dir, device=args.device)
    t0 = time.perf_counter()
    res = evaluate(run, CaptureTruth(cap, run.views), max_frames=args.eval_frames, scale=EVAL_SCALE, novel=0,
                   progress=False)
    m = run.config.model
    return {"steps": summary["steps"], "minutes": round(summary["elapsed_s"] / 60, 2),
            "eval_minutes": round((time.perf_counter() - t0) / 60, 2), "params": int(res["params"]),
            "resolution": m.resolution, "scales": list(m.scales), "prob_resolution": m.prob_resolution,
            "proposal_resolutions": list(m.proposal_resolutions), "psnr": res["psnr"], "ssim": res["ssim"],
            "mask_iou": res.get("mask_iou"), "eval_frames": res["held_out_frames"], "eval_scale": EVAL_SCALE}


def knees(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per room: best PSNR, the knee (smallest model within KNEE_DB of the best) and where the auto size sits."""
    out = []
    for data in dict.fromkeys(r["data"] for r in runs):
        rs = sorted([r for r in runs if r["data"] == data and r.get("psnr") is not None], key=lambda r: r["params"])
        if not rs:
            continue
        best = max(rs, key=lambda r: r["psnr"])
        knee = next(r for r in rs if r["psnr"] >= best["psnr"] - KNEE_DB)
        auto = next((r for r in rs if r["auto"]), None)
        row = {"data": data, "best_capacity": best["capacity"], "best_psnr": round(best["psnr"], 2),
               "knee_capacity": knee["capacity"], "knee_params": knee["params"], "knee_psnr": round(knee["psnr"], 2)}
        if auto is not None:
            row.update(auto_params=auto["params"], auto_psnr=round(auto["psnr"], 2),
                       auto_gap_db=round(best["psnr"] - auto["psnr"], 2),
                       auto_over_knee=round(auto["params"] / knee["params"], 2), auto_at_knee=auto is knee)
        out.append(row)
    return out


def main() -> int:
    args = bench_args("model_size", __doc__.splitlines()[0], extra_args)
    from livescene.device import configure_threads, reexec_with_jemalloc, select_device

    reexec_with_jemalloc()
    from livescene.errors import DivergenceError

    threads = configure_threads(args.threads)
    args.device = str(select_device(args.device).type)
    quick = args.quick
    args.steps = args.steps or (150 if quick else 2500)
    args.minutes = args.minutes or (0.5 if quick else 4.0)
    args.eval_frames = 8 if args.eval_frames is None else args.eval_frames
    args.frames = args.frames or (48 if quick else 150)
    caps = [float(c) for c in args.capacities.split(",")] if args.capacities else (QUICK_CAPACITIES if quick else CAPACITIES)
    scenes = [s for s in args.scenes.split(",") if s]
    unknown = sorted(set(scenes) - set(SCENES))
    if unknown:
        raise SystemExit(f"unknown room(s) {unknown}: choose from {', '.join(SCENES)}")
    budget = {"budget": args.budget, "quick": quick, "frames": args.frames, **({"budget_steps": args.steps} if args.budget == "steps"
                                                         else {"budget_minutes": args.minutes})}
    path = args.out / "model_size.json"
    runs: list[dict[str, Any]] = []
    if path.exists() and not args.fresh:  # reuse runs made with the same budget
        runs = [r for r in json.loads(path.read_text()).get("runs", [])
                if all(r.get(k) == v for k, v in budget.items())]
    from bench_train import depth_box  # the scene box from the capture's depth (SfM's point cloud on real data)

    t_all = time.perf_counter()
    for name in scenes:
        cap, ds = make_room(args.out, name, SCENES[name], quick, args.frames)
        box = depth_box(cap)
        figs = scene_figures(ds, box)
        for c in caps:
            if any(r["data"] == name and r["capacity"] == c for r in runs):
                continue
            print(f"[{time.perf_counter() - t_all:6.0f} s] {name} room (x{SCENES[name]:g}), capacity x{c:g} ...",
                  flush=True)
            try:
                rec = train_and_eval(ds, cap, args.out / "runs" / f"{name}_x{c:g}", c, box, args)
            except DivergenceError as exc:  # a finding, not a crash: recorded (no PSNR), the sweep goes on
                print(f"    diverged: {exc}", flush=True)
                rec = {"psnr": None, "error": f"diverged: {exc}"[:300]}
            runs.append({"data": name, "variant": f"capacity x{c:g}", "room_scale": SCENES[name], "capacity": c,
                         "auto": c == 1.0, **figs, **rec, **budget, "box": box})
            runs.sort(key=lambda r: (list(SCENES).index(r["data"]), r["capacity"]))
            summary = knees(runs)
            write_results(args.out, "model_size", runs, knees=summary, knee_db=KNEE_DB, device=args.device,
                          threads=threads)
            chart(args.out / "model_size.png", runs, quick)
    summary = knees(runs)
    print_table(runs, COLUMNS, title=f"model size against room size ({'quick' if quick else 'full'}, {args.device}, "
                                     f"{args.budget}: {args.steps if args.budget == 'steps' else args.minutes})")
    print()
    print_table(summary, ["data", "best_capacity", "best_psnr", "knee_capacity", "knee_params", "auto_params",
                          "auto_psnr", "auto_gap_db", "auto_over_knee", "auto_at_knee"],
                title=f"knee = smallest model within {KNEE_DB} dB of the best")
    for k in summary:
        if "auto_at_knee" in k:
            where = ("at the knee" if k["auto_at_knee"] else
                     f"{'above' if k['auto_over_knee'] > 1 else 'below'} the knee (x{k['knee_capacity']:g} is the knee)")
            print(f"{k['data']:>6}: auto size {k['auto_params']:,} params, {k['auto_psnr']} dB, "
                  f"{k['auto_gap_db']} dB below the best: {where}")
    print(f"-> {path}, {args.out / 'model_size.png'}  ({(time.perf_counter() - t_all) / 60:.1f} min)")
    return 0


def chart(path: Path, runs: list[dict[str, Any]], quick: bool) -> Path:
    knee = {(k["data"], k["knee_capacity"]) for k in knees(runs)}
    return scatter_chart(path, runs, "params", "psnr",
                         label=lambda r: f"x{r['capacity']:g}" + (" knee" if (r["data"], r["capacity"]) in knee else ""),
                         title=f"Held-out PSNR against model size, 3 room sizes{' (quick)' if quick else ''}",
                         logx=True, xlabel="parameters", ylabel="held-out PSNR (dB)",
                         lines_by=lambda r: f"{r['data']} room (x{r['room_scale']:g}, extent {r['extent']:.1f} m)",
                         highlight=lambda r: bool(r.get("auto")), highlight_label="auto size (capacity x1)")


if __name__ == "__main__":
    sys.exit(main())
