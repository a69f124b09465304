"""The click tool of the annotation app: the mask one object's clicks ask for on a keyframe.

The page sends every click of the session (since it last changed frame, object or tool) and the server answers
from them alone, so nothing about a session lives on the server: the prior the clicks refine is what the user sees
of the object now, i.e. its pixels on the keyframe (drawn, or the answer to the previous click), else its
propagated mask on that frame (DS/masks, or the transient layer for the ignore class), else nothing. That is the
loop `recipes/bench_masks.py --clicks` measures (`interreal.masks.clicks`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..conventions import UNANNOTATED, mask_file
from ..errors import DatasetError, InputError
from ..masks.clicks import as_clicks, check_clicks, segment
from ..transients import read_transient

MAX_CLICKS = 200  # a session's clicks; the simulated user of the benchmark needs at most 20


def check_object(oid: Any, mapping: dict[int, str], ignore_object: int) -> int:
    """The object id a click session is for; InputError (HTTP 400) naming it when there is no such object."""
    if isinstance(oid, bool) or not isinstance(oid, int):
        raise InputError(f"object {str(oid)[:40]!r} is not an object id (an integer: 0 for the first object)")
    if oid != ignore_object and oid not in mapping:
        have = ", ".join(f"{i} {n!r}" for i, n in sorted(mapping.items())) or "none yet"
        raise InputError(f"object id {oid} does not exist (objects: {have}; {ignore_object} = ignore): "
                         f"choose one of them or add the object first")
    return oid


def parse_clicks(raw: Any, w: int, h: int) -> list:
    """The session's clicks, each inside the w x h frame; InputError naming the first that is not."""
    if not isinstance(raw, list) or not raw:
        raise InputError("clicks must be a non-empty list of [x, y, positive] (positive: true on the object)")
    if len(raw) > MAX_CLICKS:
        raise InputError(f"{len(raw)} clicks; a session may have at most {MAX_CLICKS}: start again on this frame")
    clicks = as_clicks(raw)
    check_clicks(clicks, w, h)
    return clicks


def propagated(ds: Path, fid: str, oid: int, ignore_object: int, hw: tuple[int, int]) -> np.ndarray | None:
    """The object's propagated mask on this frame (the transient layer for the ignore class), or None."""
    if oid == ignore_object:
        try:
            return read_transient(ds, fid, hw)
        except DatasetError:
            return None  # `interreal validate` names a broken layer; the clicks work without it
    path = mask_file(ds, fid)
    try:
        onehot = np.load(path, allow_pickle=False) if path.is_file() else None
    except (ValueError, EOFError, OSError):
        return None
    if not isinstance(onehot, np.ndarray) or onehot.ndim != 3 or onehot.shape[:2] != hw or oid >= onehot.shape[2] - 1:
        return None
    return onehot[..., oid].astype(bool)


def click_region(index: np.ndarray, k: int, op: dict[str, Any], rgb: Callable[[], np.ndarray],
                 fallback: Callable[[], np.ndarray | None]) -> np.ndarray:
    """The object's new region on the keyframe: the clicks' mask over the prior (its pixels on the keyframe, else
    `fallback()`: its propagated mask). Pixels of other objects are not taken (the store keeps them)."""
    h, w = index.shape
    clicks = parse_clicks(op.get("clicks"), w, h)
    prior = index == k
    if not prior.any():
        prior = fallback()
    mask = segment(rgb(), clicks, prior)
    return mask & ((index == 0) | (index == k) | (index == UNANNOTATED))


__all__ = ["check_object", "parse_clicks", "propagated", "click_region", "MAX_CLICKS"]
