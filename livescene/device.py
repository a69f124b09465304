"""Device choice: CUDA when present (auto), CPU otherwise; a clear error when CUDA is asked for and absent."""

from __future__ import annotations

import os
import statistics
import sys
import time
from pathlib import Path

import torch

from .errors import LiveSceneError


def select_device(name: str | torch.device | None = "auto") -> torch.device:
    if isinstance(name, torch.device):
        return name
    name = (name or "auto").lower()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise LiveSceneError("--device cuda was asked for but torch sees no CUDA device; use --device cpu or auto")
        return torch.device(name)
    if name == "cpu":
        return torch.device("cpu")
    raise LiveSceneError(f"unknown device {name!r}: use auto, cpu or cuda")


def describe(device: torch.device) -> str:
    if device.type == "cuda":
        return f"cuda ({torch.cuda.get_device_name(device)})"
    return f"cpu ({torch.get_num_threads()} threads)"


def configure_threads(threads: int = 0) -> int:
    """Set torch's CPU threads. 0 = auto: all cores, or 1 when the machine is already busy (load average above
    half the cores): OpenMP workers that wait on descheduled siblings made a shared 2-core machine 10-100x
    slower per step than one thread. Returns the number used."""
    if threads <= 0:
        cores = os.cpu_count() or 1
        others = other_processes_cores()
        if others is None:  # no /proc: the load average (which also counts this process's own recent work)
            try:
                others = os.getloadavg()[0]
            except OSError:
                others = 0.0
        threads = 1 if others > 0.5 * cores else cores
    torch.set_num_threads(threads)
    return threads


def other_processes_cores(window: float = 0.5) -> float | None:
    """Cores busy with other processes right now (Linux /proc; None elsewhere).

    Not the load average: after `interreal process` ran SfM in this very process, the 1-minute average still reads
    about 2 on a quiet machine, and the trainer would wrongly drop to one thread.
    """
    def busy_total() -> int:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:9]]
        return v[0] + v[1] + v[2] + v[5] + v[6] + v[7]  # user nice system irq softirq steal (not idle, iowait)

    def busy_self() -> int:
        with open("/proc/self/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return int(fields[11]) + int(fields[12])  # utime + stime

    try:
        t0, s0 = busy_total(), busy_self()
        time.sleep(window)
        t1, s1 = busy_total(), busy_self()
        return max(0.0, ((t1 - t0) - (s1 - s0)) / os.sysconf("SC_CLK_TCK") / window)
    except (OSError, ValueError, IndexError):
        return None


class ThreadTrial:
    """Measure, not guess, the thread count: the first training steps run in alternating blocks at `many` threads
    and at 1 (real steps, none wasted), and the faster per-step median is kept. A busy shared machine can make many
    threads several times slower than one (1.3-1.9 vs 8.4 steps/s on a loaded 2-core box), and no reading of the
    load beforehand tells reliably; a few seconds of timing does.

    Use: `threads = trial.before_step()` before each step, `trial.after_step(seconds)` after it, until `done`."""

    def __init__(self, many: int, block: int = 3, blocks: int = 4, max_s: float = 4.0):
        # one untimed step at each (allocations, thread pools), then blocks from 1 thread up: when many threads are
        # the slow choice, `max_s` ends the trial after one of their blocks
        self.many, self.warmup, self.max_s = many, 2, max_s
        self.plan = [many, 1] + [n for b in range(blocks) for n in ([1, many][b % 2],) * block]
        self.times: dict[int, list[float]] = {many: [], 1: []}
        self.spent = 0.0
        self.chosen: int | None = None if many > 1 else many
        self.medians: dict[int, float] = {}

    @property
    def done(self) -> bool:
        return self.chosen is not None

    def before_step(self) -> int:
        n = self.plan[0] if self.plan and not self.done else (self.chosen or self.many)
        if torch.get_num_threads() != n:
            torch.set_num_threads(n)
        return n

    def after_step(self, seconds: float) -> None:
        if self.done or not self.plan:
            return
        n = self.plan.pop(0)
        self.spent += seconds
        if self.warmup > 0:  # the first steps pay for allocations and thread pools: not timed
            self.warmup -= 1
        else:
            self.times[n].append(seconds)
        if not self.plan or (self.spent > self.max_s and all(self.times.values())):
            self._decide()

    def _decide(self) -> None:
        med = {n: statistics.median(t) for n, t in self.times.items() if t}
        self.chosen = min(med, key=med.get) if med else self.many
        self.medians = med
        torch.set_num_threads(self.chosen)

    def summary(self) -> str:
        med = self.medians
        rates = ", ".join(f"{n} thread{'s' if n > 1 else ''} {1 / t:.1f} steps/s" for n, t in sorted(med.items()))
        return f"threads: measured {rates}: kept {self.chosen}"


JEMALLOC = "/usr/lib/x86_64-linux-gnu/libjemalloc.so.2"
JEMALLOC_ENV = "LIVESCENE_JEMALLOC"


def jemalloc_loaded() -> bool:
    try:
        return "jemalloc" in Path("/proc/self/maps").read_text()
    except OSError:
        return "jemalloc" in os.environ.get("LD_PRELOAD", "")


def reexec_with_jemalloc(command: tuple[str, str] | None = None) -> None:
    """Opt-in (LIVESCENE_JEMALLOC=1): re-run this process, same command line, under jemalloc.

    It was the default while an earlier setup measured it 1.6-2x faster at large batches (glibc's allocator paid
    page faults there). On this repository's machine now (torch 2.13, kernel 6.18) it is the slower one: the CPU
    preset trains at 3.7 steps/s with it and 5.6 without, 4096-ray batches at 0.67 and 1.30, rendering 1.6x slower.
    Measure before turning it on. `command` = (program, subcommand): only when the process was started as that
    command, so a CLI entry point called as a function (from a test, say) never re-executes its host."""
    if os.environ.get(JEMALLOC_ENV) != "1" or not os.path.exists(JEMALLOC) or jemalloc_loaded():
        return
    if command is not None:
        argv0 = Path(sys.argv[0]).name if sys.argv else ""
        if argv0 not in (command[0], "__main__.py") or sys.argv[1:2] != [command[1]]:
            return
    env = {**os.environ, "LD_PRELOAD": (JEMALLOC + " " + os.environ.get("LD_PRELOAD", "")).strip()}
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], env)  # loaded there: never loops
