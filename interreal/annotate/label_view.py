"""The labels as the annotation app shows and edits them: readable states and the entries that are not (kept raw,
so a hand-made mistake is listed and can be overwritten instead of breaking the page)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from .. import labels as L
from ..dataset import label_value_problem
from ..errors import InputError
from ..layout import LABELS_FILE

_EPS = 1e-6


class Conflict(Exception):
    """Another writer changed an item this edit was based on; nothing was written."""


@dataclass(frozen=True)
class BadLabel:
    """An entry of key_frame_value.yaml that is not a state in [0, 1] (object '' = the whole frame entry)."""

    frame: str
    object: str
    value: Any
    problem: str

    def as_json(self) -> dict[str, str]:
        shown = repr(self.value)
        return {"frame": self.frame, "object": self.object, "value": shown[:80] + ("…" if len(shown) > 80 else ""),
                "problem": f"{LABELS_FILE}: {self.frame}{': ' + self.object if self.object else ''}: {self.problem}"}


def finite_number(value: Any) -> bool:
    """A number (not true/false) that is a finite float; False for a 400-digit integer too."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def _label_problem(value: Any) -> str:
    """Why a raw YAML label value is not a usable state, with what to do ('' when it is one)."""
    try:
        why = label_value_problem(value)
    except OverflowError:  # a 400-digit integer
        why = f"{str(value)[:20]}... is not a finite number"
    return f"{why}: set the state again (0 = closed ... 1 = open) or clear it" if why else ""


def split_labels(raw: dict[str, Any]) -> tuple[dict[str, dict[str, float]], dict[tuple[str, str], "BadLabel"]]:
    """(every label that is a state in [0, 1], the entries that are not, kept raw) of the labels as stored."""
    good: dict[str, dict[str, float]] = {}
    bad: dict[tuple[str, str], BadLabel] = {}
    for key, entry in raw.items():
        if not isinstance(entry, dict):
            bad[(key, "")] = BadLabel(key, "", entry, "expected {object name: value}")
            continue
        for name, value in entry.items():
            problem = _label_problem(value)
            if problem:
                bad[(key, name)] = BadLabel(key, name, value, problem)
            else:
                good.setdefault(key, {})[name] = float(value)
    return good, bad


def same_state(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return abs(float(a) - float(b)) <= _EPS


def parse_label_edit(e: Any, mapping: dict[int, str], frames: dict[int, str], current: dict[str, dict[str, float]]
                     ) -> tuple[str, str, float | None, str]:
    """(frame key, object, value or None = unset, conflict: '' or why the page's `base` is stale) of one edit
    {frame, object, value, base} from the page; InputError / Conflict on an edit that cannot apply."""
    if not isinstance(e, dict):
        raise InputError(f"edit {str(e)[:80]!r} is not an object {{frame, object, value, base}}")
    name = e.get("object")
    if not isinstance(name, str):
        raise InputError(f"edit {str(e)[:80]!r}: 'object' must be an object name (a string)")
    if name not in mapping.values():  # the page only offers existing objects: its view is stale
        raise Conflict(f"unknown object {name!r} (renamed in another tab?): reload the page")
    frame = e.get("frame")
    if isinstance(frame, bool) or not isinstance(frame, (int, str)) or not str(frame).isascii():
        raise InputError(f"edit of {name!r}: 'frame' {str(frame)[:40]!r} is not a frame (give its number "
                         f"in ASCII digits, e.g. 42, or its name, e.g. frame_00042)")
    key = L.resolve_frame(frames, frame)
    value = e.get("value")
    if isinstance(value, (bool, list, dict)):
        raise InputError(f"{name} @ {key}: 'value' must be a number in [0, 1] or null, not {value!r:.40}")
    try:
        value = None if value is None else L.normalise_value(value, where=f"{name} @ {key}")
    except OverflowError:
        raise InputError(f"{name} @ {key}: {value} is outside [0, 1]") from None
    base = e.get("base")
    if base is not None and not finite_number(base):
        raise InputError(f"{name} @ {key}: 'base' {str(base)[:40]!r} must be the number the page read, "
                         f"or null when there was no label")
    base = None if base is None else float(base)
    now = current.get(key, {}).get(name)  # a bad (non-numeric) entry reads as no label: it can be set
    if same_state(now, base):
        return key, name, value, ""
    was = "no label" if base is None else f"{base:.3f}"
    is_ = "removed" if now is None else f"{now:.3f}"
    return key, name, value, f"{name} on {key} was changed elsewhere ({was} -> {is_}) since this page read it"
