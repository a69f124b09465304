"""A plain part read by its colour in the frames where the masks stage lost it.

Propagated masks lose a plain door on whole stretches (a person walks across it, it swings in front of its plain
body), and the masks stage rightly distrusts them there. Those stretches often hold the views that pin the motion:
the door closed, seen from the side (a frontal view of a closed door cut by the image border casts the same
silhouette over tens of degrees), or fully open. Once its leaf is known from the frames it keeps, a frame without
a mask can still say which of the leaf's angles its pixels' colours agree with: the keyframes (a person's masks)
teach the part's colours and those around it, and a candidate silhouette is scored by its overlap with the pixels of
the part's colours, over the region the leaf sweeps. Such a frame steers the leaf's path (`edge`), never measures a
state: an open door shows colours no keyframe taught, and where its plain body has the door's colour it reads as
closed (simulated plain captures, docs/measurements.md 2026-12-06).
"""

from __future__ import annotations

import cv2
import numpy as np

from ..images import at_size
from ..masks.appearance import AppearanceConfig, quantize
from .silhouette import Silhouettes, Views

BINS = 16               # per channel, as the masks stage's colour models
BAND = AppearanceConfig().band  # the background that matters: a band this share of the diagonal around the part
FAR = 0.1               # ... the rest of the frame counts this much
SWEEP = np.linspace(-np.pi, np.pi, 36, endpoint=False)  # the angles whose union is the region a frame is scored in
SWEEP_MARGIN = 0.02     # that region grown by this share of the diagonal


def colour_table(views: Views, keys: list[int], sil: Silhouettes) -> np.ndarray:
    """(BINS^3,) 1 for each colour seen more often on the part than around it, else 0: the keyframes' masks (the
    part) against the band around them (what it is seen against), both smoothed by one count a bin. A mask by colour,
    not a soft chance: a frame's curve then has the contrast of a mask's (soft chances of a plain part and its
    surroundings, 0.3-0.7, flatten it below what a turn between frames costs)."""
    n = BINS ** 3
    part, rest = np.ones(n), np.ones(n)
    for k in keys:
        image = views.image(k)
        mask = sil.small(views.masks[k])
        q = quantize(at_size(image, mask.shape[::-1]), BINS)
        r = max(3, int(BAND * np.hypot(*mask.shape)))
        near = cv2.dilate(mask.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2)) > 0
        part += np.bincount(q[mask], minlength=n)
        rest += np.bincount(q[near & ~mask], minlength=n) + FAR * np.bincount(q[~mask], minlength=n)
    return (part / part.sum() > rest / rest.sum()).astype(np.float32)


class ColourSilhouettes:
    """`Silhouettes`' overlap for the frames without a trusted mask: a predicted silhouette against the pixels of the
    part's colours (`colour_table`), counted over the region the part's leaf sweeps in that frame."""

    def __init__(self, views: Views, sil: Silhouettes, keys: list[int], sweep: list[np.ndarray]):
        h, w = views.masks[0].shape
        self.views, self.sil = views, sil
        self.hw = (int(round(h * sil.scale)), int(round(w * sil.scale)))
        self.table = colour_table(views, keys, sil)
        self.sweep = sweep  # the leaf's corners at the `SWEEP` angles
        self.chance: dict[int, tuple[np.ndarray, np.ndarray, tuple[int, int]]] = {}
        self.poses: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def _frame(self, i: int) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
        """(the part's colours, region scored), both cropped to the region's box, and the box's corner (x0, y0);
        cached."""
        if i not in self.chance:
            region = np.zeros(self.hw, np.uint8)
            for pts in self.sweep:
                region |= self.raster(pts, i, self.hw, (0, 0))
            r = max(1, int(SWEEP_MARGIN * np.hypot(*self.hw)))
            region = cv2.dilate(region, np.ones((2 * r + 1,) * 2, np.uint8)) > 0
            occ = self.views.occluder(i)
            if occ is not None:
                region &= ~self.sil.small(occ)
            ys, xs = np.nonzero(region)
            if not len(xs):
                self.chance[i] = (np.zeros((1, 1), np.float32), np.zeros((1, 1), bool), (0, 0))
                return self.chance[i]
            box = np.s_[ys.min():ys.max() + 1, xs.min():xs.max() + 1]
            chance = self.table[quantize(at_size(self.views.image(i), self.hw[::-1])[box], BINS)].astype(np.float32)
            self.chance[i] = (chance, region[box], (int(xs.min()), int(ys.min())))
        return self.chance[i]

    def raster(self, pts: np.ndarray, i: int, hw: tuple[int, int], corner: tuple[int, int]) -> np.ndarray:
        """(h, w) uint8 silhouette of world points `pts` in frame i, in the box of size hw at `corner` of the
        silhouettes' image (nothing where any point is behind the camera)."""
        out = np.zeros(hw, np.uint8)
        w2c = self.views.w2c[i]
        if ((pts @ w2c[2, :3] + w2c[2, 3]) <= 1e-6).any():
            return out
        if i not in self.poses:
            self.poses[i] = (cv2.Rodrigues(w2c[:3, :3])[0], w2c[:3, 3])
        uv, _ = cv2.projectPoints(pts, *self.poses[i], self.sil.k, self.sil.dist)
        big = 4 * max(self.hw)
        uv = np.clip(uv.reshape(-1, 2) - corner, -big, big)
        cv2.fillConvexPoly(out, cv2.convexHull(np.round(uv * 16).astype(np.int32)), 1, shift=4)
        return out

    def iou(self, pts: np.ndarray, i: int) -> float:
        chance, region, corner = self._frame(i)
        pred = (self.raster(pts, i, region.shape, corner) > 0) & region
        union = float(pred.sum()) + float(chance[region & ~pred].sum())
        return float(chance[pred].sum()) / union if union else 0.0

    def ious(self, shapes: np.ndarray, i: int) -> np.ndarray:
        """(A,) `iou` of each of shapes (A, N, 3) on frame i (as `Silhouettes.ious`)."""
        return np.array([self.iou(s, i) for s in shapes])
