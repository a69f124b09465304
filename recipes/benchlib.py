"""What every benchmark shares: the output files (DIR/<name>.json with "runs", DIR/<name>.png), a table, timing.

Use from a recipe:  `from benchlib import write_results, scatter_chart, print_table, bench_args`
(recipes are run as scripts, so their folder is on sys.path).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


def bench_args(name: str, description: str, extra: Callable[[argparse.ArgumentParser], None] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog=f"bench_{name}.py", description=description,
                                epilog=f"example:\n  python recipes/bench_{name}.py --quick --out bench/",
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="small sizes, a few minutes")
    p.add_argument("--out", type=Path, default=Path("bench"), help="output folder (default bench/)")
    if extra:
        extra(p)
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    return args


def environment() -> dict[str, Any]:
    return {"python": platform.python_version(), "platform": platform.platform(), "cpus": os.cpu_count(),
            "load_avg_1m": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}


def write_results(out: Path, name: str, runs: list[dict[str, Any]], **meta: Any) -> Path:
    """DIR/<name>.json = {"benchmark", "runs": [...], "environment", ...meta}."""
    from interreal.atomic import write_json

    path = Path(out) / f"{name}.json"
    write_json(path, {"benchmark": name, "runs": runs, "environment": environment(), **meta})
    return path


def print_table(runs: Sequence[dict[str, Any]], columns: Sequence[str], title: str | None = None) -> str:
    """A plain-text (markdown) table of the given columns; returns it too."""
    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        return "" if v is None else str(v)

    rows = [[fmt(r.get(c)) for c in columns] for r in runs]
    widths = [max(len(c), *(len(row[i]) for row in rows)) if rows else len(c) for i, c in enumerate(columns)]
    lines = ["| " + " | ".join(c.ljust(w) for c, w in zip(columns, widths)) + " |",
             "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    lines += ["| " + " | ".join(v.ljust(w) for v, w in zip(row, widths)) + " |" for row in rows]
    text = ("\n".join([f"### {title}", ""] + lines) if title else "\n".join(lines))
    print(text)
    return text


def scatter_chart(path: Path, runs: Iterable[dict[str, Any]], x: str, y: str, label: Callable[[dict], str],
                  title: str, logx: bool = False, xlabel: str | None = None, ylabel: str | None = None,
                  lines_by: Callable[[dict], str] | None = None,
                  highlight: Callable[[dict], bool] | None = None, highlight_label: str = "") -> Path:
    """One point per run, labelled; optional polylines joining runs with the same `lines_by` key; runs for which
    `highlight` is true get a large marker (e.g. the auto-chosen setting), named `highlight_label` in the legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [r for r in runs if r.get(x) is not None and r.get(y) is not None]
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    if lines_by is not None:
        groups: dict[str, list[dict]] = {}
        for r in runs:
            groups.setdefault(lines_by(r), []).append(r)
        for key, rs in groups.items():
            rs = sorted(rs, key=lambda r: r[x])
            ax.plot([r[x] for r in rs], [r[y] for r in rs], "-o", label=key, alpha=0.8)
    else:
        ax.scatter([r[x] for r in runs], [r[y] for r in runs])
    if highlight is not None:
        marked = [r for r in runs if highlight(r)]
        if marked:
            ax.scatter([r[x] for r in marked], [r[y] for r in marked], s=220, marker="*", c="red", zorder=5,
                       edgecolors="k", linewidths=0.6, label=highlight_label or None)
    for r in runs:
        ax.annotate(label(r), (r[x], r[y]), fontsize=7, xytext=(3, 3), textcoords="offset points")
    if logx:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel or x)
    ax.set_ylabel(ylabel or y)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if lines_by is not None or (highlight is not None and highlight_label):
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


def timed(fn: Callable[[], Any], repeat: int = 1) -> tuple[Any, float]:
    """(last result, median wall seconds over `repeat` runs)."""
    times, result = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return result, statistics.median(times)


def load_json(path: Path) -> dict[str, Any]:
    return json.loads(Path(path).read_text())
