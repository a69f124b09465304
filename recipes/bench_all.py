"""Run every stage's benchmark, gather their JSON, and write DIR/report.md with every chart and table.

    python recipes/bench_all.py --quick --out bench/          # minutes
    python recipes/bench_all.py --out bench/                  # the full figures (an hour or more on 2 cores)
    python recipes/bench_all.py --out bench/ --skip-run       # only rebuild report.md from existing JSON

Each run also redraws the README's speed-against-accuracy charts, docs/charts/<name>.png (`charts.py`), from
DIR/<name>.json, or from the README's measured figures (docs/charts/results.json) for a benchmark with no JSON in DIR.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from benchlib import bench_args
from charts import CHART_DIR, write_charts

HERE = Path(__file__).resolve().parent
BENCHES = ["synth", "poses", "masks", "train", "ground", "model_size", "stress"]
# columns shown per benchmark (others stay in the JSON)
COLUMNS: dict[str, list[str]] = {
    "synth": ["variant", "frames", "size", "wall_s", "fps", "reproj_err"],
    "poses": ["data", "variant", "registered", "total", "rot_err_deg_median", "rot_err_deg_median_rotation_gauge",
              "center_err_pct_median", "wall_s"],
    "masks": ["data", "variant", "keyframe_every", "iou_mean", "fps"],
    "train": ["data", "variant", "minutes", "steps", "psnr", "ssim", "state_mae", "novel_state_psnr", "mask_iou",
              "params", "label_fraction"],
    "ground": ["data", "query", "object", "retrieved_ok", "iou"],
    "model_size": ["data", "variant", "capacity", "params", "psnr", "minutes", "auto"],
    "stress": ["stress", "level", "stage", "metric", "value", "usable", "detected"],
}


def run_bench(name: str, out: Path, quick: bool, timeout_s: float) -> dict[str, Any]:
    script = HERE / f"bench_{name}.py"
    if not script.exists():
        return {"name": name, "status": "missing", "wall_s": 0.0}
    cmd = [sys.executable, str(script), "--out", str(out)] + (["--quick"] if quick else [])
    t0 = time.perf_counter()
    log = out / f"{name}.log"
    with open(log, "w") as fh:
        try:
            rc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, timeout=timeout_s).returncode
        except subprocess.TimeoutExpired:
            rc = "timeout"
    status = "ok" if rc == 0 else f"failed ({rc}, see {log.name})"
    print(f"[bench_all] {name}: {status} in {time.perf_counter() - t0:.0f} s", flush=True)
    return {"name": name, "status": status, "wall_s": round(time.perf_counter() - t0, 1)}


def _cell(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return "" if v is None else str(v).replace("|", "/")


def table(runs: list[dict[str, Any]], columns: list[str]) -> str:
    cols = [c for c in columns if any(c in r for r in runs)] or sorted({k for r in runs for k in r})[:10]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(_cell(r.get(c)) for c in cols) + " |" for r in runs]
    return "\n".join(lines)


def build_report(out: Path, statuses: list[dict[str, Any]]) -> Path:
    parts = ["# Benchmark report", "", f"Generated {time.strftime('%Y-%m-%d %H:%M:%S')} by `recipes/bench_all.py`.", ""]
    if statuses:
        parts += ["| benchmark | status | wall (s) |", "|---|---|---|"]
        parts += [f"| {s['name']} | {s['status']} | {s['wall_s']} |" for s in statuses]
        parts.append("")
    demo = out.parent / "demo_out" / "demo.md"
    for name in BENCHES:
        path = out / f"{name}.json"
        if not path.exists():
            continue
        data = json.loads(path.read_text())
        runs = data.get("runs", [])
        parts += [f"## {name}", ""]
        if name == "stress":
            parts += [f"Silent failures (usable == false and detected == false): **{data.get('silent_failures', '?')}**", ""]
        env = data.get("environment", {})
        if env:
            parts += [f"Environment: {env.get('cpus')} CPUs, load {env.get('load_avg_1m')}, {env.get('platform')}", ""]
        parts += [table(runs, COLUMNS.get(name, [])), ""]
        for png in sorted(out.glob(f"{name}*.png")):
            parts += [f"![{png.stem}]({png.name})", ""]
    if demo.exists():
        parts += ["## demo", "", demo.read_text(), ""]
    path = out / "report.md"
    path.write_text("\n".join(parts))
    return path


def main() -> int:
    args = bench_args("all", __doc__.splitlines()[0], lambda p: (
        p.add_argument("--skip-run", action="store_true", help="only rebuild report.md from existing JSON"),
        p.add_argument("--only", default="", help="comma-separated benchmarks (default all)"),
        p.add_argument("--timeout-min", type=float, default=120.0, help="per-benchmark time limit"),
        p.add_argument("--charts", type=Path, default=CHART_DIR, help=f"folder for the README charts (default "
                       f"{CHART_DIR.relative_to(HERE.parent)})")))
    names = [n for n in BENCHES if not args.only or n in args.only.split(",")]
    statuses = [] if args.skip_run else [run_bench(n, args.out, args.quick, args.timeout_min * 60) for n in names]
    path = build_report(args.out, statuses)
    print(f"report: {path}")
    for chart in write_charts(args.out, args.charts):
        print(f"chart: {chart} ({chart.stat().st_size // 1024} KB)")
    return 0 if all(s["status"] == "ok" for s in statuses) else 1


if __name__ == "__main__":
    raise SystemExit(main())
