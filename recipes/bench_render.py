"""Benchmark rendering a trained run: seconds per frame at 160x120, 320x240 and 640x480 for the exact renderer
(`render_view(fast=False)`: every sample of every level of every pixel read) and the fast one (`livescene.adaptive`
over `livescene.march`: a coarse lattice of pixels traced and flat regions interpolated, occupancy grid, early
termination), on the same held-out cameras back to back in one process, and the PSNR between the two renders of
each frame (and of each against the recorded frame, where the dataset has one).

    python recipes/bench_render.py RUN --out bench            # 2 held-out views per size, 3 tolerances at 320x240
    python recipes/bench_render.py RUN --quick --out bench    # 1 view at 160x120 and 320x240
    python recipes/bench_render.py RUN --sizes 320x240 --threads 1 --out bench   # one size, one thread

Writes bench/render.json ({"runs": [...], "summary": {...}}) and bench/render.png (seconds per frame against PSNR
to the exact render, per size and interpolation tolerance), prints a table. The grid is the run's own (saved with its checkpoint)
or is built and cached next to it on first use (its build time is reported). On a shared machine compare the
ratios, not the seconds: both renderers run interleaved, frame by frame, the load average is recorded, and each
render's CPU seconds (`cpu_s`, `cpu_speedup`: with one thread the work itself, whatever else runs) beside its wall
time.
"""

from __future__ import annotations

import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from benchlib import bench_args, print_table, write_results

SIZES = {"160x120": (160, 120), "320x240": (320, 240), "640x480": (640, 480)}
TOLERANCES = (0.0, None, 0.1)  # the fast renderer's interpolation tolerance swept at 320x240: every pixel traced,
# the default (`adaptive.TOLERANCE`), a looser one (the viewer drags at `viewer.session.DRAG_TOLERANCE`)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(max(float(np.mean((a - b) ** 2)), 1e-12)))


def reference_image(run, i: int, w: int, h: int) -> np.ndarray | None:
    """Frame i of the dataset, area-resized to w x h, in [0, 1]; None when it cannot be read."""
    import cv2

    from livescene.data import load_frame

    try:
        rgb, _ = load_frame(run.views, i)
    except Exception:  # noqa: BLE001 - no recorded frame: no PSNR against it
        return None
    return cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0


def bench_frame(run, i: int, size: str, tolerances: tuple[float | None, ...]) -> list[dict]:
    """The exact render and the fast ones of frame i's camera at `size`, back to back."""
    from livescene.adaptive import TOLERANCE
    from livescene.render import render_view

    views = run.views
    w, h = SIZES[size]
    intr = views.intrinsics[i].scaled(w, h)
    kw = {"time": float(views.times[i])}
    fid = views.dataset.frames[i].fid
    ref = reference_image(run, i, w, h)
    load = os.getloadavg()[0]
    c0 = time.process_time()  # CPU seconds of this process: on a shared machine steadier than the wall clock
    exact = render_view(run, views.c2w_gl[i], intr, None, fast=False, **kw)
    exact_cpu = time.process_time() - c0
    base = {"frame": fid, "size": size, "load_avg": round(load, 2)}
    rows = [{**base, "renderer": "exact", "seconds": round(exact["seconds"], 3), "cpu_s": round(exact_cpu, 3),
             "rays_per_s": round(exact["rays"] / exact["seconds"]), "speedup": 1.0, "cpu_speedup": 1.0,
             "psnr_vs_exact": None,
             "psnr_vs_frame": None if ref is None else round(psnr(exact["rgb"], ref), 3),
             "reads_per_pixel": sum(run.config.sampler.proposal_samples) + run.config.sampler.samples,
             "traced": 1.0}]
    for tol in tolerances:
        tol = TOLERANCE if tol is None else tol
        c0 = time.process_time()
        fast = render_view(run, views.c2w_gl[i], intr, None, tolerance=tol, **kw)
        cpu = time.process_time() - c0
        frame_psnr = None if ref is None else psnr(fast["rgb"], ref)
        rows.append({**base, "renderer": f"fast {tol:g}", "tolerance": tol,
                     "seconds": round(fast["seconds"], 3), "rays_per_s": round(fast["rays"] / fast["seconds"]),
                     "speedup": round(exact["seconds"] / fast["seconds"], 2), "cpu_s": round(cpu, 3),
                     "cpu_speedup": round(exact_cpu / cpu, 2),
                     "psnr_vs_exact": round(psnr(fast["rgb"], exact["rgb"]), 2),
                     "psnr_vs_frame": None if frame_psnr is None else round(frame_psnr, 3),
                     "frame_psnr_loss": None if ref is None else round(rows[0]["psnr_vs_frame"] - frame_psnr, 3),
                     "probs_l1": round(float(np.abs(fast["probs"] - exact["probs"]).mean()), 5),
                     "reads_per_pixel": round(fast["march"]["evaluated"] / fast["rays"], 2),
                     "traced": round(fast["traced"] / fast["rays"], 3)})
    return rows


def summarise(runs: list[dict]) -> dict:
    """Per size and renderer: median seconds and speedup, worst and mean PSNR to the exact render."""
    out: dict[str, dict] = {}
    for r in runs:
        key = f"{r['size']} {r['renderer']}"
        out.setdefault(key, {"seconds": [], "speedup": [], "cpu_speedup": [], "psnr_vs_exact": [],
                             "frame_psnr_loss": []})
        for k in out[key]:
            if r.get(k) is not None:
                out[key][k].append(r[k])
    summary = {}
    for key, vals in out.items():
        summary[key] = {"seconds_per_frame": statistics.median(vals["seconds"]),
                        "speedup": statistics.median(vals["speedup"]) if vals["speedup"] else None,
                        "cpu_speedup": statistics.median(vals["cpu_speedup"]) if vals["cpu_speedup"] else None,
                        "psnr_vs_exact_min": min(vals["psnr_vs_exact"]) if vals["psnr_vs_exact"] else None,
                        "psnr_vs_exact_mean": statistics.mean(vals["psnr_vs_exact"]) if vals["psnr_vs_exact"] else None,
                        "frame_psnr_loss_mean": statistics.mean(vals["frame_psnr_loss"])
                        if vals["frame_psnr_loss"] else None}
    return summary


def plot(runs: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.5), dpi=110)
    for size in SIZES:
        rs = [r for r in runs if r["size"] == size]
        if not rs:
            continue
        ex = [r["seconds"] for r in rs if r["renderer"] == "exact"]
        fa = [r for r in rs if r["renderer"] != "exact"]
        line = a.scatter([r["seconds"] for r in fa], [r["psnr_vs_exact"] for r in fa], label=f"fast, {size}")
        for r in fa:
            a.annotate(f"{r['tolerance']:g}", (r["seconds"], r["psnr_vs_exact"]), fontsize=7, xytext=(3, 3),
                       textcoords="offset points")
        a.axvline(statistics.median(ex), ls="--", color=line.get_facecolor()[0], alpha=0.7,
                  label=f"exact, {size} (median)")
        if any(r.get("psnr_vs_frame") is not None for r in rs):
            b.scatter([r["seconds"] for r in rs], [r["psnr_vs_frame"] for r in rs], label=size)
            for r in rs:
                b.annotate(r["renderer"].replace("fast ", ""), (r["seconds"], r["psnr_vs_frame"]), fontsize=6,
                           xytext=(3, 3), textcoords="offset points")
    for ax, ylabel, title in ((a, "PSNR of the fast render to the exact one (dB)",
                               "fast renderer (labels: interpolation tolerance)"),
                              (b, "PSNR to the recorded frame (dB)", "both renderers against the recorded frame")):
        ax.set_xscale("log")
        ax.set_xlabel("seconds per frame")
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main() -> int:
    args = bench_args("render", __doc__.splitlines()[0], extra=lambda p: (
        p.add_argument("run", type=Path, help="run folder of `livescene train`"),
        p.add_argument("--frames", type=int, default=0, help="held-out views per size (default 2, --quick 1)"),
        p.add_argument("--threads", type=int, default=0, help="torch threads (0 = as the CLI chooses)"),
        p.add_argument("--sizes", default="", help=f"comma-separated sizes of {', '.join(SIZES)} (default: all; "
                                                   f"--quick: the first two)"),
        p.add_argument("--device", default="auto")))
    import torch

    from livescene.device import configure_threads
    from livescene.evaluate import pick_frames
    from livescene.occupancy import grid_for
    from livescene.trainer import load_run

    threads = configure_threads(args.threads)
    run = load_run(args.run, device=args.device)
    t0 = time.perf_counter()
    had_grid = run.occupancy is not None
    grid = grid_for(run)
    grid_s = time.perf_counter() - t0
    sizes = [x.strip() for x in args.sizes.split(",") if x.strip()] or (["160x120", "320x240"] if args.quick
                                                                         else list(SIZES))
    unknown = [x for x in sizes if x not in SIZES]
    if unknown:
        raise SystemExit(f"--sizes: unknown size {unknown[0]!r}; choose from {', '.join(SIZES)}")
    n = args.frames or (1 if args.quick else 2)
    pool = run.views.held_out or run.views.train
    frames = pick_frames(pool, n)
    runs = []
    with torch.inference_mode():
        for size in sizes:
            tolerances = TOLERANCES if size == "320x240" else (None,)
            for i in frames:
                rows = bench_frame(run, i, size, tolerances)
                runs += rows
                for r in rows:
                    print(f"{r['size']:>8} {r['frame']:>6} {r['renderer']:<12} {r['seconds']:>8.3f} s"
                          + f" (cpu {r['cpu_s']:.2f} s)"
                          + (f"  x{r['speedup']:<6} cpu x{r['cpu_speedup']:<6} PSNR to exact {r['psnr_vs_exact']:.1f} dB" if r['psnr_vs_exact']
                             else "") + f"  load {r['load_avg']}", flush=True)
    summary = summarise(runs)
    meta = {"run": str(args.run), "step": run.step, "threads": threads, "device": str(run.device),
            "grid": {"from_checkpoint": had_grid, "seconds_to_load_or_build": round(grid_s, 3),
                     "shape": list(grid.shape), "occupied_default": round(grid.occupied_fraction(), 4),
                     "info": grid.info},
            "summary": summary}
    path = write_results(args.out, "render", runs, **meta)
    plot(runs, args.out / "render.png")
    print_table(runs, ["size", "frame", "renderer", "seconds", "speedup", "cpu_s", "cpu_speedup", "psnr_vs_exact",
                       "psnr_vs_frame",
                       "traced", "reads_per_pixel", "load_avg"], title="render: exact vs fast")
    print(f"grid: {'from the checkpoint' if had_grid else 'built'} in {grid_s:.1f} s, shape {grid.shape}, "
          f"{grid.occupied_fraction():.1%} of cells occupied")
    print(f"wrote {path} and {args.out / 'render.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
