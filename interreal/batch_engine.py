"""Where `interreal batch` runs its stages: a local pool of worker slots, or Ray (the `scale` extra).

Every stage is a child process (`python -m interreal process ...`, `python -m livescene train ...`): a stage that
crashes hard (a segfault in a native library, the kernel's OOM killer) takes only its own process down and is reported
with its exit status, while the other captures go on; its output goes to a log file beside the capture's results.
The two engines share `run_stage`; they differ only in who schedules the stages:

- `LocalEngine`: N worker slots on this machine; a capture's stages run one after another in its slot, a stage that
  asks for a GPU waits for a free one (CUDA_VISIBLE_DEVICES names it).
- `RayEngine`: one Ray task per stage with the stage's resource hints (CPUs for process, a GPU for train when the
  cluster has one); train waits on its capture's process task. A local Ray instance by default, `address` joins a
  cluster (whose nodes must see the output folder and have the same environment).
"""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
import threading
import time
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

from .errors import InputError, MissingExtraError

THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS",
               "OPENCV_FOR_THREADS_NUM")  # OMP_NUM_THREADS also bounds pycolmap (interreal.sfm.colmap.threads)


@dataclass
class StageCommand:
    """One stage of one capture: the command line to run and what it needs (resource hints)."""

    capture: str
    stage: str
    argv: list[str]
    log: str
    cpus: int = 1
    gpus: int = 0


@dataclass
class StageResult:
    capture: str
    stage: str
    ok: bool
    wall_s: float
    returncode: int | None
    error: str | None = None
    log: str = ""
    host: str = ""


@dataclass
class CaptureJob:
    """The stages of one capture, in order: a stage runs only when the one before it succeeded."""

    name: str
    stages: list[StageCommand] = field(default_factory=list)


Event = Callable[[str, str, str, "StageResult | None"], None]  # (capture, stage, "start" | "end", result)

# `interreal process: error: ...` / `livescene train: error: ...`: the one line an expected failure prints
_ERROR_LINE = re.compile(r"^\S+(?: \S+)?: error: .+")


def stage_error(log_text: str, returncode: int) -> str:
    """The reason a stage failed: its error message (the `...: error: ...` line and the lines of the same message
    after it) when it printed one, else its exit status and last line."""
    lines = [ln.strip() for ln in re.split(r"[\r\n]+", log_text) if ln.strip()]
    for i in range(len(lines) - 1, -1, -1):
        if _ERROR_LINE.match(lines[i]):
            message = " ".join(lines[i: i + 5])
            return message if len(message) <= 600 else message[:597] + "..."
    how = f"killed by signal {-returncode}" if returncode < 0 else f"exit status {returncode}"
    last = lines[-1] if lines else ""
    return how + (f": {last[:300]}" if last else " (no output)")


def run_stage(cmd: StageCommand, env: dict[str, str] | None = None) -> StageResult:
    """Run one stage as a child process, its output in `cmd.log`; never raises for the stage's own failure."""
    log = Path(cmd.log)
    log.parent.mkdir(parents=True, exist_ok=True)
    child_env = {**os.environ, **{v: str(max(cmd.cpus, 1)) for v in THREAD_VARS}, **(env or {})}
    t0 = time.perf_counter()
    try:
        with open(log, "w", encoding="utf-8") as fh:
            fh.write("$ " + " ".join(cmd.argv) + "\n")
            fh.flush()
            proc = subprocess.run(cmd.argv, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                  env=child_env, check=False)
    except OSError as exc:  # the interpreter itself could not start
        return StageResult(cmd.capture, cmd.stage, False, time.perf_counter() - t0, None,
                           f"could not start {cmd.argv[0]}: {exc}", str(log), os.uname().nodename)
    wall = time.perf_counter() - t0
    error = None
    if proc.returncode != 0:
        error = stage_error(log.read_text(encoding="utf-8", errors="replace"), proc.returncode)
    return StageResult(cmd.capture, cmd.stage, proc.returncode == 0, round(wall, 3), proc.returncode, error,
                       str(log), os.uname().nodename)


def skipped(cmd: StageCommand, why: str) -> StageResult:
    return StageResult(cmd.capture, cmd.stage, False, 0.0, None, why, cmd.log)


def local_gpus() -> list[str]:
    """GPU ids this machine offers (CUDA_VISIBLE_DEVICES, else `nvidia-smi -L`), without importing torch."""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        return [g for g in visible.split(",") if g.strip() and g.strip() != "-1"]
    if shutil.which("nvidia-smi") is None:
        return []
    try:
        out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=20, check=False).stdout
    except (OSError, subprocess.SubprocessError):
        return []
    return [str(i) for i, ln in enumerate(out.splitlines()) if ln.startswith("GPU ")]


class LocalEngine:
    """`workers` slots on this machine; each capture's stages run in order in one slot."""

    name = "local"

    def __init__(self, workers: int):
        if workers < 1:
            raise InputError(f"--workers {workers}: give at least 1")
        self.workers = workers
        self.cpus = os.cpu_count() or 1
        self._gpus = local_gpus()
        self._free_gpus = list(self._gpus)
        self._gpu_lock = threading.Condition()

    def describe(self) -> str:
        return (f"local pool: {self.workers} worker{'s' if self.workers > 1 else ''} on {self.cpus} CPUs"
                + (f", {len(self._gpus)} GPU{'s' if len(self._gpus) > 1 else ''}" if self._gpus else ""))

    def gpu_count(self) -> int:
        return len(self._gpus)

    def _run(self, cmd: StageCommand) -> StageResult:
        if cmd.gpus <= 0 or not self._gpus:
            return run_stage(cmd)
        with self._gpu_lock:  # one stage per GPU at a time, as Ray's num_gpus=1
            while len(self._free_gpus) < cmd.gpus:
                self._gpu_lock.wait()
            taken = [self._free_gpus.pop(0) for _ in range(cmd.gpus)]
        try:
            return run_stage(cmd, env={"CUDA_VISIBLE_DEVICES": ",".join(taken)})
        finally:
            with self._gpu_lock:
                self._free_gpus.extend(taken)
                self._gpu_lock.notify_all()

    def _job(self, job: CaptureJob, event: Event) -> list[StageResult]:
        results: list[StageResult] = []
        for cmd in job.stages:
            if results and not results[-1].ok:
                results.append(skipped(cmd, f"not run: {results[-1].stage} failed"))
                continue
            event(job.name, cmd.stage, "start", None)
            res = self._run(cmd)
            results.append(res)
            event(job.name, cmd.stage, "end", res)
        return results

    def run(self, jobs: list[CaptureJob], event: Event) -> Iterator[tuple[CaptureJob, list[StageResult]]]:
        """Yields each capture's results as soon as its last stage ends (in finishing order)."""
        with ThreadPoolExecutor(max_workers=self.workers, thread_name_prefix="batch") as pool:
            pending: dict[Future, CaptureJob] = {pool.submit(self._job, job, event): job for job in jobs}
            try:
                while pending:
                    done, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for fut in done:
                        yield pending.pop(fut), fut.result()
            except BaseException:
                for fut in pending:
                    fut.cancel()
                raise

    def close(self) -> None:
        pass


def _ray():
    try:
        import ray
    except ModuleNotFoundError as exc:
        if exc.name != "ray":
            raise
        raise MissingExtraError("scale", "the Ray engine (--engine ray / --address)") from None
    return ray


def ray_available() -> bool:
    return importlib.util.find_spec("ray") is not None


def _ray_stage(cmd: dict[str, Any], before: dict[str, Any] | None = None) -> dict[str, Any]:
    """A Ray task: one stage (skipped when the stage before it failed). Plain dicts cross the wire."""
    stage = StageCommand(**cmd)
    if before is not None and not before["ok"]:
        return asdict(skipped(stage, f"not run: {before['stage']} failed"))
    return asdict(run_stage(stage))  # with num_gpus, Ray set CUDA_VISIBLE_DEVICES here: the child inherits it


class RayEngine:
    """One Ray task per stage, with its resource hints; a local Ray instance unless `address` is given."""

    name = "ray"

    def __init__(self, workers: int, address: str | None = None):
        ray = _ray()
        if workers < 1:
            raise InputError(f"--workers {workers}: give at least 1")
        self.address = address
        self.workers = workers
        if not ray.is_initialized():
            kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False,
                                      "configure_logging": False}
            if address:
                ray.init(address=address, **kwargs)
            else:
                ray.init(num_cpus=os.cpu_count() or 1, num_gpus=len(local_gpus()), **kwargs)
        self._ray = ray
        res = ray.cluster_resources()
        self.cpus = int(res.get("CPU", 1))
        self._gpus = int(res.get("GPU", 0))
        self._task = ray.remote(_ray_stage)

    def describe(self) -> str:
        where = f"Ray cluster at {self.address}" if self.address else "local Ray instance"
        return f"{where}: {self.cpus} CPUs" + (f", {self._gpus} GPUs" if self._gpus else "")

    def gpu_count(self) -> int:
        return self._gpus

    def run(self, jobs: list[CaptureJob], event: Event) -> Iterator[tuple[CaptureJob, list[StageResult]]]:
        """Submits every stage at once (Ray schedules them by their resources); reports each stage as it ends and
        yields each capture once its last stage has ended."""
        ray = self._ray
        stage_of: dict[Any, tuple[CaptureJob, int]] = {}
        results: dict[str, list[Any]] = {}
        for job in jobs:
            refs: list[Any] = []
            for i, cmd in enumerate(job.stages):
                opts = {"num_cpus": max(cmd.cpus, 1), "num_gpus": cmd.gpus if self._gpus else 0, "max_retries": 1}
                refs.append(self._task.options(**opts).remote(asdict(cmd), refs[-1] if refs else None))
                stage_of[refs[-1]] = (job, i)
            results[job.name] = [None] * len(refs)
            event(job.name, job.stages[0].stage, "start", None)  # submitted: Ray starts it when a CPU is free
        try:
            while stage_of:
                done, _ = ray.wait(list(stage_of), num_returns=1)
                for ref in done:
                    job, i = stage_of.pop(ref)
                    res = StageResult(**ray.get(ref))
                    results[job.name][i] = res
                    event(job.name, res.stage, "end", res)
                    if i + 1 < len(job.stages) and res.ok:
                        event(job.name, job.stages[i + 1].stage, "start", None)
                    if all(r is not None for r in results[job.name]):
                        yield job, results.pop(job.name)
        except BaseException:
            for ref in stage_of:
                ray.cancel(ref, force=True)
            raise

    def close(self) -> None:
        if not self.address:
            self._ray.shutdown()
