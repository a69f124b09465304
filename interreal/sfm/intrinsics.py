"""Known camera intrinsics for `interreal poses DS --intrinsics FILE`: read, checked, scaled to the dataset's
images, and turned into COLMAP's OPENCV camera (fx, fy, cx, cy, k1, k2, p1, p2).

FILE is either
- text: a 3x3 K matrix, 9 numbers separated by spaces, commas or new lines (as classic benchmarks ship K.txt;
  lines starting with # are comments);
- JSON: {"fx", "fy", "cx", "cy"} (or nerfstudio's "fl_x", "fl_y"; a transforms.json works), optional
  distortion "k1", "k2", "p1", "p2" (OpenCV's model) and optional "w", "h" (the image size K refers to); or
  {"K": 3x3} or a bare 3x3 list.

Which size K refers to: "w"/"h" in the JSON when given; else the size of the capture the frames were taken from
(`interreal frames` records it in DS/reports/frames.json, before any resize to --long-side); else the dataset's
own image size. K is scaled by (dataset size / that size); a different aspect ratio (a crop) is refused, and so
is a principal point outside the middle of the image it is said to refer to (K of another size).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..dataset.types import Intrinsics
from ..errors import InputError
from ..report import read_report

DISTORTION = ("k1", "k2", "p1", "p2")  # COLMAP's OPENCV model: what a fixed camera can carry
FORMAT = ('a 3x3 K matrix as text (9 numbers: "fx 0 cx  0 fy cy  0 0 1"), or JSON {"fx", "fy", "cx", "cy"} '
          '(optional "k1", "k2", "p1", "p2", and "w", "h": the image size K refers to), {"K": [[...], ...]} '
          "or a 3x3 list")
ASPECT_TOL = 0.01  # relative: resizing keeps the aspect ratio to rounding (1 px in 100)
CENTRE_BAND = (0.2, 0.8)  # the principal point lies in this band of the image K refers to (a lens is centred to a
# few %; K of an image twice as large puts it at the edge)


@dataclass(frozen=True)
class KnownIntrinsics:
    """A pinhole K with OpenCV distortion, in pixels of an image of `size` (w, h; None = not said)."""

    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    size: tuple[int, int] | None = None
    source: str = ""

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def colmap_params(self) -> str:
        """COLMAP's OPENCV parameters as its comma list (ImageReaderOptions.camera_params)."""
        return ",".join(repr(float(v)) for v in (self.fx, self.fy, self.cx, self.cy, *self.dist))

    def to_json(self) -> dict:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                **dict(zip(DISTORTION, self.dist)), "w": None if self.size is None else self.size[0],
                "h": None if self.size is None else self.size[1], "source": self.source}


def read_intrinsics(path: str | Path) -> KnownIntrinsics:
    """K (and distortion, size) from a text or JSON file; InputError naming the file and the expected format."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"--intrinsics {path}: cannot read it ({exc}); expected {FORMAT}") from exc
    try:
        data = json.loads(text)
    except ValueError:
        data = None
    if data is None or isinstance(data, (int, float)):
        return _from_matrix(_numbers(text, path), path, None, {})
    if isinstance(data, list):
        return _from_matrix(_flat(data, path), path, None, {})
    if isinstance(data, dict):
        return _from_dict(data, path)
    raise InputError(f"--intrinsics {path}: unexpected JSON ({type(data).__name__}); expected {FORMAT}")


def _numbers(text: str, path: Path) -> list[float]:
    """The numbers of a text K (lines starting with # are comments)."""
    text = "\n".join(line for line in text.splitlines() if not line.lstrip().startswith("#"))
    tokens = [t for t in re.split(r"[\s,;\[\]()]+", text) if t]
    try:
        return [float(t) for t in tokens]
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise InputError(f"--intrinsics {path}: {bad!r} is not a number; expected {FORMAT}") from None


def _is_float(t: str) -> bool:
    try:
        float(t)
    except ValueError:
        return False
    return True


def _flat(data, path: Path) -> list[float]:
    try:
        arr = np.asarray(data, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"--intrinsics {path}: the matrix holds non-numbers; expected {FORMAT}") from None
    return arr.ravel().tolist()


def _from_matrix(values: list[float], path: Path, size: tuple[int, int] | None, dist: dict) -> KnownIntrinsics:
    if len(values) != 9:
        raise InputError(f"--intrinsics {path}: found {len(values)} numbers, a 3x3 K has 9; expected {FORMAT}")
    K = np.asarray(values, dtype=np.float64).reshape(3, 3)
    if not np.isfinite(K).all():
        raise InputError(f"--intrinsics {path}: K holds inf or NaN; expected {FORMAT}")
    if K[2, 2] == 0 or not np.allclose(K[2, :2], 0.0) or abs(K[1, 0]) > 1e-9:
        raise InputError(f"--intrinsics {path}: not a camera matrix (its last row must be 0 0 1 and K[1][0] 0): "
                         f"{K.tolist()}; expected {FORMAT}")
    K = K / K[2, 2]
    if abs(K[0, 1]) > 1e-6 * abs(K[0, 0]):
        raise InputError(f"--intrinsics {path}: skew {K[0, 1]:g} is not supported (COLMAP's cameras have none)")
    return _checked(K[0, 0], K[1, 1], K[0, 2], K[1, 2], dist, size, path)


def _from_dict(data: dict, path: Path) -> KnownIntrinsics:
    size = _size(data, path)
    dist = {k: data[k] for k in DISTORTION if k in data}
    extra = sorted(k for k in ("k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tauX", "tauY")
                   if data.get(k) not in (None, 0, 0.0))
    if extra:
        raise InputError(f"--intrinsics {path}: distortion {extra} is not supported (OPENCV model: k1, k2, p1, p2 "
                         "only); undistort the images first or leave --intrinsics out")
    if "K" in data:
        return _from_matrix(_flat(data["K"], path), path, size, dist)
    fx, fy = data.get("fx", data.get("fl_x")), data.get("fy", data.get("fl_y", data.get("fx", data.get("fl_x"))))
    missing = [k for k, v in (("fx", fx), ("cx", data.get("cx")), ("cy", data.get("cy"))) if v is None]
    if missing:
        raise InputError(f"--intrinsics {path}: JSON without {', '.join(missing)}; expected {FORMAT}")
    return _checked(fx, fy, data["cx"], data["cy"], dist, size, path)


def _size(data: dict, path: Path) -> tuple[int, int] | None:
    w, h = data.get("w", data.get("width")), data.get("h", data.get("height"))
    if w is None and h is None:
        return None
    try:
        size = (int(w), int(h))
    except (TypeError, ValueError):
        raise InputError(f"--intrinsics {path}: \"w\" and \"h\" must both be whole numbers of pixels, "
                         f"got {w!r}, {h!r}") from None
    if min(size) <= 0:
        raise InputError(f"--intrinsics {path}: image size {size} must be positive")
    return size


def _checked(fx, fy, cx, cy, dist: dict, size, path: Path) -> KnownIntrinsics:
    try:
        vals = [float(v) for v in (fx, fy, cx, cy)]
        d = tuple(float(dist.get(k, 0.0)) for k in DISTORTION)
    except (TypeError, ValueError):
        raise InputError(f"--intrinsics {path}: fx, fy, cx, cy and the distortion must be numbers; "
                         f"expected {FORMAT}") from None
    if not np.isfinite(vals + list(d)).all() or vals[0] <= 0 or vals[1] <= 0:
        raise InputError(f"--intrinsics {path}: the focal lengths must be positive numbers (fx={fx}, fy={fy})")
    return KnownIntrinsics(*vals, dist=d, size=size, source=str(path))  # type: ignore[arg-type]


def reference_size(known: KnownIntrinsics, ds: Path, image_size: tuple[int, int]) -> tuple[tuple[int, int], str]:
    """The image size K refers to and where that came from: the file's w/h, the capture's size recorded by
    `interreal frames` (before its resize), else the dataset's images."""
    if known.size is not None:
        return known.size, "the file's w/h"
    rep = read_report(ds, "frames") or {}
    info = (rep.get("inputs") or {}).get("source_info") or {}
    if info.get("width") and info.get("height"):
        return (int(info["width"]), int(info["height"])), "the capture's size in reports/frames.json"
    return image_size, "the dataset's images"


def scaled_to(known: KnownIntrinsics, ds: Path, image_size: tuple[int, int]) -> tuple[KnownIntrinsics, str]:
    """`known` in pixels of the dataset's images (w, h), and a note of the size it was taken to refer to.
    Scaling multiplies fx, cx by w / w_ref and fy, cy by h / h_ref (COLMAP's convention: pixel centres at +0.5,
    where a resize scales coordinates exactly); distortion coefficients are in normalised coordinates and stay."""
    (wr, hr), why = reference_size(known, ds, image_size)
    w, h = image_size
    if abs((w / h) / (wr / hr) - 1.0) > ASPECT_TOL:
        raise InputError(f"--intrinsics {known.source}: K refers to {wr}x{hr} images ({why}) but the dataset's are "
                         f"{w}x{h}, another aspect ratio (cropped?); give \"w\" and \"h\" of the images K belongs to "
                         "in a JSON file, or a K for these images")
    lo, hi = CENTRE_BAND
    if not (lo * wr < known.cx < hi * wr and lo * hr < known.cy < hi * hr):
        raise InputError(f"--intrinsics {known.source}: its principal point ({known.cx:g}, {known.cy:g}) is far from "
                         f"the centre of the {wr}x{hr} images it was taken to refer to ({why}): K belongs to images "
                         "of another size; give \"w\" and \"h\" in a JSON file")
    s = Intrinsics(wr, hr, known.fx, known.fy, known.cx, known.cy).scaled(w, h)  # the dataset's one scaling rule
    out = replace(known, fx=s.fl_x, fy=s.fl_y, cx=s.cx, cy=s.cy, size=(w, h))
    return out, f"K for {wr}x{hr} ({why}) scaled to {w}x{h}"
