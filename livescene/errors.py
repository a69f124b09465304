"""Exceptions with user-facing messages; the CLI prints them without a traceback."""

from __future__ import annotations

import errno
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from interreal.errors import InterRealError, MissingExtraError  # noqa: F401 - one error hierarchy for both CLIs


class LiveSceneError(InterRealError):
    """An expected failure of training, rendering, evaluation or grounding."""


class DivergenceError(LiveSceneError):
    """Training produced NaN/inf or diverged and could not be rolled back."""

    exit_code = 3


class InvalidDatasetError(LiveSceneError):
    """The dataset does not pass `interreal validate`: livescene refuses it (there is no override)."""


class ConfigError(LiveSceneError):
    """A training setting has the wrong type or is out of range."""


class CheckpointError(LiveSceneError):
    """No readable checkpoint where one is needed."""


class OutputError(LiveSceneError):
    """An output could not be written (disk full, read-only or permission denied)."""


# errors of the place being written to, not of the program: one line names the file and the cause
WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOTDIR, errno.EISDIR,
                errno.EFBIG, errno.ENAMETOOLONG}


def describe_write_error(exc: OSError, what: str | Path) -> str:
    """'cannot write X: No space left on device (free space ...)' for an OSError raised while writing `what`."""
    where = exc.filename or what
    hint = {errno.ENOSPC: "free some space or write elsewhere", errno.EDQUOT: "the disk quota is full",
            errno.EROFS: "the file system is read-only: write elsewhere"}.get(exc.errno or 0,
                                                                               "check the folder's permissions or write elsewhere")
    return f"cannot write {where}: {exc.strerror or exc} ({hint})"


@contextmanager
def writing(what: str | Path, cleanup: list[Path] | None = None) -> Iterator[None]:
    """Turn disk-full / permission errors while writing `what` into one OutputError; files listed in `cleanup`
    (partial outputs of this command) are removed first."""
    try:
        yield
    except OSError as exc:
        if exc.errno not in WRITE_ERRNOS:
            raise
        for p in cleanup or []:
            try:
                Path(p).unlink()
            except OSError:
                pass
        raise OutputError(describe_write_error(exc, what)) from exc
