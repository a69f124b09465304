"""`interreal batch CAPTURES... --out ROOT`: many captures, each through `process` (and `livescene train`).

Each capture is one task of stages run as child processes (`interreal.batch_engine`): on Ray (the `scale` extra) when
it is installed, else on a local pool of worker slots with the same behaviour. The batch resumes: a capture that
finished from the same inputs and options is skipped, one that failed runs again (its stages reuse what they had
finished); a failure is reported with its stage's one-line error and never stops the other captures.

Where a capture's parts are found (the naming rule), for a capture folder CAP:
  source     CAP/video.<ext> (the folder's one video file), else CAP/images/ or CAP/raw/, else CAP itself when it
             holds images
  keyframes  CAP/annotations/keyframes/, else CAP/keyframes/          (as `interreal synth` writes them)
  labels     CAP/annotations/states.{yaml,csv}, else CAP/states.{yaml,csv}, else CAP/key_frame_value.yaml
  name       CAP's folder name
and for a video file DIR/NAME.mp4: keyframes DIR/NAME.keyframes/, labels DIR/NAME.states.{yaml,csv}, name NAME.
Anything else goes in a manifest (`--manifest FILE`, see MANIFEST_HELP).

ROOT/NAME/dataset (the LiveScene dataset), ROOT/NAME/run (with --train), ROOT/NAME/logs/<stage>.log,
ROOT/NAME/batch.json (what the batch did: inputs key, stage results); ROOT/summary.md and ROOT/summary.json (one row
per capture: stage times, registered frames, mask confidence, warnings, PSNR, error) are rewritten atomically each
time a capture ends, so a killed batch still leaves the table of what it finished.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import os
import shutil
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import yaml
from rich.live import Live
from rich.table import Table

from . import atomic
from .batch_engine import CaptureJob, LocalEngine, RayEngine, StageCommand, StageResult, ray_available
from .errors import InputError
from .ingest import IMAGE_SUFFIXES, RAW_SUFFIXES, VIDEO_SUFFIXES
from .report import fingerprint, read_report, tree_fingerprint

MANIFEST_HELP = """manifest (YAML; paths relative to the manifest's folder):
  defaults:                       # for every capture; a capture's own entries override them
    process: {target: 200, long_side: 640}      # any `interreal process` option (flag name, - or _)
    train: {steps: 3000, preset: cpu}           # a train entry turns training on (keys: preset, steps, minutes,
                                                #   device, set: [KEY=VALUE, ...])
  captures:
    - kitchen/                    # a capture folder or video file: the naming rule finds the rest
    - source: lab/bench.mp4
      name: bench
      keyframes: lab/bench_masks/
      labels: lab/bench_states.csv
      process: {matcher: exhaustive}
      train: false                # this one is not trained"""

CAPTURE_KEYS = {"source", "name", "keyframes", "labels", "process", "train"}
TRAIN_KEYS = {"preset", "steps", "minutes", "device", "set"}
PROCESS_STAGES = ("frames", "masks", "poses", "labels", "motions")


@dataclass
class Capture:
    """One capture and what to do with it."""

    name: str
    source: Path
    keyframes: Path | None = None
    labels: Path | None = None
    process: dict[str, Any] = field(default_factory=dict)  # extra `interreal process` options
    train: dict[str, Any] | None = None  # None: not trained

    def key(self) -> str:
        """What the capture's results depend on: its files (name, size, time) and its options."""
        files = [tree_fingerprint(p) if p is not None else None for p in (self.source, self.keyframes, self.labels)]
        return fingerprint(files, [str(p) for p in (self.source, self.keyframes, self.labels)], self.process,
                           self.train)


# ---------------------------------------------------------------------------------------------------------------
# Finding captures
# ---------------------------------------------------------------------------------------------------------------
def _first(*paths: Path) -> Path | None:
    return next((p for p in paths if p.exists()), None)


def capture_from_path(path: Path) -> Capture:
    """A capture folder or video file, its keyframes and labels found by the naming rule (module docstring)."""
    path = Path(path)
    if path.is_file():
        d, stem = path.parent, path.stem
        return Capture(name=stem, source=path, keyframes=_first(d / f"{stem}.keyframes"),
                       labels=_first(d / f"{stem}.states.yaml", d / f"{stem}.states.csv"))
    if not path.is_dir():
        raise InputError(f"capture {path} does not exist: give a capture folder or a video file")
    videos = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES)
    if len(videos) > 1:
        raise InputError(f"capture {path} holds {len(videos)} videos ({', '.join(p.name for p in videos[:3])}): "
                         f"give each video file as its own capture, or name the source in a --manifest")
    images = any(p.suffix.lower() in IMAGE_SUFFIXES | RAW_SUFFIXES for p in path.iterdir() if p.is_file())
    source = videos[0] if videos else _first(path / "images", path / "raw") or (path if images else None)
    if source is None:
        raise InputError(f"capture {path} has no video, images/ or raw/ folder, nor images of its own: see "
                         f"`interreal batch --help` for where a capture's files go")
    ann = path / "annotations"
    return Capture(name=path.resolve().name, source=source,
                   keyframes=_first(ann / "keyframes", path / "keyframes"),
                   labels=_first(ann / "states.yaml", ann / "states.csv", path / "states.yaml", path / "states.csv",
                                 path / "key_frame_value.yaml"))


def _merge(default: Any, own: Any) -> Any:
    if isinstance(default, dict) and isinstance(own, dict):
        return {**default, **own}
    return default if own is None else own


def _train_options(value: Any, where: str) -> dict[str, Any] | None:
    if value in (None, False):
        return None
    if value is True:
        return {}
    if not isinstance(value, dict):
        raise InputError(f"{where}: train must be true, false or a mapping of {sorted(TRAIN_KEYS)}")
    unknown = set(value) - TRAIN_KEYS
    if unknown:
        raise InputError(f"{where}: unknown train option(s) {sorted(unknown)}; use {sorted(TRAIN_KEYS)}")
    return dict(value)


def read_manifest(path: Path) -> list[Capture]:
    """The captures a manifest lists (MANIFEST_HELP), paths taken relative to its folder."""
    try:
        raw = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputError(f"--manifest {path}: cannot read it ({exc.strerror or exc})") from exc
    except yaml.YAMLError as exc:
        raise InputError(f"--manifest {path} is not valid YAML ({str(exc).splitlines()[0]})") from exc
    if not isinstance(raw, dict) or not isinstance(raw.get("captures"), list):
        raise InputError(f"--manifest {path}: expected a mapping with a 'captures:' list (see interreal batch --help)")
    base = Path(path).parent
    defaults = raw.get("defaults") or {}
    if not isinstance(defaults, dict) or set(defaults) - {"process", "train"}:
        raise InputError(f"--manifest {path}: 'defaults' may hold only process: and train:")
    out = []
    for i, entry in enumerate(raw["captures"]):
        where = f"--manifest {path}, capture {i + 1}"
        entry = {"source": entry} if isinstance(entry, str) else entry
        if not isinstance(entry, dict) or "source" not in entry:
            raise InputError(f"{where}: give a path, or a mapping with at least source:")
        unknown = set(entry) - CAPTURE_KEYS
        if unknown:
            raise InputError(f"{where}: unknown key(s) {sorted(unknown)}; use {sorted(CAPTURE_KEYS)}")
        cap = capture_from_path(base / str(entry["source"]))
        if "name" in entry:
            cap.name = str(entry["name"])
        for key in ("keyframes", "labels"):
            if entry.get(key):
                p = base / str(entry[key])
                if not p.exists():
                    raise InputError(f"{where}: {key} {p} does not exist")
                setattr(cap, key, p)
        proc = _merge(defaults.get("process"), entry.get("process"))
        if proc is not None and not isinstance(proc, dict):
            raise InputError(f"{where}: process must be a mapping of `interreal process` options")
        cap.process = dict(proc or {})
        cap.train = _train_options(_merge(defaults.get("train"), entry.get("train")), where)
        out.append(cap)
    return out


def collect(paths: list[Path], manifest: Path | None, args: argparse.Namespace) -> list[Capture]:
    """The captures named on the command line and in the manifest, with the command line's options applied to
    those that do not set them; two captures with one name are refused (their outputs would collide)."""
    caps = [capture_from_path(p) for p in paths] + (read_manifest(manifest) if manifest else [])
    if not caps:
        raise InputError("no captures: give capture folders / videos, or --manifest FILE")
    cli_process = {k: v for k, v in (("target", args.target), ("long_side", args.long_side)) if v is not None}
    cli_train = {k: v for k, v in (("preset", args.train_preset), ("steps", args.train_steps),
                                   ("minutes", args.train_minutes)) if v}
    for cap in caps:
        cap.process = {**cli_process, **cap.process}
        if args.train and cap.train is None:
            cap.train = {}
        if cap.train is not None:
            cap.train = {**cli_train, **cap.train}
    seen: dict[str, Path] = {}
    for cap in caps:
        if cap.name in seen:
            raise InputError(f"two captures are named {cap.name!r} ({seen[cap.name]} and {cap.source}): name them "
                             f"apart in a --manifest (name: ...)")
        if not cap.name or cap.name in (".", "..") or "/" in cap.name:
            raise InputError(f"capture name {cap.name!r} cannot be a folder name: set name: in the manifest")
        seen[cap.name] = cap.source
    return caps


# ---------------------------------------------------------------------------------------------------------------
# Stage commands
# ---------------------------------------------------------------------------------------------------------------
def option_argv(options: dict[str, Any]) -> list[str]:
    """{"target": 12, "no_motions": True, "matcher": "sequential"} -> --target 12 --no-motions --matcher sequential."""
    argv: list[str] = []
    for key, value in options.items():
        flag = "--" + str(key).replace("_", "-")
        if value is True:
            argv.append(flag)
        elif value not in (False, None):
            for v in value if isinstance(value, list) else [value]:
                argv += [flag, str(v)]
    return argv


def capture_dir(root: Path, cap: Capture) -> Path:
    return root / cap.name


def stage_commands(cap: Capture, root: Path, cpus: int, gpu: bool, resume_run: bool) -> list[StageCommand]:
    """`interreal process` (and `livescene train`) for one capture, with their resource hints."""
    out = capture_dir(root, cap).resolve()  # absolute: a Ray worker on another node has another working folder
    ds = out / "dataset"
    argv = [sys.executable, "-m", "interreal", "process", str(cap.source.resolve()), str(ds)]
    argv += ["--keyframes", str(cap.keyframes.resolve())] if cap.keyframes else []
    argv += ["--labels", str(cap.labels.resolve())] if cap.labels else []
    cmds = [StageCommand(cap.name, "process", argv + option_argv(cap.process), str(out / "logs" / "process.log"),
                         cpus=cpus)]
    if cap.train is not None:
        t = cap.train
        targv = [sys.executable, "-m", "livescene", "train", str(ds), "--out", str(out / "run"), "--no-progress"]
        targv += ["--preset", str(t["preset"])] if t.get("preset") else []
        targv += ["--steps", str(int(t["steps"]))] if t.get("steps") else []
        targv += ["--max-minutes", str(float(t["minutes"]))] if t.get("minutes") else []
        targv += ["--device", str(t["device"])] if t.get("device") else []
        targv += ["--threads", str(cpus)] if not gpu else []
        for kv in t.get("set") or []:
            targv += ["--set", str(kv)]
        targv += ["--resume"] if resume_run else []
        cmds.append(StageCommand(cap.name, "train", targv, str(out / "logs" / "train.log"),
                                 cpus=1 if gpu else cpus, gpus=1 if gpu else 0))
    return cmds


# ---------------------------------------------------------------------------------------------------------------
# Resume
# ---------------------------------------------------------------------------------------------------------------
def state_path(root: Path, cap: Capture) -> Path:
    return capture_dir(root, cap) / "batch.json"


def read_state(root: Path, cap: Capture) -> dict[str, Any]:
    try:
        return json.loads(state_path(root, cap).read_text())
    except (OSError, ValueError):
        return {}


def finished(root: Path, cap: Capture, key: str) -> bool:
    """The capture ended "ok" from these inputs and options, and its outputs are still there and finished."""
    state = read_state(root, cap)
    if state.get("status") != "ok" or state.get("key") != key:
        return False
    ds = capture_dir(root, cap) / "dataset"
    if (read_report(ds, "process") or {}).get("status") != "ok":
        return False
    return cap.train is None or (read_report(capture_dir(root, cap) / "run", "train") or {}).get("status") == "ok"


def prepare_run(root: Path, cap: Capture, key: str) -> bool:
    """Whether train should --resume: the run of an interrupted batch with the same inputs is continued; a run
    made from other inputs is moved aside (run.stale), never trained on top of."""
    run = capture_dir(root, cap) / "run"
    if cap.train is None or not ((run / "latest.pt").exists() or any((run / "checkpoints").glob("step_*.pt"))):
        return False
    if read_state(root, cap).get("key") == key:
        return True
    stale = run.with_name("run.stale")
    if stale.exists():
        shutil.rmtree(stale)
    run.rename(stale)
    print(f"batch: {cap.name}: its inputs or options changed since {run} was trained: moved it to {stale}")
    return False


def write_state(root: Path, cap: Capture, key: str, results: list[StageResult] | None) -> dict[str, Any]:
    """ROOT/NAME/batch.json: "running" (with the inputs key, so a killed batch resumes the capture's training)
    when the capture is handed to the engine, then "ok" / "failed" with each stage's result."""
    status = "running" if results is None else "ok" if all(r.ok for r in results) else "failed"
    state = {"name": cap.name, "key": key, "status": status,
             "time": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
             "capture": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(cap).items()},
             "stages": {r.stage: asdict(r) for r in results or []}}
    atomic.write_json(state_path(root, cap), state)
    return state


# ---------------------------------------------------------------------------------------------------------------
# Summary table
# ---------------------------------------------------------------------------------------------------------------
def capture_row(root: Path, cap: Capture, status: str) -> dict[str, Any]:
    """One row of the summary, from the capture's batch.json and its stages' own reports."""
    state = read_state(root, cap)
    stages = state.get("stages", {})
    ds = capture_dir(root, cap) / "dataset"
    proc = read_report(ds, "process") or {}
    steps = proc.get("steps", {})
    times = {s: steps[s].get("wall_s") for s in PROCESS_STAGES if s in steps}
    for s in ("process", "train"):
        if s in stages and stages[s].get("returncode") is not None:
            times[s] = stages[s].get("wall_s")
    poses = (read_report(ds, "poses") or {}).get("figures", {})
    masks = (read_report(ds, "masks") or {}).get("figures", {})
    train = (read_report(capture_dir(root, cap) / "run", "train") or {})
    tf = train.get("figures", {}) if train.get("status") == "ok" else {}
    warnings = [{"stage": w.get("stage", "process"), "message": w.get("message", "")}
                for w in proc.get("warnings", []) if isinstance(w, dict)]
    warnings += [{"stage": "train", "message": w.get("message", "")} for w in train.get("warnings", [])
                 if isinstance(w, dict)]
    failed = next((s for s in stages.values() if not s.get("ok")), None)
    return {"capture": cap.name, "status": status, "source": str(cap.source), "seconds": times,
            "registered": poses.get("registered"), "frames": poses.get("total"),
            "mask_confidence": masks.get("confidence_mean") or {}, "warnings": warnings,
            "psnr": tf.get("eval_psnr"), "psnr_on": tf.get("eval_on"), "train_steps": tf.get("steps"),
            "error": f"{failed['stage']}: {failed.get('error')}" if failed else None,
            "host": next((s.get("host") for s in stages.values() if s.get("host")), None)}


def _fmt(v: Any, spec: str = ".1f") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return format(v, spec) if isinstance(v, (int, float)) else str(v)


def summary_markdown(summary: dict[str, Any]) -> str:
    cols = ["capture", "status", *PROCESS_STAGES, "process", "train", "registered", "mask conf.", "warnings",
            "PSNR", "error"]
    lines = [f"# interreal batch: {summary['root']}", "",
             f"{summary['engine']}; {summary['ok']} ok, {summary['failed']} failed, {summary['skipped']} finished "
             f"earlier, of {summary['total']}; wall {summary['wall_s']:.1f} s"
             + (f", {summary['captures_per_hour']:.1f} finished captures/hour" if summary.get("captures_per_hour")
                else ""),
             "", "stage times in seconds; mask conf. = the lowest predicted J over objects (masks stage); "
             "PSNR = the trained run's held-out PSNR", "",
             "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in summary["captures"]:
        t = r["seconds"]
        conf = min(r["mask_confidence"].values()) if r["mask_confidence"] else None
        reg = f"{r['registered']}/{r['frames']}" if r["registered"] is not None else "-"
        err = (r["error"] or "").replace("|", "\\|")
        lines.append("| " + " | ".join([r["capture"], r["status"], *(_fmt(t.get(s)) for s in PROCESS_STAGES),
                                        _fmt(t.get("process")), _fmt(t.get("train")), reg, _fmt(conf, ".2f"),
                                        str(len(r["warnings"])), _fmt(r["psnr"], ".2f"), err]) + " |")
    return "\n".join(lines) + "\n"


def write_summary(root: Path, caps: list[Capture], status: dict[str, str], meta: dict[str, Any]) -> dict[str, Any]:
    rows = [capture_row(root, c, status.get(c.name, "pending")) for c in caps]
    count = {s: sum(1 for r in rows if r["status"] == s) for s in ("ok", "failed", "skipped", "pending")}
    summary = {**meta, "total": len(rows), **count,  # throughput: captures this run finished, per hour of wall
               "captures_per_hour": round(3600.0 * count["ok"] / meta["wall_s"], 2) if count["ok"] and
               meta["wall_s"] > 0 else None,
               "captures": rows}
    atomic.write_json(root / "summary.json", summary)
    atomic.write_text(root / "summary.md", summary_markdown(summary))
    return summary


# ---------------------------------------------------------------------------------------------------------------
# Progress view
# ---------------------------------------------------------------------------------------------------------------
class Progress:
    """One line per stage start / end with the batch's counts; on a terminal, also a live table (rich)."""

    def __init__(self, caps: list[Capture], skipped: set[str], live: bool):
        self.t0 = time.perf_counter()
        self.state = {c.name: ("finished earlier" if c.name in skipped else "queued") for c in caps}
        self.lock = threading.Lock()
        self.live = None
        if live:
            self.live = Live(self._table(), refresh_per_second=2, transient=False)
            self.live.start()

    def _table(self):
        t = Table(title=f"interreal batch ({time.perf_counter() - self.t0:.0f} s)")
        t.add_column("capture")
        t.add_column("state")
        for name, st in self.state.items():
            t.add_row(name, st)
        return t

    def counts(self) -> str:
        vals = list(self.state.values())
        done = sum(v.startswith("ok") or v == "finished earlier" for v in vals)
        failed = sum(v.startswith("failed") for v in vals)
        running = sum(v.startswith("running") for v in vals)
        return f"{done + failed}/{len(vals)} done ({failed} failed), {running} running"

    def event(self, capture: str, stage: str, what: str, res: StageResult | None) -> None:
        with self.lock:
            if what == "start":
                self.state[capture] = f"running {stage}"
                line = f"{capture}: {stage} started"
            elif res is not None and res.ok:
                self.state[capture] = f"ok ({stage} {res.wall_s:.1f} s)"
                line = f"{capture}: {stage} ok in {res.wall_s:.1f} s"
            elif res is not None and res.returncode is None and res.error and res.error.startswith("not run"):
                return
            else:
                self.state[capture] = f"failed in {stage}"
                line = f"{capture}: {stage} FAILED after {res.wall_s if res else 0:.1f} s: {res.error if res else ''}"
            stamp = f"[{time.perf_counter() - self.t0:7.1f} s]"
            if self.live is not None:
                self.live.update(self._table())
                self.live.console.print(f"{stamp} {line}")
            else:
                print(f"{stamp} {line}   ({self.counts()})", flush=True)

    def close(self) -> None:
        if self.live is not None:
            self.live.update(self._table())
            self.live.stop()


# ---------------------------------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------------------------------
def make_engine(kind: str, workers: int, address: str | None):
    if address and kind == "local":
        raise InputError("--address joins a Ray cluster: drop --engine local")
    if kind == "ray" or address or (kind == "auto" and ray_available()):
        return RayEngine(workers, address)
    return LocalEngine(workers)


def run_batch(caps: list[Capture], root: Path, engine, cpus_per_task: int = 0, force: bool = False,
              live: bool = False) -> dict[str, Any]:
    """Run every capture not yet finished; returns the summary (also written to ROOT/summary.{md,json})."""
    root.mkdir(parents=True, exist_ok=True)
    workers = getattr(engine, "workers", 1)
    cpus = cpus_per_task or max(1, engine.cpus // workers)
    gpu = engine.gpu_count() > 0
    keys = {c.name: c.key() for c in caps}
    status = {c.name: "skipped" for c in caps if not force and finished(root, c, keys[c.name])}
    todo = [c for c in caps if c.name not in status]
    started = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    meta = {"root": str(root), "engine": engine.describe(), "workers": workers, "cpus_per_task": cpus,
            "started": started, "wall_s": 0.0}
    print(f"batch: {len(caps)} captures ({len(status)} finished earlier, {len(todo)} to run) on "
          f"{engine.describe()}; {cpus} CPU{'s' if cpus > 1 else ''} per capture -> {root}", flush=True)
    jobs = []
    for c in todo:
        resume = prepare_run(root, c, keys[c.name])
        jobs.append(CaptureJob(c.name, stage_commands(c, root, cpus, gpu, resume)))
        write_state(root, c, keys[c.name], None)
    by_name = {c.name: c for c in caps}
    progress = Progress(caps, set(status), live)
    t0 = time.perf_counter()
    try:
        for job, results in engine.run(jobs, progress.event):
            cap = by_name[job.name]
            status[cap.name] = write_state(root, cap, keys[cap.name], results)["status"]
            meta["wall_s"] = round(time.perf_counter() - t0, 2)
            write_summary(root, caps, status, meta)
    finally:
        progress.close()
    meta["wall_s"] = round(time.perf_counter() - t0, 2)
    return write_summary(root, caps, status, meta)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("captures", nargs="*", type=Path, help="capture folders or video files (naming rule below)")
    p.add_argument("--out", type=Path, required=True, help="output root: ROOT/NAME/{dataset,run,logs}, ROOT/summary.md")
    p.add_argument("--manifest", type=Path, help="YAML list of captures and their options (format below)")
    p.add_argument("--workers", type=int, default=2, help="captures processed at once (default 2); the CPUs are "
                                                          "shared among them")
    p.add_argument("--engine", choices=("auto", "ray", "local"), default="auto",
                   help="auto: Ray when installed (pip install 'interreal[scale]'), else the local pool")
    p.add_argument("--address", help="join this Ray cluster (e.g. ray://head:10001 or auto) instead of a local one")
    p.add_argument("--cpus-per-task", type=int, default=0, help="CPUs per capture (default: CPUs / workers)")
    p.add_argument("--target", type=int, help="frames to select per capture (interreal process --target)")
    p.add_argument("--long-side", type=int, help="long side of the dataset images (interreal process --long-side)")
    p.add_argument("--train", action="store_true", help="also train each processed capture (livescene train)")
    p.add_argument("--train-preset", help="livescene train --preset (default: auto)")
    p.add_argument("--train-steps", type=int, help="livescene train --steps")
    p.add_argument("--train-minutes", type=float, help="livescene train --max-minutes")
    p.add_argument("--force", action="store_true",
                   help="run the finished captures' stages again too (each still reuses its own finished work)")
    p.epilog = ("examples:\n"
                "  interreal batch caps/* --out batch/ --workers 2            # every capture folder in caps/\n"
                "  interreal batch --manifest captures.yaml --out batch/ --train --train-minutes 20\n"
                "  interreal batch caps/* --out batch/ --address auto         # on a running Ray cluster\n\n"
                "naming rule, for a capture folder CAP:\n"
                "  source     CAP/video.<ext> (its one video), else CAP/images/ or CAP/raw/, else CAP's own images\n"
                "  keyframes  CAP/annotations/keyframes/ or CAP/keyframes/\n"
                "  labels     CAP/annotations/states.{yaml,csv}, CAP/states.{yaml,csv} or CAP/key_frame_value.yaml\n"
                "  for a video DIR/NAME.mp4: DIR/NAME.keyframes/ and DIR/NAME.states.{yaml,csv}\n\n"
                + MANIFEST_HELP + "\n\n"
                "A finished capture is skipped when the batch runs again (--force runs it anyway); a failed one runs\n"
                "again. The exit status is 1 when any capture failed; ROOT/summary.md says which stage and why.")


def main(args: argparse.Namespace) -> int:
    if args.workers < 1:
        raise InputError(f"--workers {args.workers}: give at least 1")
    caps = collect(list(args.captures), args.manifest, args)
    engine = make_engine(args.engine, args.workers, args.address)
    try:
        summary = run_batch(caps, args.out, engine, args.cpus_per_task, args.force,
                            live=sys.stdout.isatty() and not os.environ.get("INTERREAL_NO_LIVE"))
    finally:
        engine.close()
    print(summary_markdown(summary))
    print(f"batch: {summary['ok']} ok, {summary['failed']} failed, {summary['skipped']} finished earlier -> "
          f"{args.out / 'summary.md'}, {args.out / 'summary.json'}")
    return 1 if summary["failed"] else 0
