"""Exceptions with user-facing messages; the CLI prints them without a traceback."""

from __future__ import annotations

from interreal.errors import InterRealError, MissingExtraError  # noqa: F401 - one error hierarchy for both CLIs


class LiveSceneError(InterRealError):
    """An expected failure of training, rendering, evaluation or grounding."""


class DivergenceError(LiveSceneError):
    """Training produced NaN/inf or diverged and could not be rolled back."""

    exit_code = 3
