"""Ctrl-C and SIGTERM while training: the run stops after the current step with a checkpoint and an "interrupted"
report (`Trainer._loop` checks `stop_signal` between steps); a second signal, or one while loading, stops at once."""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from typing import Any, Iterator

from interreal.report import Terminated


@contextlib.contextmanager
def stop_signals(holder: list[Any]) -> Iterator[None]:
    """Ctrl-C and SIGTERM stop the trainer in `holder` (once it is there: `in_loop`, `stop_signal`) after its current
    step; a second one, or one during loading, stops at once (KeyboardInterrupt / `Terminated`). Main thread only
    (elsewhere signals cannot be caught, and nothing changes)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):  # noqa: ARG001 - the signal module's signature
        name = "SIGTERM" if signum == signal.SIGTERM else "Ctrl-C"
        trainer = holder[0] if holder else None
        if trainer is not None and trainer.in_loop and trainer.stop_signal is None:
            trainer.stop_signal = name
            print(f"\nlivescene train: {name}: stopping after this step (again to stop at once)", file=sys.stderr)
            return
        raise Terminated("terminated (SIGTERM)") if name == "SIGTERM" else KeyboardInterrupt()

    before = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in before.items():
            signal.signal(s, h)
