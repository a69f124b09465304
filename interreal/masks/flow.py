"""Dense optical flow between neighbouring frames, computed once per pair and shared by every object.

For a pair (t, t+1) we keep both directions: the flow t+1 -> t pulls a mask forward in time
(`cv2.remap` needs, for each destination pixel, where it came from), the flow t -> t+1 pulls it backward,
and each one checks the other (forward-backward consistency): a pixel whose round trip does not come
back is occluded, disoccluded or badly matched, and is not trusted.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import InputError

DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}
METHODS = ("dis", "rlof", "farneback")


@dataclass(frozen=True)
class FlowConfig:
    """Which flow and how hard it works. DIS "fast" at ~480 px is the speed/accuracy sweet spot on CPU."""

    method: str = "dis"
    preset: str = "fast"
    # Consistency: a round-trip error below `abs_tol + rel_tol * |flow|^2` (Sundaram et al. 2010) is trusted;
    # the trust then decays smoothly (Gaussian) so that small errors do not flip a pixel to "occluded".
    abs_tol: float = 0.75
    rel_tol: float = 0.01
    # Motion boundaries (large flow gradient) are where flow smears an object onto its background: trust there
    # is lowered too (soft version of the same paper's |grad u|^2 + |grad v|^2 > 0.01 |w|^2 + 0.002 test).
    boundary_tol: float = 0.01

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise InputError(f"unknown flow method {self.method!r}; choose one of {METHODS}")
        if self.method == "dis" and self.preset not in DIS_PRESETS:
            raise InputError(f"unknown DIS preset {self.preset!r}; choose one of {tuple(DIS_PRESETS)}")


class FlowEngine:
    """Computes flow for one pair of grey (DIS, Farneback) or colour (RLOF) work-resolution images."""

    def __init__(self, cfg: FlowConfig):
        self.cfg = cfg
        self._dis = None
        if cfg.method == "dis":
            self._dis = cv2.DISOpticalFlow_create(DIS_PRESETS[cfg.preset])
            if cfg.preset == "fast":
                # A slightly finer patch stride than the stock FAST preset: sharper motion boundaries for
                # a few ms more, which is what a mask boundary needs.
                self._dis.setPatchStride(3)
                self._dis.setVariationalRefinementIterations(3)
                # Patches searched down to half the work size (the stock FAST stops at a quarter): a bike's
                # wheel or a horse's leg moving against the background is a few patches wide there and is
                # smoothed into the background's motion at a quarter. DAVIS keyframe every 10 frames: mean J
                # +0.016, no sequence down by more than 0.001; 1.7 -> 4.5 ms a pair at 480 px.
                self._dis.setFinestScale(1)

    def __call__(self, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
        """(H, W, 2) float32 displacement such that src(x) ~ dst(x + flow(x))."""
        m = self.cfg.method
        if m == "dis":
            return self._dis.calc(_grey(src), _grey(dst), None)
        if m == "farneback":
            return cv2.calcOpticalFlowFarneback(_grey(src), _grey(dst), None, 0.5, 4, 15, 3, 5, 1.1, 0)
        return cv2.optflow.calcOpticalFlowDenseRLOF(_bgr(src), _bgr(dst), None)


def _grey(img: np.ndarray) -> np.ndarray:
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)


def _bgr(img: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img


def sampling_grid(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return xs, ys


@dataclass
class Step:
    """Everything needed to move a soft map from frame `src` to frame `dst` (neighbours).

    `map_x, map_y`: where each dst pixel comes from in src. `trust`: (H, W) in [0, 1], forward-backward
    consistency times "the source lies inside the image".
    """

    map_x: np.ndarray
    map_y: np.ndarray
    trust: np.ndarray
    push: np.ndarray  # flow src -> dst, per src pixel (for object-level motion fits)

    def warp(self, arr: np.ndarray, fill: float = 0.0) -> np.ndarray:
        return cv2.remap(arr, self.map_x, self.map_y, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=fill)


def make_step(pull: np.ndarray, push: np.ndarray, grid: tuple[np.ndarray, np.ndarray], cfg: FlowConfig) -> Step:
    """`pull`: flow dst -> src (per dst pixel); `push`: flow src -> dst (per src pixel), for the consistency check."""
    xs, ys = grid
    h, w = xs.shape
    pu, pv = cv2.split(pull)  # contiguous planes: per-pixel maths on (h, w, 2) views is several times slower
    map_x = xs + pu
    map_y = ys + pv
    bu, bv = cv2.split(cv2.remap(push, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))
    err2 = cv2.add(cv2.multiply(pu + bu, pu + bu), cv2.multiply(pv + bv, pv + bv))
    pull2 = cv2.add(cv2.multiply(pu, pu), cv2.multiply(pv, pv))
    mag2 = pull2 + cv2.add(cv2.multiply(bu, bu), cv2.multiply(bv, bv))
    tol2 = cfg.abs_tol ** 2 + cfg.rel_tol * mag2
    expo = -0.5 * err2 / tol2
    if cfg.boundary_tol > 0:
        grad2 = np.zeros_like(pu)
        for c in (pu, pv):
            gx = cv2.Sobel(c, cv2.CV_32F, 1, 0, ksize=1)
            gy = cv2.Sobel(c, cv2.CV_32F, 0, 1, ksize=1)
            grad2 += gx * gx + gy * gy
        expo -= 0.5 * grad2 / (cfg.boundary_tol * pull2 + cfg.boundary_tol)
    trust = cv2.exp(expo)
    inside = (map_x >= 0) & (map_x <= w - 1) & (map_y >= 0) & (map_y <= h - 1)
    trust = (trust * inside).astype(np.float32)
    return Step(map_x, map_y, trust, push)
