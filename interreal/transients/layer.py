"""The transient layer: pixels that are no object and not static (people, hands, arms), kept out of SfM, motions
and training's losses.

Layout (beside the official files, which stay exactly as they are: the official reader never sees this folder):
`DS/transients/<fid>.png`, 8-bit single channel, 255 = transient, 0 = not, the image's size. A frame without a
file has no transient pixel. In `masks/<fid>.npy` transient pixels are background (the one-hot layout has no other
place for them); readers that honour the layer (SfM, motions, livescene) leave them out.

Keyframe input (`--keyframes DIR`): index PNG value 254 (`IGNORE`) or a LabelMe shape labelled with one of
`IGNORE_LABELS` (`ignore`, `person`, `hand`, `arm`, `transient`; an object of that name in mapping.yaml wins) paints
the "ignore" class; `interreal masks` propagates it through every frame like an object and writes the layer.

A transient mask that covers the whole frame (`WHOLE_FRAME` of its pixels or more) leaves nothing to learn from or
to match: the masks stage and `interreal validate` refuse it, naming the frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from .. import atomic
from ..errors import DatasetError, InputError
from ..layout import TRANSIENTS_DIR

IGNORE = 254  # keyframe index-PNG value of the painted "ignore" class (255 stays "not annotated")
IGNORE_LABELS = ("ignore", "person", "hand", "arm", "transient")  # LabelMe labels of the "ignore" class
WHOLE_FRAME = 0.99  # share of a frame's pixels from which a transient mask "covers the whole frame"


def transient_file(root: str | Path, fid: str) -> Path:
    return Path(root) / TRANSIENTS_DIR / f"{fid}.png"


def is_ignore_label(label: str, object_names: list[str]) -> bool:
    """A LabelMe label that paints the ignore class (an object with that very name is the object)."""
    return label not in object_names and label.strip().lower() in IGNORE_LABELS


def whole_frame(mask: np.ndarray) -> bool:
    return bool(mask.size) and float(np.count_nonzero(mask)) >= WHOLE_FRAME * mask.size


def track_labels(index_map: np.ndarray, n_objects: int) -> np.ndarray:
    """A keyframe index map with the ignore class as one more tracked class (n_objects + 1), so the masks stage
    propagates it with the same tracker as the objects."""
    if not (index_map == IGNORE).any():
        return index_map
    out = index_map.copy()
    out[index_map == IGNORE] = n_objects + 1
    return out


def split_labels(labels: np.ndarray, n_objects: int) -> tuple[np.ndarray, np.ndarray]:
    """A tracked index map whose class n_objects + 1 is the ignore class -> (object index map with transient
    pixels as background, transient bool mask)."""
    transient = labels == n_objects + 1
    if not transient.any():
        return labels, transient
    out = labels.copy()
    out[transient] = 0
    return out, transient


def write_transient(root: str | Path, fid: str, mask: np.ndarray) -> None:
    """Write a frame's transient mask (atomic); a whole-frame mask is refused with the frame named."""
    if mask.ndim != 2:
        raise ValueError(f"transient mask must be 2-D, got shape {mask.shape}")
    if whole_frame(mask):
        raise InputError(f"frame {fid}: the transient (ignore) mask covers {100 * np.mean(mask):.0f} % of the frame, "
                         f"leaving nothing static to reconstruct or train on; paint only the person / hand on that "
                         f"keyframe, or drop the frame")
    atomic.write_image(transient_file(root, fid), np.where(mask, 255, 0).astype(np.uint8))


def clear_transients(root: str | Path, keep: set[str] = frozenset()) -> int:
    """Remove transient masks of frames not in `keep` (a re-run without the ignore class leaves none stale)."""
    folder = Path(root) / TRANSIENTS_DIR
    if not folder.is_dir():
        return 0
    gone = 0
    for p in folder.glob("*.png"):
        if p.stem not in keep:
            p.unlink()
            gone += 1
    if not any(folder.iterdir()):
        folder.rmdir()
    return gone


def has_transients(root: str | Path) -> bool:
    folder = Path(root) / TRANSIENTS_DIR
    return folder.is_dir() and any(folder.glob("*.png"))


def read_transient(root: str | Path, fid: str, hw: tuple[int, int] | None = None) -> np.ndarray | None:
    """The frame's transient mask (H, W) bool, or None when the frame has none; DatasetError when unreadable or of
    another size than `hw` (H, W)."""
    path = transient_file(root, fid)
    if not path.exists():
        return None
    img = _decode(path)
    found = content_problem(img, hw)
    if found:
        raise DatasetError(f"{path} (frame {fid}): {found[1]}")
    return img > 0


def excluded(root: str | Path, fid: str, hw: tuple[int, int], dilate: int = 0) -> np.ndarray | None:
    """Pixels a feature-based stage (SfM, motions) must not use: the transient mask grown by `dilate` px."""
    m = read_transient(root, fid, hw)
    if m is None or dilate <= 0 or not m.any():
        return m
    import cv2

    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate + 1, 2 * dilate + 1))
    return cv2.dilate(m.astype(np.uint8), k) > 0


def content_problem(img: np.ndarray | None, hw: tuple[int, int] | None) -> tuple[str, str] | None:
    """(kind, what is wrong) with a decoded transient PNG, None when it is fine."""
    if img is None:
        return "bad-transient", "cannot decode the PNG"
    if img.ndim != 2 or img.dtype != np.uint8:
        return "bad-transient", f"a {img.dtype} image of shape {img.shape}; transient masks are 8-bit single-channel"
    if hw is not None and img.shape != tuple(hw):
        return "transient-size", f"mask is {img.shape[1]}x{img.shape[0]}, image is {hw[1]}x{hw[0]}"
    values = np.unique(img)
    if not set(values.tolist()) <= {0, 255}:
        return "bad-transient", (f"holds values {values[~np.isin(values, [0, 255])][:5].tolist()}; a transient mask "
                                 f"is boolean (0 or 255)")
    if whole_frame(img):
        return "transient-whole-frame", (
            f"covers {100 * np.count_nonzero(img) / img.size:.0f} % of the frame: the whole frame is transient and "
            f"nothing static is left; repaint the ignore class on the keyframes (only the person / hand) and re-run "
            f"`interreal masks`, or drop the frame")
    return None


def problems(root: str | Path, fids: list[str], sizes: dict[str, tuple[int, int]], check_contents: bool = True
             ) -> list[tuple[str, Path, str]]:
    """(kind, path, message) per problem of the transient layer, for `interreal validate`.

    fids: every frame the dataset lists; sizes: fid -> image (w, h) where known. `check_contents=False` reads only
    each PNG's header (size and mode), as the quick validation does for the masks.
    """
    folder = Path(root) / TRANSIENTS_DIR
    if not folder.is_dir():
        return []
    out: list[tuple[str, Path, str]] = []
    known = set(fids)  # none known (no transforms.json yet): only the files themselves are checked
    for path in sorted(folder.iterdir()):
        if path.name.startswith("."):
            continue
        if path.suffix.lower() != ".png" or (known and path.stem not in known):
            out.append(("stray-transient", path, f"not the transient mask of a listed frame (expected "
                                                 f"{TRANSIENTS_DIR}/<frame id>.png); delete it or re-run "
                                                 f"`interreal masks`"))
            continue
        wh = sizes.get(path.stem)
        hw = (wh[1], wh[0]) if wh else None
        found = content_problem(_decode(path), hw) if check_contents else _header_problem(path, hw)
        if found:
            out.append((found[0], path, f"frame {path.stem}: {found[1]}"))
    return out


def _decode(path: Path) -> np.ndarray | None:
    """The PNG's pixels as stored (None when empty or not an image). Not `interreal.dataset`'s decoder: validation
    there imports this module."""
    import cv2

    data = np.fromfile(str(path), dtype=np.uint8)
    return cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None


def _header_problem(path: Path, hw: tuple[int, int] | None) -> tuple[str, str] | None:
    try:
        with Image.open(path) as im:
            size, mode = im.size, im.mode
    except (OSError, UnidentifiedImageError):
        return "bad-transient", "cannot decode the PNG"
    if mode not in ("L", "1"):
        return "bad-transient", f"a {mode} image; transient masks are 8-bit single-channel (0 / 255)"
    if hw is not None and (size[1], size[0]) != tuple(hw):
        return "transient-size", f"mask is {size[0]}x{size[1]}, image is {hw[1]}x{hw[0]}"
    return None
