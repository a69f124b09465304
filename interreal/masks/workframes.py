"""The work resolution propagation runs at, and the frames kept at it.

Flow and the soft maps live on a smaller grid than the images (`work_size`, `WORK_LONG_SIDE` by default);
`FrameCache` holds each frame's full-size RGB, its work-size copy and colour bins once for
the current gap, so the forward and backward chains decode nothing twice, and each frame's texture record: how plain
each pixel is against the frame's own noise floor (`texture`), from which `FrameCache.flow_kept` says where a plain
pixel keeps the label the flow brings rather than take its neighbours'.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Callable

import cv2
import numpy as np

from ..images import at_size
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
        # outlives `drop` (a step reads its source frame's record after the frame's image is gone), at most
        # TEXTURE_KEPT of them
        self._texture: OrderedDict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = OrderedDict()
        self._texture_lock = threading.Lock()

    def full(self, pos: int) -> np.ndarray:
        if pos not in self._full:
            self._full[pos] = self.load(pos)
        return self._full[pos]

    def work(self, pos: int) -> np.ndarray:
        if pos not in self._work:
            self._work[pos] = at_size(self.full(pos), self.work_size)
        return self._work[pos]

    def bins(self, pos: int) -> np.ndarray:
        """The work image's colour bins (`appearance.quantize`), computed once per frame."""
        q = self._bins.get(pos)
        if q is None:
            q = self._bins[pos] = quantize(self.work(pos), self.n_bins)
        return q

    def texture(self, pos: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The work image's chromaticity ((h, w, 2): r and g over r + g + b), how plain each pixel is (1 - `texture`)
        and the inverse of its hue tolerance (AGREE_FLOOR noise floors over the brightness: dark pixels are noisy in
        hue), computed once per frame and kept for the TEXTURE_KEPT frames used last."""
        with self._texture_lock:  # the two chains' threads share the records
            t = self._texture.get(pos)
            if t is not None:
                self._texture.move_to_end(pos)
                return t
        rgb = self.work(pos).astype(np.float32)
        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        r, g, b = cv2.split(rgb)
        sigma = noise_floor(grey)
        total = r + g + b + 1.0
        chroma = cv2.merge([cv2.divide(r, total), cv2.divide(g, total)])
        inv_tol = cv2.max(grey, 8.0) * np.float32(1.0 / (AGREE_FLOOR * max(sigma, 0.5)))
        t = (chroma, 1.0 - texture(grey, sigma), inv_tol)
        with self._texture_lock:
            self._texture[pos] = t
            while len(self._texture) > TEXTURE_KEPT:
                self._texture.popitem(last=False)
        return t

    def flow_kept(self, src: int, dst: int, warp: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """(h, w) in [0, 1]: how far an untrusted pixel of dst keeps the label the flow (`warp`, src -> dst) brings.

        Where dst is plain the flow is an interpolation from its surroundings, as any fill is, and filling it pulls
        a plain surface's inside toward whatever its rim touches (a plain door's mask was eaten step by step). But a
        plain pixel that the flow fills with another hue than its own is a surface the flow lost (a plain wall
        uncovered as a person walks off): there the fill decides, as it does on texture. Hue, not brightness: a
        door that turns toward the light brightens by half in a frame or two."""
        c_dst, plain, inv_tol = self.texture(dst)
        if not plain.any():  # textured everywhere: the fill decides everywhere
            return np.zeros_like(plain)
        diff = cv2.transform(cv2.absdiff(warp(self.texture(src)[0]), c_dst), np.ones((1, 2), np.float32))
        diff = cv2.multiply(cv2.boxFilter(diff, -1, (3, 3)), inv_tol)
        return cv2.multiply(plain, cv2.exp(-cv2.multiply(diff, diff)))

    def put(self, pos: int, full: np.ndarray, work: np.ndarray) -> None:
        """Images decoded elsewhere (the flow worker); kept only if not already cached."""
        self._full.setdefault(pos, full)
        self._work.setdefault(pos, work)

    def peek(self, pos: int) -> np.ndarray | None:
        """The full-size image if it is still cached (no load)."""
        return self._full.get(pos)

    def keep_only(self, keep: set[int]) -> None:
        with self._texture_lock:
            for d in (self._full, self._work, self._bins, self._texture):
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


# a pixel is plain up to PLAIN_LOW times the gradient energy of the noise floor, textured from PLAIN_HIGH times
# (a ramp between); the flow agrees with a plain pixel's hue within AGREE_FLOOR floors (a Gaussian weight)
PLAIN_LOW, PLAIN_HIGH, AGREE_FLOOR = 2.0, 8.0, 5.0
TEXTURE_KEPT = 16  # frames' texture records (about 2 MB each at the default work size; both chains' last steps)
_LAPLACE = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)


def noise_floor(grey: np.ndarray) -> float:
    """A grey image's floor of variation (grey levels): Immerkaer's noise estimate from the Laplacian's mean absolute
    response (6 sigma for Gaussian noise), which the image's texture and its compression raise too, so it scales
    with how noisy and how busy the frame is. (Its lower quartile, nearer the true noise, counted a compressed plain
    door as texture: `--hard` door J 0.38 / 0.32 against 0.40 / 0.47.)"""
    lap = cv2.filter2D(grey, -1, _LAPLACE)[1:-1, 1:-1]
    return float(np.sqrt(np.pi / 2) * cv2.norm(lap, cv2.NORM_L1) / lap.size / 6.0)


def texture(grey: np.ndarray, sigma: float | None = None, radius: int = 3) -> np.ndarray:
    """(h, w) in [0, 1]: 0 where a grey image (float) is plain, 1 where it has texture a flow can follow.

    The Sobel gradient energy over a (2 radius + 1) window, over the 24 sigma^2 that the `noise_floor` sigma alone
    gives: a plain painted surface under video noise sits at 1-2, edges and patterns at tens to hundreds, and a
    noisy phone frame and a clean one are judged alike."""
    sigma = noise_floor(grey) if sigma is None else sigma
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3)
    energy = cv2.boxFilter(cv2.add(cv2.multiply(gx, gx), cv2.multiply(gy, gy)), -1, (2 * radius + 1, 2 * radius + 1))
    scale = 1.0 / (max(24.0 * sigma * sigma, 1e-3) * (PLAIN_HIGH - PLAIN_LOW))  # the ramp, in OpenCV's calls
    ramp = cv2.addWeighted(energy, scale, energy, 0.0, -PLAIN_LOW / (PLAIN_HIGH - PLAIN_LOW))
    return cv2.min(cv2.max(ramp, 0.0), 1.0)
