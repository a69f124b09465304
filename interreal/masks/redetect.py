"""Re-detection: find an object again after its chain lost it, from what its keyframe says it looks like.

A chain moves a mask by flow from frame to frame, so once the mask has collapsed (an occluder passed over the
object, the object left the view for a moment, a fast move the flow could not follow) nothing brings it back:
flow only moves what is there. A chain with no keyframe at its far end (before the first keyframe, after the
last; `between_keyframes` for the others) therefore keeps, per object, the appearance of the object on the
chain's keyframe (its colour model, unit weight, and ORB features inside its mask) and the size its mask had
over the last frames. When the mask shrinks under `collapse` of that size, every frame is searched for the
object until it is found:

- candidates: connected regions where the keyframe's colour model, smoothed over a small window, says
  "object" (P(object | colour) above `level`), of a plausible size (within `size` of the median size over the
  frames before the loss: an object found again has about the size it had; a region of the object's colour
  much larger than it was is background that shares its colours, and over `max_share` of the view it is),
  scored by their likelihood, their mass and how near they lie to where the object was last seen (the
  remnant of its mask, else its last healthy mask): the reach grows with the object's size and, while it stays
  lost, with the frames since (an object moves on while hidden);
- a candidate is accepted when ORB features of the keyframe's object match into it (`min_matches` matches
  that pass the ratio test and agree on one similarity transform), or, from colour alone, when colour tells the
  object apart on the keyframe itself (`heldout_information` at least `min_info`) and the candidate stands out
  (its score at least `margin` times the runner-up's), and, where part of the object is still in the chain's
  mask, the candidate does not move with the background while that remnant moves otherwise (the chain's flow
  and one homography each, `Propagator._moves_apart`): a look-alike on the background (a patch of dirt the
  colour of a muddy bike) is not the object;
- the accepted region is put back into the soft map as the object, and propagation carries on from it;
- an object that left the view is looked for only where it comes back: when most of what its mask lost as it
  collapsed went out of the image over a side (the chain's flow from frame to frame takes it past that side) and
  what is left of it lies at that side, a candidate must reach that side (a door that swung down out of the frame
  is not the cabinet's rim of its colour in mid-view); the chain reports the exit (`exits`), and the stage has no
  mask for it until it is back (`verdict.left_view`).

No constant depends on one footage: sizes are relative to the object's own recent size, smoothing and
distances to the image size, and colour-only acceptance is gated by how well colour separated the labels on
the keyframe (measured there, not tuned).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from .appearance import AppearanceConfig, ColourModel, heldout_information
from .soft import argmax_labels


@dataclass(frozen=True)
class RedetectConfig:
    """When a mask counts as collapsed, and what a candidate must show to be taken for the object."""

    enabled: bool = True
    # also on the chains between two keyframes (fusion with the other chain already brings a lost object back
    # there). Off: on the simulated capture (keyframe every 60) it re-found the fridge door and the drawer on
    # look-alike regions while they turned edge-on, and the drawer's J fell from 0.934 to 0.794
    between_keyframes: bool = False
    collapse: float = 0.2          # a mask under this share of its recent size (largest over `window`) collapsed
    window: int = 10               # frames of recent size
    smooth: float = 0.015          # smoothing radius of the colour likelihood, share of the image's long side
    level: float = 0.5             # smoothed P(object | colour) inside a candidate: more likely object than not
    size: tuple[float, float] = (0.3, 1.5)  # candidate area / the object's area before the loss (median, `window`)
    max_share: float = 0.5         # a region over this share of the view is background, not a re-found object
    min_share: float = 0.002       # nor is a speck under this share of the view
    min_info: float = 0.25         # colour-only acceptance: colour must separate the labels this well on the keyframe
    margin: float = 2.0            # colour-only acceptance: best candidate's score over the runner-up's
    features: int = 600            # ORB features per image
    min_matches: int = 8           # ORB matches (ratio test, one similarity transform) that confirm a candidate
    ratio: float = 0.8             # Lowe's ratio test on the Hamming distances


@dataclass
class Event:
    """One re-detection: frame position, object index, the candidate's area share, how it was confirmed, and the
    frame where the chain first found the mask collapsed (where the stage could not hold the object: a frame to
    annotate)."""

    pos: int
    obj: int
    area: float
    how: str  # "features" or "colour" (or "refused": a colour find not taken, `Redetector.refusals`; "left-view")
    since: int
    sides: tuple[bool, ...] = ()  # "left-view": the image sides (left, top, right, bottom) it left the view over


class Redetector:
    """The memory of one chain: per object, the keyframe's appearance and the mask's recent sizes."""

    def __init__(self, image: np.ndarray, soft: np.ndarray, known: np.ndarray, cfg: RedetectConfig,
                 app: AppearanceConfig, n_objects: int):
        """image: the keyframe's work-size RGB; soft, known: its soft map and known-pixels map (`anchor_soft`)."""
        self.cfg = cfg
        self.k = n_objects
        self._key = (image, soft, known, app)  # the appearance memory is built at the first search (`_memory`)
        self.model: ColourModel | None = None
        self.info = 0.0
        labels = argmax_labels(soft)
        h, w = labels.shape
        self.r = max(1, round(cfg.smooth * max(h, w)))
        self.sizes = [deque(maxlen=cfg.window) for _ in range(n_objects)]
        self.present = np.zeros(n_objects, bool)
        self.lost = np.zeros(n_objects, int)
        self.collapsed_at = np.zeros(n_objects, int)  # frame where the current collapse began
        self.where = np.full((n_objects, 2), np.nan)  # last seen centroid (x, y), work pixels
        # per object and frame over the last `window`, the mask's pixels that the flow from the frame before took
        # past each side of the image (left, top, right, bottom); the sides it left the view over when most of
        # what it lost as it collapsed went out over them (`check`), until it is found again
        self.gone = [deque(maxlen=cfg.window) for _ in range(n_objects)]
        self.depth = [deque(maxlen=cfg.window) for _ in range(n_objects)]  # ... and how far it reached from each
        self.exit = np.zeros((n_objects, 4), bool)
        self.prev = np.where(known > 0.5, labels, 0)  # the labels the previous check left (the keyframe's first)
        for k in range(n_objects):
            mask = (labels == k + 1) & (known > 0.5)
            area = int(mask.sum())
            self.present[k] = area > 0
            if area:
                self.sizes[k].append(area)
                self.where[k] = _centroid(mask)
        self.key_pts: list[np.ndarray] = []
        self.key_desc: list[np.ndarray | None] = []
        self.events: list[Event] = []
        # each colour find refused because it moved with the background (`check`; `how` "refused")
        self.refusals: list[Event] = []
        # each collapse that was the object leaving the view over the image border (`how` "left-view")
        self.exits: list[Event] = []

    def check(self, soft: np.ndarray, image: np.ndarray, bins: np.ndarray, pos: int,
              moves_apart: Callable[[np.ndarray, np.ndarray], bool] | None = None,
              flow: np.ndarray | None = None) -> np.ndarray:
        """The soft map of frame `pos`, with every collapsed object searched for and, when found, put back.

        image: the frame's work-size RGB; bins: its colour bins (`quantize`); moves_apart(region, remnant): False
        when the flow says the region moves with the background where what is left of the object does not
        (`Propagator._moves_apart`). Colour alone finds look-alike background (a dirt track under a muddy bike),
        so a region found by colour beside a remnant that still moves as the object must move as it does.
        flow: (h, w, 2) from the frame the chain came from to this one: where most of what a collapsed mask lost
        went out of the image, the object left the view (a door swung out of it, the camera turned away), and it
        comes back over that border, not in mid-view (a look-alike of its colour there is not it)."""
        if not self.cfg.enabled:
            return soft
        labels = argmax_labels(soft)
        out = outflow(self.prev, flow, self.k) if flow is not None and self.prev.shape == labels.shape else None
        for k in range(self.k):
            self.gone[k].append(out[k] if out is not None else np.zeros(4, int))
            if not self.present[k]:
                continue  # absent on the keyframe: nothing to remember it by
            mask = labels == k + 1
            area = int(mask.sum())
            recent = max(self.sizes[k]) if self.sizes[k] else 0
            if area:
                self.where[k] = _centroid(mask)
            if recent and area >= self.cfg.collapse * recent:
                self.sizes[k].append(area)
                self.depth[k].append(reach_from_sides(mask))
                self.lost[k] = 0
                continue
            if self.lost[k] == 0:
                self.collapsed_at[k] = pos
                self.exit[k] = self._left_over(k, recent - area, mask if area else self.prev == k + 1)
                if self.exit[k].any():
                    self.exits.append(Event(pos, k, area / mask.size, "left-view", pos,
                                            tuple(bool(v) for v in self.exit[k])))
            self.lost[k] += 1
            found = self._search(k, image, bins, float(np.median(self.sizes[k])) if self.sizes[k] else 0.0)
            if found is None:
                continue
            region, how = found
            if how == "colour" and area and moves_apart is not None and not moves_apart(region, mask):
                self.refusals.append(Event(pos, k, float(region.mean()), "refused", int(self.collapsed_at[k])))
                continue
            soft = _reseed(soft, k, region)
            labels = argmax_labels(soft)
            self.exit[k] = False
            self.sizes[k].clear()
            self.sizes[k].append(int(region.sum()))
            self.where[k] = _centroid(region)
            self.lost[k] = 0
            self.events.append(Event(pos, k, float(region.mean()), how, int(self.collapsed_at[k])))
        self.prev = labels
        return soft

    def _left_over(self, k: int, shrunk: int, remnant: np.ndarray) -> np.ndarray:
        """(4,) the image sides object k left the view over as its mask collapsed: most of the `shrunk` pixels it
        lost over the last `window` frames went out of the image (half or more; over each such side a quarter of
        them or more), and what is left of it (`remnant`: its mask now, else on the frame before) lies at that side
        and reaches out from it no farther than `collapse` of how far it reached before (it shrank into the border,
        as its area did). A door that turns edge-on as it swings past the border keeps a strip in mid-view: not
        out of the view. None of them when the mask collapsed in view."""
        none = np.zeros(4, bool)
        gone = np.sum(list(self.gone[k]), 0) if self.gone[k] else np.zeros(4)
        if shrunk <= 0 or gone.sum() < 0.5 * shrunk or not remnant.any() or not self.depth[k]:
            return none
        before = np.max(list(self.depth[k]), 0)
        return (gone >= 0.25 * gone.sum()) & border_sides(remnant, self.r) & \
            (reach_from_sides(remnant) <= self.cfg.collapse * before)

    def _memory(self) -> None:
        """The keyframe's colour model (unit weight), how well it separates the labels there, and the ORB features
        inside each object. Built at the first search, not per chain: most chains never lose their object, and
        this costs about as much as propagating one frame."""
        if self.model is not None:
            return
        image, soft, known, app = self._key
        unit = AppearanceConfig(weight=1.0, bins=app.bins, band=app.band, prior=app.prior)
        self.model = ColourModel.fit(image, soft, known, unit)
        self.info = heldout_information(image, soft, known, unit)
        labels = argmax_labels(soft)
        h, w = labels.shape
        self._orb = cv2.ORB_create(self.cfg.features, fastThreshold=10)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        kps, desc = self._orb.detectAndCompute(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), None)
        for k in range(self.k):
            mask = (labels == k + 1) & (known > 0.5)
            inside = [i for i, kp in enumerate(kps) if mask[min(h - 1, int(kp.pt[1])), min(w - 1, int(kp.pt[0]))]] \
                if desc is not None else []
            self.key_pts.append(np.array([kps[i].pt for i in inside], np.float32).reshape(-1, 2))
            self.key_desc.append(desc[inside] if inside else None)

    def _search(self, k: int, image: np.ndarray, bins: np.ndarray, recent: float) -> tuple[np.ndarray, str] | None:
        """The region of the frame that is object k, or None when no candidate is convincing."""
        self._memory()
        cfg = self.cfg
        table = self.model.table
        p = table[bins, k] / np.maximum(table[bins].sum(-1), 1e-12)  # P(object k | colour)
        side = 2 * self.r + 1
        ps = cv2.boxFilter(p.astype(np.float32), -1, (side, side))
        n, comp, stats, _ = cv2.connectedComponentsWithStats((ps > cfg.level).astype(np.uint8), connectivity=8)
        h, w = bins.shape
        reach = 2.0 * np.sqrt(max(recent, 1)) + 0.05 * max(h, w) * self.lost[k]
        cands = []
        for i in range(1, n):
            a = int(stats[i, cv2.CC_STAT_AREA])
            if recent and not cfg.size[0] * recent <= a <= cfg.size[1] * recent:
                continue
            if not cfg.min_share * h * w <= a <= cfg.max_share * h * w:
                continue
            region = comp == i
            if self.exit[k].any() and not (border_sides(region, self.r) & self.exit[k]).any():
                continue  # it left the view over that border: it comes back over it, not in mid-view
            # score: how surely the region is the object, times its mass (a larger region of the same colour
            # is more of the object than a speck of it), times its nearness to where the object was last seen
            near = 1.0
            if np.isfinite(self.where[k, 0]):
                near = float(np.exp(-np.hypot(*(_centroid(region) - self.where[k])) / reach))
            cands.append((float(ps[region].mean()) * np.sqrt(a) * near, region))
        if not cands:
            return None
        cands.sort(key=lambda c: -c[0])
        matched = self._feature_votes(k, image, [r for _, r in cands])
        if matched is not None:
            return cands[matched][1], "features"
        runner = cands[1][0] if len(cands) > 1 else 0.0
        if self.info >= cfg.min_info and cands[0][0] >= cfg.margin * runner:
            return cands[0][1], "colour"
        return None

    def _feature_votes(self, k: int, image: np.ndarray, regions: list[np.ndarray]) -> int | None:
        """Index of the region that the keyframe's ORB features of object k match into (consistently), or None."""
        desc_k = self.key_desc[k]
        if desc_k is None or len(desc_k) < self.cfg.min_matches:
            return None
        grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        kps, desc = self._orb.detectAndCompute(grey, None)
        if desc is None or len(desc) < 2:
            return None
        pairs = self._matcher.knnMatch(desc_k, desc, k=2)
        good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < self.cfg.ratio * m[1].distance]
        if len(good) < self.cfg.min_matches:
            return None
        src = self.key_pts[k][[m.queryIdx for m in good]]
        dst = np.array([kps[m.trainIdx].pt for m in good], np.float32)
        h, w = regions[0].shape
        _, inl = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC, ransacReprojThreshold=0.02 * max(h, w))
        if inl is None:
            return None
        dst = dst[inl.ravel() > 0]
        xs = np.clip(dst[:, 0].astype(int), 0, w - 1)
        ys = np.clip(dst[:, 1].astype(int), 0, h - 1)
        votes = [int(r[ys, xs].sum()) for r in regions]
        best = int(np.argmax(votes))
        return best if votes[best] >= self.cfg.min_matches else None


def outflow(labels: np.ndarray, flow: np.ndarray, n_objects: int) -> np.ndarray:
    """(n_objects, 4) pixels of each object in `labels` (work size) that `flow` (h, w, 2) takes past the image's
    left, top, right and bottom side."""
    h, w = labels.shape
    out = np.zeros((n_objects, 4), int)
    x = flow[..., 0] + np.arange(w, dtype=np.float32)[None, :]
    y = flow[..., 1] + np.arange(h, dtype=np.float32)[:, None]
    past = [x < 0, y < 0, x > w - 1, y > h - 1]
    if not any(p.any() for p in past):
        return out
    for k in range(n_objects):
        m = labels == k + 1
        out[k] = [int((m & p).sum()) for p in past]
    return out


def reach_from_sides(mask: np.ndarray, share: float = 0.9) -> np.ndarray:
    """(4,) how far a (non-empty) mask reaches from the image's left, top, right and bottom side: the `share`
    percentile of its pixels' distances to each (a few stray pixels do not count)."""
    h, w = mask.shape
    out = np.zeros(4)
    for i, (line, n) in enumerate(((mask.sum(0), w), (mask.sum(1), h))):  # pixels per column, per row
        cum = np.cumsum(line)
        out[i] = np.searchsorted(cum, share * cum[-1])                      # from the left / top side
        out[i + 2] = n - 1 - np.searchsorted(cum, (1 - share) * cum[-1])    # from the right / bottom side
    return out


def border_sides(mask: np.ndarray, margin: int) -> np.ndarray:
    """(4,) bool: the mask reaches within `margin` px of the image's left, top, right, bottom side."""
    m = max(int(margin), 1)
    return np.array([mask[:, :m].any(), mask[:m].any(), mask[:, -m:].any(), mask[-m:].any()])


def _centroid(mask: np.ndarray) -> np.ndarray:
    ys, xs = np.nonzero(mask)
    return np.array([xs.mean(), ys.mean()]) if len(xs) else np.full(2, np.nan)


def _reseed(soft: np.ndarray, k: int, region: np.ndarray) -> np.ndarray:
    """Object k takes the region (probability 0.95 there); the other labels share what is left as before."""
    out = soft.copy()
    m = region.astype(np.float32) * 0.95
    new_k = np.maximum(out[..., k], m)
    rest = 1.0 - out[..., k]
    scale = (1.0 - new_k) / np.maximum(rest, 1e-6)
    for j in range(out.shape[-1]):
        if j != k:
            out[..., j] *= scale
    out[..., k] = new_k
    return (out / out.sum(-1, keepdims=True)).astype(np.float32)
