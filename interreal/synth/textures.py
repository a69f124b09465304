"""Surface textures from the photographs scikit-image ships, packed into one atlas.

Real photographs give SIFT the kind of features a real room has. They are cropped (seeded), resized to moderate
resolution and slightly blurred, so that a 1-2 m patch of wall carries a photo's worth of detail but no texel-level
aliasing at 1-4 m: a radiance field can fit it at 320x240. One atlas lets the renderer sample every surface of a
frame with a single `cv2.remap` call; tiles are sampled with mirrored repeat, which has no seams.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import skimage.data
from PIL import Image

TILE = 256  # texels per tile side
PAD = 4  # texels between tiles in the atlas (bilinear never bleeds across)

# colour photos and grayscale photos (tinted when used)
COLOUR_PHOTOS = ("astronaut", "coffee", "chelsea", "rocket", "hubble_deep_field", "immunohistochemistry", "retina",
                 "colorwheel", "logo")
GRAY_PHOTOS = ("brick", "grass", "gravel", "camera", "moon", "coins", "text", "page", "clock", "cell")


# skimage.data function -> the file it reads from the package folder (read with Pillow, as skimage does, but without
# the ~1 s import of skimage's image-IO plugins; same pixels, checked in tests/test_synth.py)
_FILES = {"astronaut": "astronaut.png", "coffee": "coffee.png", "chelsea": "chelsea.png", "rocket": "rocket.jpg",
          "hubble_deep_field": "hubble_deep_field.jpg", "immunohistochemistry": "ihc.png", "retina": "retina.jpg",
          "colorwheel": "color.png", "logo": "logo.png", "brick": "brick.png", "grass": "grass.png",
          "gravel": "gravel.png", "camera": "camera.png", "moon": "moon.png", "coins": "coins.png",
          "text": "text.png", "page": "page.png", "clock": "clock_motion.png", "cell": "cell.png"}


def _load(name: str) -> np.ndarray:
    """Pixels of skimage.data.<name>() (uint8 gray / RGB / RGBA)."""
    path = Path(skimage.data.__file__).parent / _FILES.get(name, "")
    if name not in _FILES or not path.is_file():
        return np.asarray(getattr(skimage.data, name)())
    with Image.open(path) as im:
        return np.asarray(im)


@lru_cache(maxsize=None)
def _photo(name: str) -> np.ndarray:
    """skimage.data image as float32 RGB in [0, 1] (cached: read-only, shared by every scene build)."""
    img = _load(name)
    if img.dtype == bool:
        img = img.astype(np.uint8) * 255
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.shape[2] == 4:  # RGBA logo: blend on white
        a = img[..., 3:4].astype(np.float32) / 255.0
        img = img[..., :3].astype(np.float32) * a + 255.0 * (1 - a)
    out = img[..., :3].astype(np.float32) / 255.0
    out.setflags(write=False)
    return out


@dataclass
class Atlas:
    """Tiles stacked vertically in one float32 RGB image; tile i occupies rows [y0[i], y0[i] + size[i])."""

    tiles: list[np.ndarray] = field(default_factory=list)
    names: list[str] = field(default_factory=list)
    image: np.ndarray | None = None
    y0: np.ndarray | None = None
    size: np.ndarray | None = None

    def add(self, name: str, tile: np.ndarray) -> int:
        if name in self.names:
            return self.names.index(name)
        self.tiles.append(np.clip(tile, 0.0, 1.0).astype(np.float32))
        self.names.append(name)
        self.image = None
        return len(self.tiles) - 1

    def build(self) -> "Atlas":
        width = max(t.shape[1] for t in self.tiles)
        rows, y0, y = [], [], 0
        for t in self.tiles:
            y0.append(y)
            canvas = np.zeros((t.shape[0] + PAD, width, 3), np.float32)
            canvas[: t.shape[0], : t.shape[1]] = t
            rows.append(canvas)
            y += canvas.shape[0]
        self.image = np.ascontiguousarray(np.concatenate(rows, axis=0))
        self.y0 = np.asarray(y0, np.float32)
        self.size = np.asarray([t.shape[0] for t in self.tiles], np.float32)
        return self


class TextureMaker:
    """Seeded crops / mosaics / low-texture variants of the skimage photographs."""

    def __init__(self, rng: np.random.Generator, contrast: float = 0.8):
        self.rng = rng
        self.contrast = contrast

    @staticmethod
    def _source(name: str) -> np.ndarray:
        return _photo(name)

    def crop(self, name: str, size: int = TILE, tint: tuple[float, float, float] | None = None,
             min_frac: float = 0.55) -> np.ndarray:
        """A random square crop of photo `name` resized to `size`, softened and contrast-scaled."""
        src = self._source(name)
        h, w = src.shape[:2]
        side = int(min(h, w) * self.rng.uniform(min_frac, 1.0))
        y = int(self.rng.integers(0, h - side + 1))
        x = int(self.rng.integers(0, w - side + 1))
        tile = cv2.resize(src[y: y + side, x: x + side], (size, size), interpolation=cv2.INTER_AREA)
        tile = cv2.GaussianBlur(tile, (0, 0), 0.7)
        if name in GRAY_PHOTOS:
            tint = tint or tuple(self.rng.uniform(0.55, 1.0, 3))
        if tint is not None:
            tile = tile * np.asarray(tint, np.float32)
        mean = tile.reshape(-1, 3).mean(0)
        return mean + (tile - mean) * self.contrast

    def mosaic(self, names: list[str], size: int = 2 * TILE) -> np.ndarray:
        """2x2 mosaic of crops of four photos: a large non-repeating patch for a wall or floor."""
        half = size // 2
        q = [self.crop(n, half) for n in names[:4]]
        return np.concatenate([np.concatenate(q[:2], 1), np.concatenate(q[2:4], 1)], 0)

    def low(self, base: tuple[float, float, float], size: int = TILE) -> np.ndarray:
        """Low texture: a base colour with faint, very smooth variation (plaster, paint)."""
        noise = self.rng.normal(0, 1, (size // 16, size // 16, 1)).astype(np.float32)
        noise = cv2.resize(noise, (size, size), interpolation=cv2.INTER_CUBIC)[..., None]
        noise = cv2.GaussianBlur(noise, (0, 0), size / 24)
        noise = noise.reshape(size, size, 1) / max(1e-6, float(np.abs(noise).max()))
        return np.asarray(base, np.float32) * (1.0 + 0.06 * noise)

    @staticmethod
    def flat(colour: tuple[float, float, float], size: int = 8) -> np.ndarray:
        return np.ones((size, size, 3), np.float32) * np.asarray(colour, np.float32)
