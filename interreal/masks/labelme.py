"""LabelMe keyframes (`DIR/<fid>.json`) as an index map: the one rasteriser, used by `interreal masks` and shown
by `interreal annotate`, so the app shows the mask the stage propagates.

`shapes[].label` = object name, `shape_type` polygon or rectangle. A polygon is filled as LabelMe itself draws it
(its outline included, points rounded to pixels). A rectangle means "the object is inside this box" and is cut
out with GrabCut (polygons win over boxes; boxes go largest first, so smaller ones win). A shape of the ignore
class (`interreal.transients`: ignore / person / hand / arm) paints 254 over everything, a rectangle of it whole.
Shapes drawn on the source video (another size, same aspect ratio) are scaled to the frames.
"""

from __future__ import annotations

import base64
import json
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from ..errors import InputError
from ..transients import IGNORE, is_ignore_label
from .appearance import grabcut


def same_aspect(a: tuple[int, int], b: tuple[int, int], tol: float = 0.01) -> bool:
    """Whether two (w, h) sizes are the same picture at another resolution (aspect ratios within `tol`)."""
    return abs((a[0] / a[1]) / (b[0] / b[1]) - 1.0) <= tol


def read_doc(path: Path) -> dict:
    """The LabelMe JSON document; InputError when it is not one."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, UnicodeDecodeError, RecursionError) as exc:
        if isinstance(exc, PermissionError):
            raise
        raise InputError(f"{path}: not valid LabelMe JSON ({exc}); re-save it from LabelMe") from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("shapes"), list):
        raise InputError(f"{path}: LabelMe JSON needs a 'shapes' list")
    return doc


def embedded_image(doc: dict) -> np.ndarray | None:
    """The RGB image a LabelMe file embeds (`imageData`, base64 PNG / JPEG), or None when it has none or it does
    not decode: what the person actually drew on."""
    data = doc.get("imageData")
    if not isinstance(data, str) or not data:
        return None
    try:
        raw = np.frombuffer(base64.b64decode(data, validate=False), np.uint8)
    except (ValueError, TypeError):
        return None
    img = cv2.imdecode(raw, cv2.IMREAD_COLOR) if raw.size else None
    return None if img is None else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def object_labels(paths: list[Path]) -> list[str]:
    """Object names in the order the files (and their shapes) first use them, the ignore class left out."""
    names: list[str] = []
    for p in paths:
        for shape in read_doc(p).get("shapes", []):
            label = str(shape.get("label", "")) if isinstance(shape, dict) else ""
            if label and label not in names and not is_ignore_label(label, []):
                names.append(label)
    return names


def rasterise(path: Path, size: tuple[int, int], names: list[str], image: Callable[[], np.ndarray] | None,
              strict: bool = True) -> np.ndarray:
    """(h, w) uint8 index map of a LabelMe file at frame size (w, h): 0 background, k = object k - 1, 254 ignore.

    `image()` gives the RGB frame (only rectangles need it). `strict` (the masks stage): any bad shape, overlap of
    two objects' polygons or an empty result raises InputError naming the file and what to fix; else (the
    annotation app, which only shows the file) such shapes are left out."""
    doc = read_doc(path)
    w, h = size
    scale = _scale(path, doc, size)
    polys = np.zeros((len(names), h, w), bool)
    ignore = np.zeros((h, w), bool)
    boxes: list[tuple[int, tuple[int, int, int, int]]] = []
    for i, shape in enumerate(doc["shapes"]):
        try:
            kind, k, region = _shape(path, i, shape, scale, size, names)
        except InputError:
            if strict:
                raise
            continue
        if kind == "ignore":
            ignore |= region
        elif kind == "polygon":
            polys[k] |= region
        else:
            boxes.append((k, region))
    if strict:
        _check_overlap(path, polys, names)
    index = np.zeros((h, w), np.uint8)
    for k in range(len(names)):
        index[polys[k]] = k + 1
    for k, box in sorted(boxes, key=lambda kb: -(kb[1][2] - kb[1][0]) * (kb[1][3] - kb[1][1])):
        if image is None:
            raise InputError(f"{path}: rectangles need the frame image to be refined")
        drawn = polys.any(0)
        inside = grabcut_box(image(), box, taken=drawn)
        index[inside & ~drawn] = k + 1
    index[ignore] = IGNORE  # a hand is in front of what it touches
    if strict and not index.any():
        raise InputError(f"{path}: empty annotation (no shape covers any pixel); draw the objects, or delete the file")
    return index


def _scale(path: Path, doc: dict, size: tuple[int, int]) -> tuple[float, float]:
    w, h = size
    dw, dh = doc.get("imageWidth"), doc.get("imageHeight")
    if dw is None or dh is None or (int(dw), int(dh)) == (w, h):
        return 1.0, 1.0
    if not same_aspect((int(dw), int(dh)), (w, h)):
        raise InputError(f"{path}: drawn on a {dw}x{dh} image but the frames are {w}x{h} (another aspect "
                         f"ratio); annotate DS/images/")
    return w / int(dw), h / int(dh)  # drawn on the source video: scale the shapes to the frames


def _shape(path: Path, i: int, shape, scale: tuple[float, float], size: tuple[int, int], names: list[str]):
    """("ignore", -1, pixels) | ("polygon", object, pixels) | ("rectangle", object, box) of one shape."""
    w, h = size
    label = str(shape.get("label", "")) if isinstance(shape, dict) else ""
    if is_ignore_label(label, names):
        return "ignore", -1, _ignore_shape(path, i, shape, scale, size)
    if label not in names:
        raise InputError(f"{path}: shape {i} has label '{label}', not an object name ({names}) nor the ignore "
                         f"class (ignore / person / hand / arm); fix the label or add the object to mapping.yaml")
    k = names.index(label)
    kind = shape.get("shape_type", "polygon") or "polygon"
    pts = _points(path, i, f"'{label}'", shape, scale)
    if kind == "polygon":
        m = np.zeros((h, w), np.uint8)
        cv2.fillPoly(m, [np.round(pts).astype(np.int32)], 1)
        if len(pts) < 3:
            raise InputError(f"{path}: polygon {i} ('{label}') has {len(pts)} point(s); a polygon needs 3 or more")
        x, y = pts[:, 0], pts[:, 1]
        if abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))) / 2 < 0.5:  # shoelace area, px^2
            raise InputError(f"{path}: polygon {i} ('{label}') has no area (its points lie on a line)")
        if not m.any():
            lo, hi = pts.min(0), pts.max(0)
            if hi[0] < 0 or hi[1] < 0 or lo[0] >= w or lo[1] >= h:
                raise InputError(f"{path}: polygon {i} ('{label}') lies wholly outside the {w}x{h} frame (x "
                                 f"{lo[0]:.0f}..{hi[0]:.0f}, y {lo[1]:.0f}..{hi[1]:.0f}): was it drawn on another "
                                 f"image? Annotate DS/images/")
            raise InputError(f"{path}: polygon {i} ('{label}') covers no pixel (smaller than one): draw it larger")
        return "polygon", k, m > 0
    if kind == "rectangle":
        if len(pts) != 2:
            raise InputError(f"{path}: rectangle {i} ('{label}') needs 2 corner points")
        x0, y0 = np.clip(np.floor(pts.min(0)), 0, [w - 1, h - 1]).astype(int)
        x1, y1 = np.clip(np.ceil(pts.max(0)), 0, [w, h]).astype(int)
        if x1 - x0 < 3 or y1 - y0 < 3:
            raise InputError(f"{path}: rectangle {i} ('{label}') is empty (under 3 px on a side)")
        return "rectangle", k, (int(x0), int(y0), int(x1), int(y1))
    raise InputError(f"{path}: shape {i} ('{label}') is a {kind}; use polygons or rectangles")


def _points(path: Path, i: int, what: str, shape: dict, scale: tuple[float, float]) -> np.ndarray:
    try:
        pts = np.asarray(shape["points"], dtype=np.float64).reshape(-1, 2) * np.asarray(scale)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: shape {i} ({what}) has no usable points ({exc})") from exc
    if not np.all(np.isfinite(pts)):
        raise InputError(f"{path}: shape {i} ({what}) has non-finite points")
    return pts


def _ignore_shape(path: Path, i: int, shape, scale: tuple[float, float], size: tuple[int, int]) -> np.ndarray:
    """The pixels of one ignore-class shape (a polygon, or a rectangle taken whole: it is only left out)."""
    w, h = size
    kind = shape.get("shape_type", "polygon") or "polygon"
    try:
        pts = np.asarray(shape["points"], dtype=np.float64).reshape(-1, 2) * np.asarray(scale)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: shape {i} (ignore) has no usable points ({exc})") from exc
    if not np.all(np.isfinite(pts)) or kind not in ("polygon", "rectangle") or len(pts) < (3 if kind == "polygon" else 2):
        raise InputError(f"{path}: shape {i} (ignore) must be a polygon of 3+ finite points or a 2-point rectangle")
    m = np.zeros((h, w), np.uint8)
    if kind == "polygon":
        cv2.fillPoly(m, [np.round(pts).astype(np.int32)], 1)
    else:
        (x0, y0), (x1, y1) = np.floor(pts.min(0)).astype(int), np.ceil(pts.max(0)).astype(int)
        m[max(y0, 0):max(y1, 0), max(x0, 0):max(x1, 0)] = 1
    return m > 0


def _check_overlap(path: Path, polys: np.ndarray, names: list[str]) -> None:
    for a in range(len(names)):
        for b in range(a + 1, len(names)):
            both = polys[a] & polys[b]
            if both.any():
                ys, xs = np.nonzero(both)
                raise InputError(
                    f"{path}: polygons of '{names[a]}' and '{names[b]}' overlap on {len(xs)} pixels "
                    f"(x {xs.min()}..{xs.max()}, y {ys.min()}..{ys.max()}); objects are exclusive: "
                    f"cut one polygon back so each pixel belongs to one object")


def grabcut_box(image: np.ndarray, box: tuple[int, int, int, int], taken: np.ndarray | None = None,
                iterations: int = 4) -> np.ndarray:
    """Object mask inside `box` (x0, y0, x1, y1) by GrabCut; pixels in `taken` are forced background."""
    h, w = image.shape[:2]
    x0, y0, x1, y1 = box
    mask = np.full((h, w), cv2.GC_BGD, np.uint8)
    mask[y0:y1, x0:x1] = cv2.GC_PR_FGD
    if taken is not None:
        mask[taken] = cv2.GC_BGD
    box_only = mask == cv2.GC_PR_FGD
    out = grabcut(image, mask, iterations)
    if out is None:
        return box_only  # too little background to model colour: keep the box
    if not out.any():
        out = box_only
    return out
