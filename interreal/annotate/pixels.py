"""Pixels of the annotation app: index PNGs in and out, the per-object versions of a keyframe (what a merge-safe
edit compares), and the region of a polygon or box the page draws (a pixel is in when its centre is)."""

from __future__ import annotations

import hashlib
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from skimage.draw import polygon as fill_polygon

from ..dataset import decode_image
from ..errors import InputError
from ..layout import KEYFRAMES_DIR


def file_version(path: Path) -> str:
    """Content hash of a file ('0' when absent): the version a client read."""
    try:
        return hashlib.sha1(path.read_bytes()).hexdigest()[:16]
    except FileNotFoundError:
        return "0"


def mask_versions(index: np.ndarray | None) -> dict[str, str]:
    """Per index value (object id + 1, 0 = background): a hash of where that value is on the keyframe."""
    if index is None:
        return {}
    out = {}
    for v in np.unique(index):
        bits = np.packbits(index == v)
        out[str(int(v))] = hashlib.sha1(bits.tobytes()).hexdigest()[:12]
    return out


def png_bytes(index: np.ndarray) -> bytes:
    ok, enc = cv2.imencode(".png", np.ascontiguousarray(index.astype(np.uint8)))
    if not ok:
        raise OSError("could not encode PNG")
    return enc.tobytes()


def read_index_png(path: Path) -> np.ndarray | None:
    if not path.exists():
        return None
    try:
        img = decode_image(path)
    except IsADirectoryError:
        img = None
    if img is None or img.ndim not in (2, 3):
        raise InputError(f"{KEYFRAMES_DIR}/{path.name} is not a readable index PNG; delete it or fix it")
    return img[..., 0] if img.ndim == 3 else img


def png_bytes_rgb(rgb: np.ndarray) -> bytes:
    ok, enc = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    return enc.tobytes()


def rasterise(op: dict[str, Any], w: int, h: int) -> np.ndarray:
    """Bool (h, w) region of a polygon or box given in image pixel coordinates."""
    shape = op.get("shape", "polygon")
    pts = op.get("points")
    try:
        arr = np.asarray(pts, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("points must be a list of [x, y] pairs") from None
    if arr.ndim != 2 or arr.shape[1] != 2 or not np.all(np.isfinite(arr)) or len(arr) > 10000:
        raise InputError("points must be a list of finite [x, y] pairs (at most 10000)")
    if len(arr) and np.abs(arr).max() > 1e6:
        raise InputError("points must be image pixel coordinates (within a million pixels of the frame)")
    canvas = np.zeros((h, w), dtype=np.uint8)
    if shape == "box":
        if len(arr) != 2:
            raise InputError("a box needs two corner points")
        (x0, y0), (x1, y1) = arr.min(axis=0), arr.max(axis=0)
        x0, y0 = max(0, math.ceil(x0 - 0.5)), max(0, math.ceil(y0 - 0.5))
        x1, y1 = min(w, math.ceil(x1 - 0.5)), min(h, math.ceil(y1 - 0.5))
        canvas[y0:y1, x0:x1] = 1
    elif shape == "polygon":
        if len(arr) < 3:
            raise InputError("a polygon needs at least three points")
        # a pixel belongs to the shape when its centre (x + 0.5, y + 0.5) does, as for the box
        rr, cc = fill_polygon(arr[:, 1] - 0.5, arr[:, 0] - 0.5, shape=(h, w))
        canvas[rr, cc] = 1
    else:
        raise InputError(f"shape {shape!r}: use polygon or box")
    region = canvas.astype(bool)
    if not region.any():
        raise InputError("the shape covers no pixel of the frame")
    return region


def encode_index_png(index: np.ndarray) -> bytes:
    return png_bytes(index)
