"""Speed-against-accuracy charts for the README (`docs/charts/*.png`), drawn from the benchmarks' JSON.

`python recipes/bench_all.py --skip-run --out bench/` calls `write_charts`: each chart reads `bench/<name>.json`
when that benchmark has run, else the README's measured figures in `docs/charts/results.json` (same schema), and
says which in its footnote. PNGs are palette-quantised to stay small (< 100 KB) for the repository.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable

REPO = Path(__file__).resolve().parent.parent
CHART_DIR = REPO / "docs" / "charts"
FALLBACK = CHART_DIR / "results.json"
MAX_BYTES = 100_000


def chart_source(bench_dir: Path, name: str) -> tuple[list[dict[str, Any]], str]:
    """(runs, where from): the benchmark's own JSON in `bench_dir`, else the README figures."""
    path = Path(bench_dir) / f"{name}.json"
    if path.exists():
        data = json.loads(path.read_text())
        return data.get("runs", []), f"{path.name} ({data.get('environment', {}).get('cpus', '?')} CPUs)"
    fallback = json.loads(FALLBACK.read_text()).get(name, {}) if FALLBACK.exists() else {}
    return fallback.get("runs", []), f"README figures: {fallback.get('source', 'none')}"


def _figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.2, 3.3), dpi=90)
    return plt, fig, ax


def _finish(plt, fig, ax, path: Path, title: str, source: str, xlabel: str, ylabel: str, *, log: str = "x",
            legend: str = "best") -> Path:
    """Log axes, axis labels and legend, then `_save`: the one ending every chart shares."""
    if "x" in log:
        ax.set_xscale("log")
    if "y" in log:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel, fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.legend(fontsize=7, loc=legend)
    return _save(plt, fig, ax, path, title, source)


def _save(plt, fig, ax, path: Path, title: str, source: str) -> Path:
    """Title, footnote with the source, grid; saved as a palette PNG."""
    import io

    from PIL import Image

    from matplotlib.ticker import LogLocator, NullFormatter, ScalarFormatter

    for axis in (ax.xaxis, ax.yaxis):  # plain numbers at 1, 2, 5 x 10^k on log axes, not 2x10^0
        if axis.get_scale() == "log":
            axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            axis.set_major_formatter(ScalarFormatter())
            axis.set_minor_formatter(NullFormatter())
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.tick_params(labelsize=7)
    fig.text(0.01, 0.01, source[:110], fontsize=5.5, color="0.4")
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    img = Image.open(buf).convert("RGB").quantize(colors=64)
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save(path, optimize=True)
    return path


def render_chart(runs: list[dict], source: str, path: Path) -> Path | None:
    """Seconds per frame against PSNR to the recorded frame, exact and fast renderer, per image size."""
    runs = [r for r in runs if r.get("seconds") and r.get("psnr_vs_frame") is not None]
    if not runs:
        return None
    plt, fig, ax = _figure()
    for size in dict.fromkeys(r["size"] for r in runs):
        rs = [r for r in runs if r["size"] == size]
        ax.plot([r["seconds"] for r in rs], [r["psnr_vs_frame"] for r in rs], "o", label=size)
        for k, r in enumerate(rs):  # alternate above / below: settings of one size often land together
            ax.annotate(r["renderer"], (r["seconds"], r["psnr_vs_frame"]), fontsize=6,
                        xytext=(3, 3 if k % 2 == 0 else -9), textcoords="offset points")
    return _finish(plt, fig, ax, path, "render: speed against accuracy", source,
                   "seconds per frame (1 thread, log)", "PSNR to the frame (dB)")


def poses_chart(runs: list[dict], source: str, path: Path) -> Path | None:
    """Wall seconds against median rotation error, ours and the ns-process-data recipe (baseline)."""
    runs = [r for r in runs if r.get("wall_s") and r.get("rot_err_deg_median") is not None]
    if not runs:
        return None
    plt, fig, ax = _figure()
    for variant, colour in (("ours", "tab:blue"), ("baseline", "tab:red")):
        rs = [r for r in runs if (r.get("variant", "") == "baseline") == (variant == "baseline")]
        if rs:
            ax.scatter([r["wall_s"] for r in rs], [max(r["rot_err_deg_median"], 1e-4) for r in rs], color=colour,
                       label="ns-process-data recipe" if variant == "baseline" else "interreal poses")
        for r in rs:
            ax.annotate(r["data"], (r["wall_s"], max(r["rot_err_deg_median"], 1e-4)), fontsize=6, xytext=(3, 2),
                        textcoords="offset points")
    return _finish(plt, fig, ax, path, "poses: speed against accuracy", source, "wall time (s, log)",
                   "median rotation error (deg, log)", log="xy")


def masks_chart(runs: list[dict], source: str, path: Path) -> Path | None:
    """Annotation effort (keyframes per 100 frames) against mean J, averaged over sequences, with frames/s."""
    curve = [r for r in runs if str(r.get("setting", "")).startswith("effort") and r.get("j_mean") is not None]
    if not curve:
        return None
    levels = sorted({r["effort_level"] for r in curve})
    j = [sum(r["j_mean"] for r in curve if r["effort_level"] == k) /
         sum(1 for r in curve if r["effort_level"] == k) for k in levels]
    fps = [r.get("fps") for r in curve if r.get("fps")]
    plt, fig, ax = _figure()
    ax.plot(levels, j, "-o", color="tab:blue",
            label=f"mask propagation ({sum(fps) / len(fps):.1f} frames/s)" if fps else "mask propagation")
    for k, v in zip(levels, j):
        ax.annotate(f"{v:.3f}", (k, v), fontsize=6, xytext=(3, -8), textcoords="offset points")
    return _finish(plt, fig, ax, path, "masks: annotation effort against accuracy", source,
                   "keyframes per 100 frames (annotation effort, log)", "mean J (IoU)", legend="lower right")


def clicks_chart(runs: list[dict], source: str, path: Path) -> Path | None:
    """Clicks against mean IoU per set (the simulated user of `bench_masks.py --clicks`), NoC levels drawn."""
    curve = [r for r in runs if r.get("kind") == "curve" and r.get("iou") is not None]
    if not curve:
        return None
    plt, fig, ax = _figure()
    for name in dict.fromkeys(r["set"] for r in curve):
        rs = sorted((r for r in curve if r["set"] == name), key=lambda r: r["clicks"])
        ax.plot([r["clicks"] for r in rs], [r["iou"] for r in rs], "-o", ms=3,
                label=f"{name} ({rs[0].get('s_per_click', 0):.2f} s a click)")
    for level in (0.85, 0.9):
        ax.axhline(level, color="0.6", lw=0.8, ls="--")
        ax.annotate(f"NoC@{round(100 * level)}", (1, level), fontsize=6, xytext=(2, 2), textcoords="offset points")
    return _finish(plt, fig, ax, path, "click to segment: clicks against accuracy", source,
                   "clicks (simulated user)", "mean IoU", log="", legend="lower right")


def model_size_chart(runs: list[dict], source: str, path: Path) -> Path | None:
    """Parameters (the model's cost) against held-out PSNR per room; the automatic size starred."""
    runs = [r for r in runs if r.get("params") and r.get("psnr") is not None]
    if not runs:
        return None
    plt, fig, ax = _figure()
    for room in dict.fromkeys(r["data"] for r in runs):
        rs = sorted([r for r in runs if r["data"] == room], key=lambda r: r["params"])
        ax.plot([r["params"] / 1e6 for r in rs], [r["psnr"] for r in rs], "-o", ms=3, label=f"{room} room")
    auto = [r for r in runs if r.get("auto")]
    if auto:
        ax.scatter([r["params"] / 1e6 for r in auto], [r["psnr"] for r in auto], marker="*", s=90, c="red",
                   zorder=5, label="automatic size")
    return _finish(plt, fig, ax, path, "model size: cost against accuracy", source,
                   "model parameters (millions, log)", "held-out PSNR (dB)")


def train_chart(runs: list[dict], source: str, path: Path) -> Path | None:
    """Training minutes against held-out PSNR (circle) and novel-state PSNR (square) per variant, the two joined;
    variants of one length are spread a little apart so each pair stays readable."""
    runs = [r for r in runs if r.get("minutes") and r.get("psnr") is not None]
    if not runs:
        return None
    plt, fig, ax = _figure()
    seen: dict[float, int] = {}
    for r in runs:
        k = seen[r["minutes"]] = seen.get(r["minutes"], -1) + 1
        x = r["minutes"] + 0.35 * k
        colour = f"C{runs.index(r)}"
        ax.plot([x], [r["psnr"]], "o", color=colour)
        if r.get("novel_state_psnr") is not None:
            ax.plot([x, x], [r["psnr"], r["novel_state_psnr"]], "-", color=colour, alpha=0.5)
            ax.plot([x], [r["novel_state_psnr"]], "s", color=colour)
        ax.plot([], [], "o-", color=colour, label=str(r.get("variant", "")))
    ax.set_xlabel("training minutes, 2-core CPU (circle: held-out, square: novel states)", fontsize=7)
    ax.set_ylabel("PSNR (dB)", fontsize=8)
    ax.set_xlim(0, max(r["minutes"] for r in runs) * 1.15 + 0.35 * max(seen.values()))
    ax.legend(fontsize=6, loc="lower left")
    return _save(plt, fig, ax, path, "train: time against accuracy", source)


CHARTS: dict[str, Callable[[list[dict], str, Path], Path | None]] = {
    "render": render_chart, "poses": poses_chart, "masks": masks_chart, "model_size": model_size_chart,
    "train": train_chart, "masks_clicks": clicks_chart,
}


def write_charts(bench_dir: Path, out_dir: Path = CHART_DIR) -> list[Path]:
    """Every chart that has data, as `out_dir/<name>.png`; ValueError if one would exceed MAX_BYTES."""
    written = []
    for name, draw in CHARTS.items():
        runs, source = chart_source(bench_dir, name)
        path = draw(runs, source, Path(out_dir) / f"{name}.png")
        if path is None:
            continue
        if path.stat().st_size > MAX_BYTES:
            raise ValueError(f"{path} is {path.stat().st_size} bytes, over {MAX_BYTES}: make the chart smaller")
        written.append(path)
    return written
