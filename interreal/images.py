"""Image reading for every stage: decode any dataset image to upright RGB uint8, list a folder's frames, check a
file is a whole image. One reader so the masks stage, the annotation app and training see the same pixels."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from .errors import DatasetError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")


def at_size(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """`img` resized to `size` (w, h) by area (a frame at a stage's work size); as it is when it has that size."""
    return img if (img.shape[1], img.shape[0]) == size else cv2.resize(img, size, interpolation=cv2.INTER_AREA)


def decode_image(path: str | Path, flags: int | None = None) -> np.ndarray | None:
    """The decoded pixels of an image file as OpenCV gives them (BGR order; `flags` default IMREAD_UNCHANGED: index
    masks keep their values), None when the file is empty or not an image. Reads through numpy, so non-ASCII paths
    work on every platform."""
    import cv2  # 0.2 s to import: only when pixels are read (validation and livescene's loader read headers)

    data = np.fromfile(str(path), dtype=np.uint8)
    if not data.size:
        return None
    return cv2.imdecode(data, cv2.IMREAD_UNCHANGED if flags is None else flags)


def read_image_rgb(path: str | Path) -> np.ndarray:
    """RGB uint8 (H, W, 3) of any 8/16-bit image; RGBA is blended on white as the official reader does."""
    import cv2

    img = decode_image(path)
    if img is None:
        raise DatasetError(f"cannot decode image {path}: the file is not an image or is truncated")
    if img.dtype == np.uint16:
        img = (img / 257.0).round().astype(np.uint8)
    if img.ndim == 2:
        return np.repeat(img[..., None], 3, axis=2)
    if img.shape[2] == 4:
        rgb = img[..., 2::-1].astype(np.float32)
        a = img[..., 3:4].astype(np.float32) / 255.0
        return (rgb * a + 255.0 * (1 - a)).round().astype(np.uint8)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)  # 10x faster than copying a reversed-stride view


def list_images(folder: str | Path) -> list[Path]:
    """Frame images in a dataset's images/ folder, in name order."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def image_hw(path: str | Path) -> tuple[int, int]:
    """(h, w) from the image's header (no pixels decoded); PIL's error when it is not an image."""
    with Image.open(path) as im:
        return im.size[1], im.size[0]


def image_size(path: Path, decode: bool = True) -> tuple[int, int] | None:
    """(w, h), or None when the file is not a whole image. `decode`: decode every pixel (sure, ~15 ms a frame);
    else the header and the format's end marker (a truncated PNG / JPEG lacks it; ~0.3 ms a frame)."""
    try:
        with Image.open(path) as im:
            if decode:
                im.load()
            size, fmt = im.size, im.format
    except Exception:  # noqa: BLE001 - any decoder failure is a listed problem, never a crash
        return None
    if not decode and fmt in ("PNG", "JPEG"):
        try:
            with open(path, "rb") as fh:
                fh.seek(max(0, path.stat().st_size - 64))
                tail = fh.read()
        except OSError:
            return None
        if (b"IEND" if fmt == "PNG" else b"\xff\xd9") not in tail:
            return None
    return size
