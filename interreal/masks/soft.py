"""Soft object maps: (h, w, K+1) per-pixel probabilities, objects first and background last.

A keyframe's index map becomes one (`anchor_soft`); filters run on the object channels only (`filter_objects`:
the background is one minus their sum); `argmax_labels` turns a map into the exclusive index map the dataset
stores. Short-last-axis reductions are written out by hand (`chsum`, `argmax_channels`): numpy's are slow there.
"""

from __future__ import annotations

from typing import Callable

import cv2
import numpy as np

from ..conventions import UNANNOTATED


def disk(r: int) -> np.ndarray:
    """An elliptical structuring element of radius r px (every band around a mask in this package is one)."""
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def anchor_soft(index_map: np.ndarray, n_objects: int, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Keyframe index map -> (soft map (h, w, K+1) at work size, known (h, w) in [0, 1]); 255 = unknown."""
    known = (index_map != UNANNOTATED).astype(np.float32)
    onehot = np.zeros(index_map.shape + (n_objects + 1,), np.float32)
    for k in range(n_objects):
        onehot[..., k] = index_map == k + 1
    onehot[..., n_objects] = index_map == 0
    if (index_map.shape[1], index_map.shape[0]) != size:
        onehot = cv2.resize(onehot, size, interpolation=cv2.INTER_AREA).reshape(size[1], size[0], -1)
        known = cv2.resize(known, size, interpolation=cv2.INTER_AREA)
    soft = onehot / np.maximum(onehot.sum(-1, keepdims=True), 1e-6)
    soft[known < 1e-3] = 1.0 / (n_objects + 1)
    return soft.astype(np.float32), known


def chsum(x: np.ndarray) -> np.ndarray:
    """Per-pixel sum over the last axis, (h, w, C) -> (h, w, 1); numpy's reduction over a short last axis is slow."""
    c = x.shape[-1]
    if c <= 4 and x.dtype == np.float32:
        return cv2.transform(x, np.ones((1, c), np.float32))[..., None] if c > 1 else x.copy()
    return x.sum(-1, keepdims=True)


def filter_objects(fn: Callable[[np.ndarray], np.ndarray], soft: np.ndarray) -> np.ndarray:
    """Apply a linear, constant-preserving filter (resize, guided filter) to a (h, w, K+1) soft map.

    Only the K object channels are filtered: the channels sum to one, so the filtered background is one minus
    the filtered objects, exactly; with one object this halves the cost of the step.
    """
    k = soft.shape[-1] - 1
    obj = fn(np.ascontiguousarray(soft[..., :k]) if k > 1 else np.ascontiguousarray(soft[..., 0]))
    obj = obj.reshape(obj.shape[0], obj.shape[1], k)
    out = np.empty(obj.shape[:2] + (k + 1,), np.float32)
    out[..., :k] = obj
    out[..., k] = 1.0 - (chsum(obj)[..., 0] if k > 1 else obj[..., 0])
    return out


def argmax_labels(soft: np.ndarray) -> np.ndarray:
    """(h, w, K+1) soft (background last) -> uint8 index map (0 = background, k = object k-1)."""
    return channels_to_labels(argmax_channels(soft), soft.shape[-1])


def argmax_channels(soft: np.ndarray) -> np.ndarray:
    """(h, w, C) -> (h, w) uint8 channel of the maximum; ties go to the lower channel, as argmax does.

    A running maximum over the few channels: numpy's argmax over a short last axis is several times slower.
    """
    best = soft[..., 0].copy()
    idx = np.zeros(best.shape, np.uint8)
    for j in range(1, soft.shape[-1]):
        ch = soft[..., j]
        idx[ch > best] = j
        np.maximum(best, ch, out=best)
    return idx


def channels_to_labels(idx: np.ndarray, c: int) -> np.ndarray:
    """Channel index (background = channel c-1) -> index map (0 = background, k = object k-1)."""
    out = idx + np.uint8(1)
    out[out == c] = 0
    return out


def fill_untrusted(soft: np.ndarray, trust: np.ndarray, radius: int, keep: np.ndarray | None = None) -> np.ndarray:
    """(h, w, C) soft map with its untrusted pixels (trust (h, w) in [0, 1]) taken from the trusted ones within
    `radius`: where the flow failed, its neighbours know better. `keep` (h, w) in [0, 1], when given, is how far an
    untrusted pixel keeps the flow's label all the same (`FrameCache.flow_kept`: a plain surface the flow carried).
    The last channel is the background, which a pixel with nothing trusted nearby (a border that just came into
    view) takes."""
    k = (2 * radius + 1, 2 * radius + 1)
    num = cv2.boxFilter(soft * trust[..., None], -1, k)
    den = cv2.boxFilter(trust, -1, k)
    prior = np.zeros(soft.shape[-1], np.float32)
    prior[-1] = 1.0
    fill = (num + 1e-3 * prior) / (den[..., None] + 1e-3)
    w = 1.0 - trust if keep is None else (1.0 - trust) * (1.0 - keep)
    return (soft + w[..., None] * (fill - soft)).astype(np.float32, copy=False)
