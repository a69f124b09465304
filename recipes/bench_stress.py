"""Failure-edge stress suite: where does each stage break, and does the toolkit SAY so when it does?

For each stress (wall texture, motion blur, fast motion, occluder, exposure drift, noise, label fraction, number of
objects, articulation size) and level, simulate a capture, run the pipeline, and record per (stage, metric):
`value`, `usable` (the figure meets its usable threshold) and `detected` (the stage raised an error, or its report
carries a warning whose cause says its output is degraded: `DEGRADED_CAUSES`). The goal is zero rows with usable == false and detected == false: no silent failure.

    python recipes/bench_stress.py --quick --out bench/
"""

from __future__ import annotations

import json
import shutil
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from benchlib import bench_args, print_table, scatter_chart, write_results

# metric -> (stage, direction, usable threshold); "min" = higher is better
THRESHOLDS: dict[str, tuple[str, str, float]] = {
    "registered_frac": ("poses", "min", 0.9),
    "rot_err_deg": ("poses", "max", 1.0),
    "mask_iou_min": ("masks", "min", 0.85),
    "psnr": ("train", "min", 24.0),
    "state_mae": ("train", "max", 0.1),
}

# stress -> (SynthConfig field, quick levels, full levels, train?)
STRESSES: dict[str, tuple[str, list, list, bool]] = {
    "texture": ("texture", ["photo", "none"], ["photo", "low", "none"], False),
    "motion_blur": ("motion_blur", [0.0, 1.0], [0.0, 0.5, 1.0], False),
    "fast_motion": ("speed", [1.0, 6.0], [1.0, 3.0, 6.0], False),
    "occluder": ("occluder", [0.0, 1.0], [0.0, 0.5, 1.0], False),
    "exposure_drift": ("exposure_drift", [0.0, 0.6], [0.0, 0.3, 0.6], False),
    "noise": ("noise", [0.0, 12.0], [0.0, 4.0, 12.0], False),
    "label_fraction": ("label_fraction", [0.02, 0.25], [0.01, 0.02, 0.05, 0.1, 0.25], True),
    "objects": ("parts", [1, 4], [1, 2, 4, 6, 10], True),
    "articulation": ("articulation", [0.25, 1.0], [0.25, 0.5, 1.0], True),
}


@dataclass
class LevelResult:
    """What one (stress, level) run produced: figures, and what each stage said (warnings, or the error)."""

    stress: str
    level: Any
    metrics: dict[str, float | None]
    warnings: dict[str, list[str]]  # stage -> warning messages
    error: tuple[str, str] | None = None  # (stage, message) when a stage refused the input


def is_usable(metric: str, value: float | None) -> bool:
    if value is None:
        return False
    _, direction, thr = THRESHOLDS[metric]
    return value >= thr if direction == "min" else value <= thr


def rows_for(res: LevelResult) -> list[dict[str, Any]]:
    """The flat records of one level: one per metric, with `usable` and `detected`."""
    rows = []
    for metric, (stage, _, thr) in THRESHOLDS.items():
        if metric not in res.metrics and not (res.error and res.error[0] == stage):
            continue
        value = res.metrics.get(metric)
        usable = is_usable(metric, value)
        # said so: the stage warned, or it (or an earlier stage, which stops the later ones) raised an error
        said = bool(res.warnings.get(stage)) or (
            res.error is not None and _stage_order(res.error[0]) <= _stage_order(stage))
        rows.append({"stress": res.stress, "level": res.level, "stage": stage, "metric": metric, "value": value,
                     "threshold": thr, "usable": usable, "detected": said,
                     "message": (res.error[1] if res.error else "; ".join(res.warnings.get(stage, [])))[:300]})
    return rows


def _stage_order(stage: str) -> int:
    order = ["frames", "process", "masks", "poses", "labels", "train"]
    return order.index(stage) if stage in order else len(order)


def silent_failures(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [r for r in rows if not r["usable"] and not r["detected"]]


# warnings that declare a stage's output degraded (advice such as "add a keyframe near frame 12" does not count)
DEGRADED_CAUSES: dict[str, set[str]] = {
    "frames": {"texture/exposure"},
    "masks": {"masks-unreliable", "masks-fine-parts"},
    "poses": {"low-registration", "texture", "blur", "motion", "exposure", "split-model"},
    "labels": {"stale-label"},
    "train": {"few-labels", "low-fit", "states-unreliable"},
}


def _warnings(report_path: Path, stage: str) -> list[str]:
    """Messages of the warnings in a stage report whose cause says the output is degraded."""
    try:
        rep = json.loads(report_path.read_text())
    except (OSError, ValueError):
        return []
    causes = DEGRADED_CAUSES.get(stage, set())
    out = []
    for w in rep.get("warnings", []):
        cause = w.get("cause") if isinstance(w, dict) else None
        if cause in causes or (stage == "poses" and cause and cause not in ("no-masks",)):
            out.append(w.get("message", str(w)))
    return out


def run_level(stress: str, field: str, level: Any, train: bool, work: Path, frames: int, size: tuple[int, int],
              train_steps: int) -> LevelResult:
    """Simulate, process (frames -> masks -> poses -> labels) and optionally train + evaluate one level."""
    from interreal.errors import InterRealError
    from interreal.process import process
    from interreal.scoring import mask_ious, pose_errors
    from interreal.synth import SynthConfig, write_capture

    cap, ds, run = work / "capture", work / "dataset", work / "run"
    for p in (cap, ds, run):
        shutil.rmtree(p, ignore_errors=True)
    cfg = SynthConfig(frames=frames, width=size[0], height=size[1], seed=1, keyframe_every=max(10, frames // 4))
    setattr(cfg, field, type(getattr(cfg, field))(level))
    write_capture(cfg.check(), cap, progress=False)
    metrics: dict[str, float | None] = {}
    warnings: dict[str, list[str]] = {}
    try:
        fig = process(cap / "video.mp4", ds, keyframes=cap / "annotations" / "keyframes",
                      labels=cap / "annotations" / "states.yaml", long_side=size[0])
        metrics["registered_frac"] = fig["registered"] / max(fig["total"], 1)
        metrics["rot_err_deg"] = pose_errors(ds, cap)["rot_err_deg_median"]
        ious = mask_ious(ds, cap)
        metrics["mask_iou_min"] = min(ious.values()) if ious else None
    except InterRealError as exc:
        stage = _failed_stage(ds)
        return LevelResult(stress, level, metrics, _collect(ds, run), (stage, str(exc)))
    finally:
        warnings = _collect(ds, run)
    if train:
        from livescene.config import load_preset
        from interreal.synth.evaltruth import CaptureTruth
        from livescene.evaluate import evaluate
        from livescene.trainer import load_run
        from livescene.trainer import train as fit

        tc = load_preset("cpu")
        tc.steps = train_steps
        try:
            fit(ds, run, tc, show_progress=False)
            r = load_run(run)
            ev = evaluate(r, CaptureTruth(cap, r.views), max_frames=4, novel=0, progress=False)
            metrics["psnr"], metrics["state_mae"] = ev.get("psnr"), ev.get("state_mae")
        except InterRealError as exc:
            return LevelResult(stress, level, metrics, _collect(ds, run), ("train", str(exc)))
        warnings = _collect(ds, run)
    return LevelResult(stress, level, metrics, warnings)


def _collect(ds: Path, run: Path) -> dict[str, list[str]]:
    out = {stage: _warnings(ds / "reports" / f"{stage}.json", stage) for stage in ("frames", "masks", "poses", "labels")}
    out["train"] = _warnings(run / "reports" / "train.json", "train")
    return out


def _failed_stage(ds: Path) -> str:
    for stage in ("frames", "masks", "poses", "labels"):
        try:
            rep = json.loads((ds / "reports" / f"{stage}.json").read_text())
        except (OSError, ValueError):
            return stage
        if rep.get("status") != "ok":
            return stage
    return "process"


def run_suite(stresses: dict[str, tuple[str, list, list, bool]], quick: bool, work: Path,
              runner: Callable[..., LevelResult] = run_level, levels: set[str] | None = None,
              done: list[dict[str, Any]] | None = None,
              on_level: Callable[[list[dict[str, Any]]], None] | None = None) -> list[dict[str, Any]]:
    """Every level of every stress (`levels`: only those whose str() is in it). Rows in `done` (an earlier,
    interrupted run) are kept and their levels skipped; `on_level` gets all rows so far after each level, so a
    killed run loses one level at most."""
    frames, size, steps = (40, (320, 240), 300) if quick else (90, (320, 240), 1500)
    rows: list[dict[str, Any]] = list(done or [])
    finished = {(r["stress"], str(r["level"])) for r in rows}
    for stress, (field, q_levels, f_levels, train) in stresses.items():
        for level in (q_levels if quick else f_levels):
            if (levels and str(level) not in levels) or (stress, str(level)) in finished:
                continue
            t0 = time.perf_counter()
            try:
                res = runner(stress, field, level, train, work / stress, frames, size, steps)
            except Exception as exc:  # noqa: BLE001 - a crash is a failure nobody explained: record it, go on
                traceback.print_exc()
                res = LevelResult(stress, level, {}, {}, ("crash", f"{type(exc).__name__}: {exc}"))
                rows.append({"stress": stress, "level": level, "stage": "crash", "metric": "crash", "value": None,
                             "threshold": None, "usable": False, "detected": False, "message": res.error[1][:300]})
            new = rows_for(res)
            for r in new:
                r["wall_s"] = round(time.perf_counter() - t0, 1)
            rows += new
            print(f"[stress] {stress}={level}: " + ", ".join(f"{r['metric']}={_fmt(r['value'])}"
                                                           f"{'' if r['usable'] else ' (!' + ('detected' if r['detected'] else 'SILENT') + ')'}"
                                                           for r in new), flush=True)
            if on_level is not None:
                on_level(rows)
    return rows


def earlier_rows(path: Path, quick: bool) -> list[dict[str, Any]]:
    """The rows of an earlier run in the same mode (quick or full) at `path`, to resume it; [] if none."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return []
    return list(data.get("runs", [])) if bool(data.get("quick")) == bool(quick) else []


def _fmt(v: Any) -> str:
    return "n/a" if v is None else (f"{v:.3g}" if isinstance(v, float) else str(v))


def charts(rows: list[dict[str, Any]], out: Path) -> list[Path]:
    paths = []
    for metric in THRESHOLDS:
        rs = [r for r in rows if r["metric"] == metric and r["value"] is not None and not isinstance(r["level"], str)]
        if not rs:
            continue
        for r in rs:
            r["_x"] = float(r["level"])
        path = out / f"stress_{metric}.png"
        scatter_chart(path, rs, "_x", "value", lambda r: "" if r["usable"] else ("!" if r["detected"] else "SILENT"),
                      f"stress: {metric} by level (threshold {THRESHOLDS[metric][2]})", xlabel="stress level",
                      ylabel=metric, lines_by=lambda r: r["stress"])
        for r in rs:
            r.pop("_x", None)
        paths.append(path)
    return paths


def main() -> int:
    def extra(p) -> None:
        p.add_argument("--only", default="", help="comma-separated stresses to run (default all)")
        p.add_argument("--levels", default="", help="comma-separated levels to run (default all), e.g. --only objects "
                                                    "--levels 10")
        p.add_argument("--fresh", action="store_true", help="redo levels already in DIR/stress.json (default: an "
                                                            "earlier run in the same mode is resumed and extended)")

    args = bench_args("stress", __doc__.splitlines()[0], extra)
    unknown = set(filter(None, args.only.split(","))) - set(STRESSES)
    if unknown:
        raise SystemExit(f"unknown stress(es) {sorted(unknown)}; choose from {sorted(STRESSES)}")
    chosen = {k: v for k, v in STRESSES.items() if not args.only or k in args.only.split(",")}
    done = [] if args.fresh else earlier_rows(args.out / "stress.json", args.quick)

    def save(rows: list[dict[str, Any]], complete: bool = False) -> None:
        write_results(args.out, "stress", rows, quick=args.quick, complete=complete,
                      silent_failures=len(silent_failures(rows)), thresholds=THRESHOLDS)

    rows = run_suite(chosen, args.quick, args.out / "stress_work", levels=set(filter(None, args.levels.split(","))),
                     done=done, on_level=save)
    silent = silent_failures(rows)
    save(rows, complete=True)
    charts(rows, args.out)
    # the required stress.png: value against level for every metric, one panel per metric
    _overview(rows, args.out / "stress.png")
    print_table(rows, ["stress", "level", "stage", "metric", "value", "usable", "detected"], title="stress suite")
    print(f"\nsilent failures (usable == false and detected == false): {len(silent)}")
    return 0


def _overview(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = [m for m in THRESHOLDS if any(r["metric"] == m for r in rows)]
    if not metrics:
        return
    fig, axes = plt.subplots(1, len(metrics), figsize=(4 * len(metrics), 3.6), dpi=100, squeeze=False)
    for ax, metric in zip(axes[0], metrics):
        rs = [r for r in rows if r["metric"] == metric and r["value"] is not None]
        labels = [f"{r['stress']}={r['level']}" for r in rs]
        colors = ["tab:green" if r["usable"] else ("tab:orange" if r["detected"] else "tab:red") for r in rs]
        ax.barh(range(len(rs)), [r["value"] for r in rs], color=colors)
        ax.set_yticks(range(len(rs)), labels, fontsize=6)
        ax.axvline(THRESHOLDS[metric][2], color="k", ls="--", lw=1)
        ax.set_title(metric, fontsize=9)
    fig.suptitle("stress: green usable, orange failed but detected, red silent failure", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
