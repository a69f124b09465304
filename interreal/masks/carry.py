"""`--transients auto`'s layer carried by flow into the frames where the hand model found no hand.

The hand model loses a hand for stretches of frames (turned side-on, blurred, half out of the view, a second arm it
never locks on) while the hand and its sleeve are still there: on simulated sleeved arms it finds one on 34-81 % of
the frames. The arm moves smoothly, so the layer of the last frame with a hand is pulled frame by frame by the flow
into such a stretch (at most `CARRY_FRAMES` on), and the layer of the next frame with a hand backwards likewise; where
both reach, the nearer weighs more. Flow drags a mask onto the background where it loses the arm (the arm leaves the
view, a plain wall slides under it), so a carried pixel is kept only where its colour reads as the layer's rather
than as its surroundings' in the frames it came from (a colour never seen on the layer is not). Frames with a hand keep
their own layer, and a painted keyframe still wins over any of it (`stage.with_auto`).
"""

from __future__ import annotations

import time
from typing import Callable

import cv2
import numpy as np

from ..images import at_size
from ..transients.auto import AutoLayer
from .appearance import quantize
from .flow import FlowConfig, FlowEngine, sampling_grid
from .soft import disk

CARRY_FRAMES = 12  # frames a found layer is carried on, each way: the hand model's gaps last 5-20 frames
KEEP = 0.5  # a carried pixel's blended layer value from which it is the layer's
MIN_PIXELS = 30  # work-size pixels: a carried layer smaller than this is nothing
BINS = 16  # colour bins per channel (as the masks stage's colour models)
SETTINGS = [CARRY_FRAMES, KEEP, MIN_PIXELS, BINS]


def stretches(found: np.ndarray) -> list[tuple[int, int]]:
    """[(first, last)] of each run of frames without a found layer (found: (n,) bool)."""
    out, start = [], None
    for p, f in enumerate(found.tolist() + [True]):
        if not f and start is None:
            start = p
        elif f and start is not None:
            out.append((start, p - 1))
            start = None
    return out


def carry_layer(layer: AutoLayer, load: Callable[[int], np.ndarray], n: int,
                clock: Callable[[], float] = time.perf_counter) -> AutoLayer:
    """`layer` with masks added on the frames the hand model missed, carried from the frames around them (see the
    module's docstring); `load(pos)` -> RGB uint8 of any size (resized to the layer's). Records the frames it filled
    in `layer.carried` and its time in `layer.seconds["carry"]`."""
    t0 = clock()
    wsize = layer.work_size
    found = np.array([len(layer.track.hands[p]) > 0 and p in layer.masks for p in range(n)])
    cache: dict[int, np.ndarray] = {}

    def small(pos: int) -> np.ndarray:
        if pos not in cache:
            cache[pos] = at_size(load(pos), wsize)
        return cache[pos]

    engine, grid = FlowEngine(FlowConfig()), sampling_grid(wsize[1], wsize[0])
    carried: list[int] = []
    for a, b in stretches(found):
        sources = [(s, step) for s, step in ((a - 1, 1), (b + 1, -1)) if 0 <= s < n and found[s]]
        reach = {s: _pulled(layer.masks[s], s, step, a, b, small, engine, grid) for s, step in sources}
        tables = {s: layer_colours(small(s), layer.masks[s]) for s, _ in sources}
        for pos in range(a, b + 1):
            got = [(s, reach[s][pos]) for s, _ in sources if pos in reach[s]]
            if not got:
                continue
            weights = np.array([1.0 / abs(pos - s) for s, _ in got])
            weights /= weights.sum()
            bins = quantize(small(pos), BINS)
            value = sum(w * m for w, (_, m) in zip(weights, got))
            colour = sum(w * tables[s][bins] for w, (s, _) in zip(weights, got))
            mask = (value > KEEP) & (colour > 0.5)
            if int(mask.sum()) >= MIN_PIXELS:
                layer.masks[pos] = mask
                carried.append(pos)
        for p in [p for p in cache if p <= b]:  # stretches come in order: what lies behind this one is done
            del cache[p]
    layer.carried = sorted(carried)
    layer.seconds["carry"] = round(clock() - t0, 3)
    return layer


def _pulled(mask: np.ndarray, src: int, step: int, a: int, b: int, small: Callable[[int], np.ndarray],
            engine: FlowEngine, grid: tuple[np.ndarray, np.ndarray]) -> dict[int, np.ndarray]:
    """Frame -> the layer of frame `src` pulled there by the flow, frame by frame in the direction `step`, over the
    stretch a..b and at most `CARRY_FRAMES` frames; (H, W) float32 in [0, 1]. The flow's forward-backward trust is
    not weighed in: a sleeve's plain inside is untrusted flow, and the carry faded out within a few frames."""
    out: dict[int, np.ndarray] = {}
    value = mask.astype(np.float32)
    prev = src
    for pos in range(src + step, (b + 1 if step > 0 else a - 1), step):
        if abs(pos - src) > CARRY_FRAMES:
            break
        pull = engine(small(pos), small(prev))  # per pixel of pos: where it came from in prev
        value = cv2.remap(value, grid[0] + pull[..., 0], grid[1] + pull[..., 1], cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        if not (value > KEEP).any():
            break
        out[pos] = value
        prev = pos
    return out


def layer_colours(img: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(BINS^3,) per colour bin: how much more the layer of one frame shows it than the band around the layer (one
    hand size wide), as the share p_layer / (p_layer + p_band) of the two normalised histograms; 0 for a colour
    neither shows, so a carried pixel of a colour never seen on the layer is not kept."""
    bins = quantize(img, BINS)
    size = max(2, round(float(np.sqrt(mask.sum()))))
    band = (cv2.dilate(mask.astype(np.uint8), disk(size)) > 0) & ~mask
    on = np.bincount(bins[mask], minlength=BINS ** 3) / max(1, int(mask.sum()))
    off = np.bincount(bins[band], minlength=BINS ** 3) / max(1, int(band.sum()))
    total = on + off
    return np.divide(on, total, out=np.zeros_like(total), where=total > 0)
