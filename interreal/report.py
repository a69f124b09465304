"""Stage reports: `DS/reports/<stage>.json` with inputs, settings, wall time per step, figures and warnings.

A report is written with status "running" before the stage touches the dataset and "ok" only at the end,
so `interreal validate` can refuse a dataset whose last stage crashed half-way.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import platform
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from . import atomic
from .conventions import REPORTS_DIR


def report_path(root: str | Path, stage: str) -> Path:
    return Path(root) / REPORTS_DIR / f"{stage}.json"


def read_report(root: str | Path, stage: str) -> dict[str, Any] | None:
    path = report_path(root, stage)
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def warning_lines(root: str | Path, stages: list[str]) -> list[str]:
    """'  warning (stage): message' for every warning the stages' reports hold: terminal summaries show what the
    reports say, so nothing a stage noticed is only in a JSON file."""
    lines = []
    for stage in stages:
        for w in (read_report(root, stage) or {}).get("warnings", []):
            lines.append(f"  warning ({stage}): {w.get('message', w) if isinstance(w, dict) else w}")
    return lines


def fingerprint(*parts: Any) -> str:
    """Stable hash of settings/inputs, used to decide whether a finished step can be reused."""
    blob = json.dumps(parts, sort_keys=True, default=str).encode()
    return hashlib.sha1(blob).hexdigest()[:16]


def files_fingerprint(paths: list[Path]) -> str:
    """Files by name, size and modification time: a rewritten file counts as changed, an untouched one does not."""
    return fingerprint([(p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in paths])


def tree_fingerprint(path: Path) -> str | None:
    """`files_fingerprint` of a folder's files, or of one file; None when it cannot be listed (the stage then
    runs and fails with its own clear error)."""
    try:
        return files_fingerprint(sorted(p for p in path.iterdir() if p.is_file()) if path.is_dir() else [path])
    except OSError:
        return None


def finished_with(root: str | Path, stage: str, resume_key: str) -> dict[str, Any] | None:
    """The stage's report when it finished ("ok") from the same inputs and settings (`resume_key`), else None."""
    rep = read_report(root, stage)
    if rep is None or rep.get("status") != "ok" or rep.get("resume_key") != resume_key:
        return None
    return rep


class Terminated(KeyboardInterrupt):
    """SIGTERM (a scheduler, `docker stop`, `timeout`) turned into an exception by a long command, so it stops as on
    Ctrl-C: its work saved, its report "interrupted", its locks released (`livescene train`)."""


class StageReport:
    """Collects what a stage did; use as a context manager around the stage's work.

    >>> with StageReport(ds, "poses", settings={...}) as rep:
    ...     with rep.step("extract"):
    ...         ...
    ...     rep.figures["registered"] = 50
    ...     rep.warn("frames 120-160 did not register", cause="texture")
    """

    def __init__(self, root: str | Path, stage: str, inputs: dict | None = None, settings: dict | None = None,
                 resume_key: str | None = None):
        self.root = Path(root)
        self.stage = stage
        self.data: dict[str, Any] = {
            "stage": stage,
            "status": "running",
            "started": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "inputs": inputs or {},
            "settings": settings or {},
            "steps": {},
            "figures": {},
            "warnings": [],
            "host": {"python": sys.version.split()[0], "platform": platform.platform()},
        }
        if resume_key is not None:  # what `finished_with` compares a later run's inputs and settings against
            self.data["resume_key"] = resume_key
        self._t0 = time.perf_counter()

    @property
    def figures(self) -> dict[str, Any]:
        return self.data["figures"]

    @property
    def steps(self) -> dict[str, Any]:
        return self.data["steps"]

    def warn(self, message: str, cause: str | None = None, **extra: Any) -> None:
        entry = {"message": message, "cause": cause, **extra}
        self.data["warnings"].append(entry)

    @contextmanager
    def step(self, name: str) -> Iterator[dict[str, Any]]:
        info: dict[str, Any] = {}
        t0 = time.perf_counter()
        try:
            yield info
        finally:
            info["wall_s"] = round(time.perf_counter() - t0, 4)
            self.data["steps"][name] = info

    def write(self) -> None:
        atomic.write_json(report_path(self.root, self.stage), self.data)

    def __enter__(self) -> "StageReport":
        # a report's temporary file left by a killed run (atomic writes rename it into place when they finish)
        for tmp in report_path(self.root, self.stage).parent.glob(f".{self.stage}.json.*.tmp"):
            try:
                tmp.unlink()
            except OSError:
                pass
        self.write()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.data["wall_s"] = round(time.perf_counter() - self._t0, 3)
        if exc is None:
            self.data["status"] = "ok"
        elif issubclass(exc_type, KeyboardInterrupt):  # Ctrl-C, or SIGTERM turned into one (`Terminated`)
            self.data["status"] = "interrupted"
            self.data["error"] = str(exc) or "interrupted (Ctrl-C)"
        else:
            self.data["status"] = "failed"
            self.data["error"] = f"{exc_type.__name__}: {exc}"
        self.write()
