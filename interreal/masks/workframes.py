"""The work resolution propagation runs at, and the frames kept at it.

Flow and the soft maps live on a smaller grid than the images (`work_size`, `WORK_LONG_SIDE` by default);
`FrameCache` holds each frame's full-size RGB, its work-size copy and colour bins once for
the current gap, so the forward and backward chains decode nothing twice.
"""

from __future__ import annotations

from typing import Callable

import cv2
import numpy as np

from .appearance import quantize


class FrameCache:
    """Full-size RGB and work-size grey/colour images, loaded once and kept for the current gap."""

    def __init__(self, load: Callable[[int], np.ndarray], work_size: tuple[int, int], bins: int = 16):
        self.load = load
        self.work_size = work_size  # (w, h)
        self.n_bins = bins
        self._full: dict[int, np.ndarray] = {}
        self._work: dict[int, np.ndarray] = {}
        self._bins: dict[int, np.ndarray] = {}

    def full(self, pos: int) -> np.ndarray:
        if pos not in self._full:
            self._full[pos] = self.load(pos)
        return self._full[pos]

    def work(self, pos: int) -> np.ndarray:
        if pos not in self._work:
            img = self.full(pos)
            if (img.shape[1], img.shape[0]) != self.work_size:
                img = cv2.resize(img, self.work_size, interpolation=cv2.INTER_AREA)
            self._work[pos] = img
        return self._work[pos]

    def bins(self, pos: int) -> np.ndarray:
        """The work image's colour bins (`appearance.quantize`), computed once per frame."""
        q = self._bins.get(pos)
        if q is None:
            q = self._bins[pos] = quantize(self.work(pos), self.n_bins)
        return q

    def put(self, pos: int, full: np.ndarray, work: np.ndarray) -> None:
        """Images decoded elsewhere (the flow worker); kept only if not already cached."""
        self._full.setdefault(pos, full)
        self._work.setdefault(pos, work)

    def peek(self, pos: int) -> np.ndarray | None:
        """The full-size image if it is still cached (no load)."""
        return self._full.get(pos)

    def keep_only(self, keep: set[int]) -> None:
        for d in (self._full, self._work, self._bins):
            for k in [k for k in d if k not in keep]:
                d.pop(k, None)

    def drop(self, pos: int) -> None:
        for d in (self._full, self._work, self._bins):
            d.pop(pos, None)


# auto work size: long chains need the finer grid (drift accumulates step by step); when every keyframe gap is
# short, both chains re-anchor within a few steps and the coarser grid costs little (DAVIS, keyframe every 10:
# IoU 0.955 -> 0.941 and 0.946 -> 0.931, 1.5x faster; first frame only: 0.908 -> 0.898 and 0.807 -> 0.789)
# the default work size (long side, px). Dense keyframes used 400 for speed until writing moved off the chains'
# path: at 480 a keyframe every 10 frames gains +0.019 mean J on the shared DAVIS sequences (every one up or level)
# at 16-22 frames/s for the whole command; 512 gave +0.006 more at 14-21
WORK_LONG_SIDE = 480


def work_size(w: int, h: int, long_side: int) -> tuple[int, int]:
    if long_side <= 0 or max(w, h) <= long_side:
        return w, h
    s = long_side / max(w, h)
    return max(8, round(w * s)), max(8, round(h * s))
