"""Exceptions the toolkit raises on bad input or failed stages.

Every message says what was wrong and what to do; the CLI prints it without a traceback and exits non-zero.
"""

from __future__ import annotations


class InterRealError(Exception):
    """Base class: an expected failure with a message meant for the user."""

    exit_code = 2


class InputError(InterRealError):
    """The user's input (video, images, annotations, options) cannot be used."""


class LowParallaxError(InputError):
    """The capture cannot give poses: the camera turned in place or stood still (no parallax between frames)."""


class DatasetError(InterRealError):
    """A dataset folder is missing something or is inconsistent."""


class StageError(InterRealError):
    """A stage ran but could not produce a usable result (e.g. SfM registered too few frames)."""

    exit_code = 3


class MissingExtraError(InterRealError):
    """An optional dependency group is not installed."""

    def __init__(self, extra: str, what: str):
        super().__init__(
            f"{what} needs the optional extra '{extra}': pip install 'interreal[{extra}]' "
            f"(or re-run `bash .ci/setup`, which installs every extra)"
        )
