"""The one place for the dataset's conventions: frame naming, mask layout, camera axes.

- Frames are named `frame_<source index, 5 digits>`; the frame id is the last `_` token of the stem
  (that is what the official LiveScene reader uses), so `frame_00042.png` -> "00042".
- Masks: `masks/<fid>.npy`, bool (H, W, objects + 1), exactly one channel true per pixel, background LAST.
  In memory and in compact PNG stores we use an index map: 0 = background, k = object id k - 1
  (the `--keyframes` PNG format; 255 = not annotated).
- Camera axes: OpenCV inside the code (x right, y down, looking along +z);
  OpenGL in transforms.json (x right, y up, looking along -z). Convert only at the edges.
- Part motions (`articulation.json`, optional): in transforms.json's world frame and units; an object's rest pose is
  its pose at state 0, and state s turns a hinge by s * range radians about its axis through its origin
  (right-hand rule) or moves a slide by s * range world units along its axis.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .layout import (  # noqa: F401 - the layout's names, also reachable here as before
    ARTICULATION_FILE,
    IMAGES_DIR,
    LABELS_FILE,
    MAPPING_FILE,
    MASKS_DIR,
    PROMPTS_FILE,
    REPORTS_DIR,
    TRANSFORMS_FILE,
)

FORBIDDEN_NAME_CHARS = ("=", "\n", "\r", "\t")  # '=' separates name and value in --state NAME=VALUE
MAX_NAME_LENGTH = 100


def object_name_problem(name: object) -> str | None:
    """Why `name` cannot name an object (what every command that takes names refuses), or None when it can."""
    text = str(name).strip() if name is not None else ""
    if not text:
        return "an object needs a non-empty name"
    bad = [c for c in FORBIDDEN_NAME_CHARS if c in text]
    if bad:
        return f"object name {text!r} contains {bad!r}; '=' separates name and value in --state NAME=VALUE"
    if len(text) > MAX_NAME_LENGTH:
        return f"object name {text[:20]!r}... is longer than {MAX_NAME_LENGTH} characters"
    return None


FRAME_PREFIX = "frame_"
FRAME_DIGITS = 5
UNANNOTATED = 255  # keyframe index-mask value for "not annotated"


def frame_name(index: int) -> str:
    """Image stem for a frame at `index` in the source video."""
    if index < 0:
        raise ValueError(f"frame index must be >= 0, got {index}")
    return f"{FRAME_PREFIX}{index:0{FRAME_DIGITS}d}"


def frame_id(path_or_stem: str | Path) -> str:
    """Frame id string (as the official reader derives it) from an image path, stem or label key."""
    return Path(str(path_or_stem)).stem.split("_")[-1]


def frame_index(fid: str | Path) -> int:
    """Integer frame number of a frame id, path or label key; ValueError when it does not parse."""
    token = frame_id(fid)
    if not token.isdigit():
        raise ValueError(f"frame id '{token}' (from '{fid}') is not a number")
    return int(token)


def fid_of_index(index: int) -> str:
    return f"{index:0{FRAME_DIGITS}d}"


def mask_file(root: Path, fid: str) -> Path:
    return Path(root) / MASKS_DIR / f"{fid}.npy"


def index_to_onehot(index_map: np.ndarray, n_objects: int) -> np.ndarray:
    """(H, W) int index map (0 = background, k = object k-1) -> (H, W, n_objects + 1) bool, background last."""
    if index_map.ndim != 2:
        raise ValueError(f"index map must be 2-D, got shape {index_map.shape}")
    out = np.zeros(index_map.shape + (n_objects + 1,), dtype=bool)
    for obj in range(n_objects):
        out[..., obj] = index_map == obj + 1
    out[..., n_objects] = index_map == 0
    return out


def onehot_to_index(onehot: np.ndarray) -> np.ndarray:
    """(H, W, objects + 1) one-hot (background last) -> (H, W) uint8 index map (0 = background). A pixel with no
    channel set (official data may have them) is UNANNOTATED, not object 0 as an argmax would say."""
    n_objects = onehot.shape[-1] - 1
    idx = np.argmax(onehot, axis=-1).astype(np.int32) + 1
    idx[idx == n_objects + 1] = 0
    idx[~onehot.any(axis=-1)] = UNANNOTATED
    return idx.astype(np.uint8)


_FLIP_YZ = np.diag([1.0, -1.0, -1.0, 1.0])


def opencv_to_opengl(c2w: np.ndarray) -> np.ndarray:
    """Camera-to-world (…, 4, 4) with OpenCV camera axes -> OpenGL camera axes (and back: it is an involution)."""
    return np.asarray(c2w, dtype=np.float64) @ _FLIP_YZ


opengl_to_opencv = opencv_to_opengl
