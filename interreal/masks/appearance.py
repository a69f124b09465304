"""Colour models per label, learned on a keyframe: they stop the slow leak of a mask into the background.

Flow is smooth across object boundaries, so a warped mask creeps a pixel or two per frame into whatever
moves with the object (water around a swan, a road under a car). A colour likelihood per label, learned
where the label is known (the keyframe), pulls the boundary back at every step. The background model is
learned on a band around the objects (the background that matters is the one next to them).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class AppearanceConfig:
    weight: float = 0.25     # exponent on the colour likelihood ratio (0 = off)
    bins: int = 16           # per channel (16 -> 4096 colours)
    band: float = 0.08       # local-background band around objects, as a fraction of the image diagonal
    prior: float = 1.0       # Laplace smoothing, in counts per bin


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
        near = cv2.dilate(objects, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))) > 0
        bg = ok & (labels == c - 1)
        hist[c - 1] = np.bincount(bins[(bg & near).ravel()], minlength=n) + 0.1 * np.bincount(bins[bg.ravel()], minlength=n)
        counts = hist.sum(1)
        hist += cfg.prior
        hist /= hist.sum(1, keepdims=True)
        return cls(hist.astype(np.float32), cfg, counts)

    def ratio(self, bins: np.ndarray) -> np.ndarray:
        """Colour bins (h, w) from `quantize` -> (h, w, K+1) likelihood of each label, normalised over labels,
        raised to the configured weight. Bins, not the image: a frame's bins serve both chains and the vote."""
        return self.table[bins]


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
