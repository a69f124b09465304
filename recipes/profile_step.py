"""Where a training step and a render spend their time, on this machine's device (CUDA when there, else CPU).

    python recipes/profile_step.py DS [--preset gpu] [--steps 60] [--run RUN] [--out profile.json]

Times `--steps` training steps of a fresh model on dataset DS (after half as many to warm up), then profiles a few
with torch.profiler: wall time, the device's busy time and the kernels launched a step (CUDA), and the operators
that cost most. With `--run`, also a render of that run's first frame. What it found on an H200 (docs/scale.md): the
gpu preset at 19 steps/s with the GPU busy 40 % of the time, 1676 kernels a step: launch-bound.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import environment  # noqa: E402
from interreal.atomic import write_json  # noqa: E402
from livescene.config import load_preset  # noqa: E402
from livescene.device import select_device  # noqa: E402
from livescene.render import render_view  # noqa: E402
from livescene.trainer import Trainer, load_run  # noqa: E402


def _sync(device: torch.device) -> Callable[[], None]:
    return torch.cuda.synchronize if device.type == "cuda" else (lambda: None)


def profiled(fn: Callable[[], Any], device: torch.device, rows: int) -> dict[str, Any]:
    """Run fn once under torch.profiler: wall seconds, device-busy seconds, kernels, and the costliest operators."""
    sync = _sync(device)
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with profile(activities=acts) as prof:
        t0 = time.perf_counter()
        fn()
        sync()
        wall = time.perf_counter() - t0
    events = prof.key_averages()
    on_device = [e for e in events if e.device_type.name == "CUDA"]
    key = "self_device_time_total" if device.type == "cuda" else "self_cpu_time_total"
    top = sorted(events, key=lambda e: getattr(e, key), reverse=True)[:rows]
    return {"wall_s": round(wall, 4),
            "device_busy_s": round(sum(e.self_device_time_total for e in on_device) / 1e6, 4) if on_device else None,
            "kernels": sum(e.count for e in on_device) if on_device else None,
            "top": [{"op": e.key[:80], "self_s": round(getattr(e, key) / 1e6, 4), "calls": e.count} for e in top]}


def profile_training(ds: Path, preset: str, steps: int, device: torch.device, rows: int) -> dict[str, Any]:
    sync = _sync(device)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(ds, Path(tmp) / "run", load_preset(preset), device=str(device), show_progress=False)

        def run(n: int) -> float:
            sync()
            t0 = time.perf_counter()
            for _ in range(n):
                trainer.train_step()
            sync()
            return n / (time.perf_counter() - t0)

        run(max(1, steps // 2))  # warm: kernels loaded, allocator settled
        rate = run(steps)
        few = max(2, steps // 6)
        prof = profiled(lambda: run(few), device, rows)
    return {"preset": preset, "steps_per_s": round(rate, 2), "profiled_steps": few, **prof,
            "kernels_per_step": round(prof["kernels"] / few) if prof["kernels"] else None}


def profile_render(run_dir: Path, device: torch.device, rows: int) -> dict[str, Any]:
    run = load_run(run_dir, device=str(device))
    intr, c2w, t = run.views.intrinsics[0], run.views.c2w_gl[0], float(run.views.times[0])
    for _ in range(2):
        render_view(run, c2w, intr, None, time=t)
    return {"size": [intr.w, intr.h], **profiled(lambda: render_view(run, c2w, intr, None, time=t), device, rows)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="example: python recipes/profile_step.py out/ds --preset gpu --run out/run")
    p.add_argument("dataset", type=Path)
    p.add_argument("--preset", default="auto", help="training preset (auto: gpu on CUDA, else cpu)")
    p.add_argument("--steps", type=int, default=60, help="timed training steps (default 60)")
    p.add_argument("--run", type=Path, default=None, help="a trained run to profile a render of")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda")
    p.add_argument("--rows", type=int, default=12, help="operators listed (default 12)")
    p.add_argument("--out", type=Path, default=None, help="write the figures as JSON here")
    args = p.parse_args(argv)
    device = select_device(args.device)
    preset = args.preset if args.preset != "auto" else ("gpu" if device.type == "cuda" else "cpu")
    out: dict[str, Any] = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
                           "torch": torch.__version__, "environment": environment(),
                           "train": profile_training(args.dataset, preset, args.steps, device, args.rows)}
    if args.run is not None:
        out["render"] = profile_render(args.run, device, args.rows)
    for part in ("train", "render"):
        if part in out:
            rec = out[part]
            busy = "" if rec["device_busy_s"] is None else f", device busy {rec['device_busy_s']:.3f} s"
            print(f"{part}: wall {rec['wall_s']:.3f} s{busy}"
                  + (f", {rec['kernels']} kernels" if rec["kernels"] else "")
                  + (f"; {rec['steps_per_s']} steps/s" if part == "train" else ""))
            for row in rec["top"]:
                print(f"  {row['self_s']:8.4f} s  {row['calls']:6d}  {row['op']}")
    if args.out is not None:
        write_json(args.out, out)  # atomic, as every file the project writes
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
