"""Benchmark `interreal batch`: captures per hour with 1 and 2 workers on this machine, a corrupt video among them.

    python recipes/bench_batch.py --out bench             # 4 captures (preset small: 60 frames, 320x240) + 1 corrupt
    python recipes/bench_batch.py --quick --out bench     # 2 captures, 24 frames selected each
    python recipes/bench_batch.py --out bench --engine ray  # the Ray engine (pip install '.[scale]')

Each run is `interreal batch CAPTURES --out DIR --workers W` into an empty DIR, in a child process: the CPU-bound stages only
(frames, masks, poses, labels, motions; no training). Records (DIR/batch.json, {"runs": [...]}): engine, workers,
wall_s, ok / failed captures, captures_per_hour (finished captures / wall), cpu_s (this batch's CPU time, all its
processes), max_rss_mb (the largest process), dataset_mb (per capture), other_cpu_s (CPU time the rest of the
machine used meanwhile, from /proc/stat: the contention the figure was measured under), load averages before / after,
the summed stage seconds, and per run whether the corrupt capture failed with its stage's error while every other
capture finished with a complete summary row. `speedup` = captures_per_hour(2 workers) / captures_per_hour(1 worker),
per repeat; the runs alternate 1, 2, 2, 1, ... so a change in the machine's load does not favour one side.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from benchlib import bench_args, print_table, write_results

from interreal import atomic

STAGES = ("frames", "masks", "poses", "labels", "motions", "process")


def machine_busy_s() -> float | None:
    """CPU seconds the whole machine has been busy since boot (/proc/stat), or None without /proc."""
    try:
        fields = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
    except OSError:
        return None
    ticks = [int(v) for v in fields]
    idle = ticks[3] + (ticks[4] if len(ticks) > 4 else 0)
    return (sum(ticks[:8]) - idle) / os.sysconf("SC_CLK_TCK")


def make_captures(root: Path, n: int, preset: str) -> list[Path]:
    """n simulated captures (seeds 0..n-1; reused when already there) and one corrupt video."""
    caps = []
    for seed in range(n):
        cap = root / f"cap{seed}"
        if not (cap / "gt" / "meta.json").exists():
            subprocess.run([sys.executable, "-m", "interreal", "synth", str(cap), "--preset", preset, "--seed",
                            str(seed), "--quiet"], check=True, stdout=subprocess.DEVNULL)
        caps.append(cap)
    broken = root / "broken"
    broken.mkdir(parents=True, exist_ok=True)
    (broken / "video.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 200)  # a cut-off MP4
    return caps + [broken]


def run_batch(caps: list[Path], out: Path, workers: int, engine: str, target: int | None) -> dict[str, Any]:
    if out.exists():  # a fresh output root: `process` would reuse the previous run's finished steps
        shutil.rmtree(out)
    argv = [sys.executable, "-m", "interreal", "batch", *map(str, caps), "--out", str(out), "--workers",
            str(workers), "--engine", engine] + (["--target", str(target)] if target else [])
    load_before = os.getloadavg()[0]
    busy0, cpu0 = machine_busy_s(), resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(argv, capture_output=True, text=True, env={**os.environ, "INTERREAL_NO_LIVE": "1"})
    wall = time.perf_counter() - t0
    busy1, cpu1 = machine_busy_s(), resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    try:
        summary = json.loads((out / "summary.json").read_text())
    except (OSError, ValueError):
        raise SystemExit(f"interreal batch wrote no summary (exit {proc.returncode}):\n{proc.stderr[-2000:]}")
    rows = summary["captures"]
    good = [r for r in rows if r["capture"] != "broken"]
    broken = next(r for r in rows if r["capture"] == "broken")
    complete = all(r["status"] == "ok" and r["registered"] and r["seconds"].get("poses") is not None
                   and r["mask_confidence"] for r in good)
    stage_s = {s: round(sum(r["seconds"].get(s) or 0.0 for r in good), 1) for s in STAGES}
    return {"engine": engine, "workers": workers, "wall_s": round(wall, 1), "ok": summary["ok"],
            "failed": summary["failed"], "captures_per_hour": round(3600.0 * len(good) / wall, 1),
            "cpu_s": round(cpu, 1), "cpu_per_wall": round(cpu / wall, 2),
            "max_rss_mb": round(cpu1.ru_maxrss / 1024.0),  # the largest process so far (Linux: KiB)
            "dataset_mb": round(sum(f.stat().st_size for r in good for f in (out / r["capture"] / "dataset")
                                    .rglob("*") if f.is_file()) / len(good) / 2 ** 20, 1),
            "other_cpu_s": round(busy1 - busy0 - cpu, 1) if busy0 is not None else None,
            "load_before": round(load_before, 2), "load_after": round(os.getloadavg()[0], 2),
            "corrupt_failed_others_finished": bool(broken["status"] == "failed" and broken["error"] and complete),
            "corrupt_error": broken["error"], "exit": proc.returncode, "stage_s": stage_s,
            "registered": {r["capture"]: f"{r['registered']}/{r['frames']}" for r in good}}


def main() -> None:
    args = bench_args("batch", __doc__.split("\n\n")[0], extra=lambda p: (
        p.add_argument("--engine", choices=("local", "ray"), default="local"),
        p.add_argument("--captures", type=int, default=0, help="simulated captures (default 4; --quick 2)"),
        p.add_argument("--preset", default="small", help="interreal synth preset (default small, the smallest)"),
        p.add_argument("--repeats", type=int, default=1, help="pairs of (1-worker, 2-worker) runs (default 1)")))
    n = args.captures or (2 if args.quick else 4)
    target = 24 if args.quick else None
    caps = make_captures(args.out / "batch_captures", n, args.preset)
    print(f"bench_batch: {n} captures (preset {args.preset}) + 1 corrupt, engine {args.engine}; load "
          f"{os.getloadavg()}", flush=True)
    runs = []
    order = []
    for rep in range(args.repeats):
        order += [1, 2] if rep % 2 == 0 else [2, 1]
    for i, workers in enumerate(order):
        run = run_batch(caps, args.out / f"batch_w{workers}_{i}", workers, args.engine, target)
        run["repeat"] = i // 2
        runs.append(run)
        print(f"  workers {workers}: {run['wall_s']} s, {run['captures_per_hour']} captures/hour, cpu "
              f"{run['cpu_per_wall']}x wall, others used {run['other_cpu_s']} CPU s, load {run['load_before']} -> "
              f"{run['load_after']}", flush=True)
    speedups = []
    for rep in range(args.repeats):
        pair = {r["workers"]: r for r in runs if r["repeat"] == rep}
        speedups.append(round(pair[2]["captures_per_hour"] / pair[1]["captures_per_hour"], 2))
    uptime = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    table = print_table(runs, ["engine", "workers", "wall_s", "ok", "failed", "captures_per_hour", "cpu_per_wall",
                               "other_cpu_s", "load_before", "load_after", "corrupt_failed_others_finished"],
                        title=f"interreal batch: {n} captures + 1 corrupt ({os.cpu_count()} CPUs)")
    print(f"speedup 2 vs 1 worker: {speedups}; {uptime}")
    path = write_results(args.out, "batch", runs, speedup=speedups, captures=n, preset=args.preset,
                         engine=args.engine, uptime=uptime)
    atomic.write_text(args.out / "batch.md", table + f"\n\nspeedup 2 vs 1 worker: {speedups}\n{uptime}\n")
    print(f"-> {path}")


if __name__ == "__main__":
    main()
