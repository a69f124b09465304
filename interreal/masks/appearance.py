"""Colour models per label, learned on a keyframe: they stop the slow leak of a mask into the background.

Flow is smooth across object boundaries, so a warped mask creeps a pixel or two per frame into whatever
moves with the object (water around a swan, a road under a car). A colour likelihood per label, learned
where the label is known (the keyframe), pulls the boundary back at every step. The background model is
learned on a band around the objects (the background that matters is the one next to them). Where one colour
belongs to both labels over the whole frame (a car's underside and its shadow), `LocalColour` keeps each label's
colours near every pixel of the keyframe, carried along a chain with the object.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from .soft import disk


@dataclass(frozen=True)
class AppearanceConfig:
    weight: float = 0.25     # exponent on the colour likelihood ratio (0 = off)
    bins: int = 16           # per channel (16 -> 4096 colours)
    band: float = 0.08       # local-background band around objects, as a fraction of the image diagonal
    prior: float = 1.0       # Laplace smoothing, in counts per bin
    # One-sided chains (before the first keyframe, after the last) have no second keyframe to pull them back:
    # there the colour model is the only anchor to the keyframe, so it is weighed by how much it actually tells
    # labels apart on the keyframe (`heldout_information`, in [0, 1]), never less than `weight`.
    adaptive: bool = True


def quantize(image: np.ndarray, bins: int) -> np.ndarray:
    """RGB uint8 (h, w, 3) -> (h, w) int32 colour bin."""
    shift = 8 - int(np.log2(bins))
    q = (image >> shift).astype(np.int32)
    return (q[..., 0] * bins + q[..., 1]) * bins + q[..., 2]


class ColourModel:
    """Normalised colour histograms, one per label (objects..., background last)."""

    def __init__(self, hist: np.ndarray, cfg: AppearanceConfig, counts: np.ndarray | None = None):
        self.hist = hist  # (K+1, bins^3) float32, each row sums to 1
        self.counts = np.ones(len(hist)) if counts is None else counts  # (K+1,) pixels each row was learned on
        self.cfg = cfg
        # per colour bin: likelihood of each label normalised over labels, to the configured power
        table = hist.T / hist.T.sum(1, keepdims=True)
        self.table = np.ascontiguousarray(table ** cfg.weight if cfg.weight != 1.0 else table, dtype=np.float32)

    @classmethod
    def fit(cls, image: np.ndarray, soft: np.ndarray, known: np.ndarray, cfg: AppearanceConfig) -> "ColourModel":
        h, w, c = soft.shape
        bins = quantize(image, cfg.bins).ravel()
        n = cfg.bins ** 3
        labels = np.argmax(soft, axis=-1)
        ok = (known > 0.5) & (soft.max(-1) > 0.5)
        hist = np.zeros((c, n), np.float64)
        for k in range(c - 1):
            sel = (ok & (labels == k)).ravel()
            hist[k] = np.bincount(bins[sel], minlength=n)
        # background: the band around the objects counts fully, the rest of the image a little
        objects = (ok & (labels < c - 1)).astype(np.uint8)
        r = max(3, int(cfg.band * np.hypot(h, w)))
        near = cv2.dilate(objects, disk(r)) > 0
        bg = ok & (labels == c - 1)
        hist[c - 1] = np.bincount(bins[(bg & near).ravel()], minlength=n) + 0.1 * np.bincount(bins[bg.ravel()], minlength=n)
        counts = hist.sum(1)
        hist += cfg.prior
        hist /= hist.sum(1, keepdims=True)
        return cls(hist.astype(np.float32), cfg, counts)

    def reweighted(self, weight: float) -> "ColourModel":
        """The same histograms with another exponent on the likelihood ratio."""
        return ColourModel(self.hist, replace(self.cfg, weight=weight), self.counts)

    def ratio(self, bins: np.ndarray) -> np.ndarray:
        """Colour bins (h, w) from `quantize` -> (h, w, K+1) likelihood of each label, normalised over labels,
        raised to the configured weight. Bins, not the image: a frame's bins serve both chains and the vote."""
        return self.table[bins]


def grabcut(rgb: np.ndarray, trimap: np.ndarray, iterations: int, seed: int = 0) -> np.ndarray | None:
    """(h, w) bool foreground of GrabCut on an RGB image from a trimap of cv2.GC_* values (changed in place), or
    None when it cannot model the colours (too few pixels on one side). `seed` fixes its k-means start (OpenCV's
    RNG, set here), so the same input always cuts alike."""
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.setRNGSeed(seed)
    try:
        cv2.grabCut(np.ascontiguousarray(rgb[..., ::-1]), trimap, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        return None
    return (trimap == cv2.GC_FGD) | (trimap == cv2.GC_PR_FGD)


def joint_log_table(models: list[ColourModel]) -> np.ndarray:
    """(bins^3, K+1) log-likelihood of each colour under each label, pooling the keyframes at both ends of a gap.

    Pooling matters for a part that changes appearance between its keyframes (a door seen face-on in one and
    edge-on in the other): either view is evidence of the label's colours, equally. A keyframe where the
    label is absent does not count, so it does not halve that object's likelihood.
    """
    w = (np.stack([m.counts for m in models]) > 0).astype(np.float64) + 1e-6  # (n_models, K+1)
    w /= w.sum(0, keepdims=True)
    hist = sum(wi[:, None] * m.hist for wi, m in zip(w, models))
    return np.ascontiguousarray(np.log(hist.T), dtype=np.float32)


def heldout_information(image: np.ndarray, soft: np.ndarray, known: np.ndarray, cfg: AppearanceConfig) -> float:
    """Fraction of the label uncertainty that colour removes on keyframe pixels the model was not fitted on.

    Two folds of a checkerboard of blocks (1/30 of the image's long side, so that a pixel's near-identical
    neighbours do not sit in the other fold); each fold's model (weight 1) scores the other fold's pixels in
    the band around the objects (where the colour decides anything). Per label, the mean log-probability of the
    true label; averaged over labels (a small object counts as much as the background); minus that of a uniform
    guess; divided by log(number of labels). 0: colour says nothing (or misleads); 1: it separates perfectly.
    Measured on the keyframe itself, so no sequence's constant enters the weight it sets.
    """
    h, w, c = soft.shape
    labels = np.argmax(soft, axis=-1)
    ok = (known > 0.5) & (soft.max(-1) > 0.5)
    objects = (ok & (labels < c - 1)).astype(np.uint8)
    if not objects.any():
        return 0.0
    r = max(3, int(cfg.band * np.hypot(h, w)))
    near = cv2.dilate(objects, disk(r)) > 0
    block = max(2, round(max(h, w) / 30))
    ys, xs = np.mgrid[:h, :w]
    odd = ((ys // block + xs // block) % 2).astype(bool)
    bins = quantize(image, cfg.bins)
    unit = replace(cfg, weight=1.0)
    gains = []
    for fold in (odd, ~odd):
        model = ColourModel.fit(image, soft, known * fold, unit)
        test = ~fold & near & ok
        y = labels[test]
        present = [k for k in range(c) if (y == k).any()]
        if len(present) < 2:
            continue
        p = model.table[bins[test]]
        p = p / p.sum(1, keepdims=True)
        gain = np.mean([np.log(p[y == k, k]).mean() for k in present]) + np.log(len(present))
        gains.append(gain / np.log(len(present)))
    return float(np.clip(np.mean(gains), 0.0, 1.0)) if gains else 0.0


LOCAL_RADIUS = 0.03  # `LocalColour`'s window around each pixel, as a share of the work image's long side
LOCAL_FLOOR = 16.0   # its variance floor (Lab units squared): a flat window must not make one colour certain
LOCAL_CELL = 4       # ... and its maps are kept on a grid of this many work pixels (the windows are 29 px wide at
                     # 480 px: the maps are smooth), which makes moving them every step 16x cheaper


@dataclass
class LocalColour:
    """Each object's and the background's colour near every pixel, learned on a keyframe and carried along a
    chain with the object (Video SnapCut's local classifiers, as maps).

    A global histogram cannot tell a car's dark underside from the shadow it casts, or a white car from the white
    concrete it drives on: over the whole keyframe those colours belong to both labels. Near a given part of the
    object they seldom do: the keyframe says the dark strip right under the car is background. Per object k the
    maps hold, around every work pixel, the mean Lab colour and variance of the object's and of the background's
    keyframe pixels within `LOCAL_RADIUS` (box sums), and the share of the window each covers, on a grid of
    `LOCAL_CELL` px. The maps move with the object's own motion (`warp`), so they stay next to the part they
    describe.
    """

    stats: np.ndarray  # (h / cell, w / cell, K, 10): object mean (3), variance, share; background the same
    cell: int = LOCAL_CELL

    @classmethod
    def fit(cls, image: np.ndarray, soft: np.ndarray, known: np.ndarray, cell: int = LOCAL_CELL) -> "LocalColour":
        h, w, c = soft.shape
        lab = lab_of(image)
        r = max(2, round(LOCAL_RADIUS * max(h, w)))
        box = (2 * r + 1, 2 * r + 1)
        grid = (max(1, -(-w // cell)), max(1, -(-h // cell)))
        labels = np.argmax(soft, axis=-1)
        ok = (known > 0.5) & (soft.max(-1) > 0.5)
        sq = (lab * lab).sum(-1)
        out = np.zeros((grid[1], grid[0], c - 1, 10), np.float32)
        bg = (ok & (labels == c - 1)).astype(np.float32)
        for k in range(c - 1):
            for j, m in enumerate(((ok & (labels == k)).astype(np.float32), bg)):
                planes = (m, *np.moveaxis(lab * m[..., None], -1, 0), sq * m)  # share, colour sums, square sum
                sums = np.dstack([cv2.resize(cv2.boxFilter(np.ascontiguousarray(x), -1, box, normalize=True), grid,
                                             interpolation=cv2.INTER_AREA) for x in planes])
                n = sums[..., 0]
                mean = sums[..., 1:4] / np.maximum(n, 1e-6)[..., None]
                var = sums[..., 4] / np.maximum(n, 1e-6) - (mean * mean).sum(-1)
                out[..., k, 5 * j:5 * j + 3] = mean
                out[..., k, 5 * j + 3] = np.maximum(var / 3.0, LOCAL_FLOOR)
                out[..., k, 5 * j + 4] = n
        return cls(out, cell)

    def log_ratio(self, k: int, lab: np.ndarray, ys: np.ndarray, xs: np.ndarray, min_share: float = 0.1) -> np.ndarray:
        """Log-likelihood of object k over the background for the Lab colours `lab` (n, 3) at work pixels (ys, xs),
        under the two local Gaussians there; NaN where either label covers under `min_share` of the window (no
        local evidence: the caller falls back on the global model)."""
        gh, gw = self.stats.shape[:2]
        st = self.stats[np.minimum(ys // self.cell, gh - 1), np.minimum(xs // self.cell, gw - 1), k]
        d_f = ((lab - st[:, 0:3]) ** 2).sum(-1)
        d_b = ((lab - st[:, 5:8]) ** 2).sum(-1)
        v_f, v_b = np.maximum(st[:, 3], LOCAL_FLOOR), np.maximum(st[:, 8], LOCAL_FLOOR)  # 0 where a warp left the image
        out = -0.5 * d_f / v_f - 1.5 * np.log(v_f) + 0.5 * d_b / v_b + 1.5 * np.log(v_b)
        out[(st[:, 4] < min_share) | (st[:, 9] < min_share)] = np.nan
        return out

    def warp(self, hs: list[np.ndarray | None], map_x: np.ndarray, map_y: np.ndarray) -> None:
        """Move every object's maps one step: object k's by its homography hs[k] (work pixels) where trusted, else
        by the chain's per-pixel warp (`flow.Step`'s map_x, map_y: where each work pixel of the new frame comes
        from; brought to the cell grid once for all objects)."""
        gh, gw = self.stats.shape[:2]
        c, o = self.cell, (self.cell - 1) / 2  # cell i's centre is work pixel c i + o
        coarse = None
        for k, H in enumerate(hs):
            parts = [np.ascontiguousarray(self.stats[..., k, i:j]) for i, j in ((0, 4), (4, 8), (8, 10))]
            if H is not None:
                S = np.array([[1.0 / c, 0.0, -o / c], [0.0, 1.0 / c, -o / c], [0.0, 0.0, 1.0]])
                moved = [cv2.warpPerspective(x, S @ H @ np.linalg.inv(S), (gw, gh), flags=cv2.INTER_LINEAR,
                                             borderMode=cv2.BORDER_REPLICATE) for x in parts]
            else:
                if coarse is None:  # a cell's mean source position, back in cells
                    coarse = [(((cv2.resize(m, (gw, gh), interpolation=cv2.INTER_AREA) if c > 1 else m) - o) / c)
                              .astype(np.float32) for m in (map_x, map_y)]
                moved = [cv2.remap(x, *coarse, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) for x in parts]
            self.stats[..., k, :] = np.dstack([m.reshape(gh, gw, -1) for m in moved])


def lab_of(image: np.ndarray) -> np.ndarray:
    """(h, w, 3) float32 CIE Lab (L 0..100) of an RGB uint8 image."""
    return cv2.cvtColor(image.astype(np.float32) / 255.0, cv2.COLOR_RGB2Lab)
