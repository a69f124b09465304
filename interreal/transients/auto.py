"""`--transients auto`: the transient layer proposed without painting, from the hands the hand model finds.

The model finds where a hand is, never the forearm or the sleeve. What joins them is the body: the forearm leaves the
wrist on the side away from the fingers and runs to the image edge (whoever opens a drawer reaches in from outside
the frame). So each hand gives
- a core: the convex hull of its landmarks, eroded (surely the hand),
- a reach: that hull plus a band from the wrist, away from the knuckles, to the image edge, as wide as the palm
  (probably hand or arm),
and a GrabCut of the frame (colour models of the core and of the pixels around the reach) decides which of the
reach and its surroundings is hand, arm or sleeve, kept only where connected to the core. Object pixels are taken
out when the layer is written (a part in motion is not a transient).

Measured on the shared laptop video against careful hand-and-arm polygons (`recipes/bench_transients.py`): the hull
alone 0.03-0.46 IoU, grown 0.6-0.8 where the hand is found. A person standing in view with no hand in sight (legs at
the image edge) is not found: the pose model's person mask fires on too few frames of such videos to seed it.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
from tqdm import tqdm

from .. import __version__, atomic
from ..report import files_fingerprint, fingerprint
from .hands import MEDIAPIPE_VERSION, MIDDLE_MCP, WRIST, HandTrack, find_hands, hand_length, hand_scale

WORK_LONG_SIDE = 480  # px: GrabCut's resolution (a hand is tens of pixels wide there; full size costs 4x)
BAND_WIDTH = 0.3  # the forearm band's width, in hand lengths (wrist to middle knuckle): the forearm's spine, not its
#                  width; a band as wide as the arm teaches GrabCut the colours beside it as the arm's
CORE_ERODE = 0.1  # the core: the landmarks' hull eroded by this many palm widths (their outline is on the skin)
AROUND = 0.4  # hand sizes (the square root of the core's area) around the reach that GrabCut may grow into
CONTEXT = 3.0  # hand sizes around that of fixed background GrabCut learns the scene's colours from (a wooden
#                shelf of the skin's colour away from the hand must be there, or the arm grows onto it)
MAX_SHARE = 0.5  # a grown layer over this share of the frame leaked (onto a wall of the skin's colour): hull only
GRABCUT_ITERS = 2
ROUNDS = 3  # GrabCuts at most, each from the last one's region (an arm that bends leaves the band: the next follows)
SETTLED = 0.05  # ... stopping once the region changes by less than this share of its area


@dataclass
class AutoLayer:
    """The proposed layer: per frame position a (h, w) bool mask at `work_size` (absent = nothing found)."""

    masks: dict[int, np.ndarray]
    work_size: tuple[int, int]  # (w, h)
    track: HandTrack
    leaked: list[int] = field(default_factory=list)  # frames where growing leaked (the hull was kept)
    seconds: dict[str, float] = field(default_factory=dict)

    def full(self, pos: int, size: tuple[int, int]) -> np.ndarray | None:
        """Frame `pos`'s mask at `size` (w, h), None when the layer has nothing there."""
        m = self.masks.get(pos)
        if m is None:
            return None
        return cv2.resize(m.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0


def layer_key(images: list[Path]) -> str:
    """What the layer depends on: the frames' files and this code (no keyframe: a new one leaves it as it was)."""
    settings = [WORK_LONG_SIDE, BAND_WIDTH, CORE_ERODE, AROUND, CONTEXT, MAX_SHARE, GRABCUT_ITERS, ROUNDS, SETTLED]
    return fingerprint("transients-auto", __version__, MEDIAPIPE_VERSION, files_fingerprint(images), settings)


def save_layer(path: Path, key: str, layer: AutoLayer) -> None:
    """The layer and its hand track in one file, for the next run over the same frames (`load_layer`)."""
    pos = sorted(layer.masks)
    stack = np.stack([layer.masks[p] for p in pos]) if pos else np.zeros((0, layer.work_size[1], layer.work_size[0]))
    hands = [np.asarray(h, np.float64).reshape(-1, 21, 2) for h in layer.track.hands]
    meta = {"key": key, "work_size": list(layer.work_size), "leaked": layer.leaked, "seconds": layer.seconds,
            "how": layer.track.how, "track_seconds": layer.track.seconds}
    with atomic.atomic_open(path) as fh:
        np.savez_compressed(fh, meta=np.array(json.dumps(meta)), pos=np.array(pos, np.int64),
                            masks=np.packbits(stack.astype(bool), axis=-1), counts=np.array([len(h) for h in hands]),
                            hands=np.concatenate(hands) if hands else np.zeros((0, 21, 2)))


def load_layer(path: Path, key: str) -> AutoLayer | None:
    """The layer `save_layer` kept under this key, else None (no file, another key, an unreadable file)."""
    try:
        with np.load(path) as z:
            meta = json.loads(str(z["meta"]))
            if meta["key"] != key:
                return None
            w, h = meta["work_size"]
            masks = np.unpackbits(z["masks"], axis=-1, count=w).astype(bool)
            ends = np.cumsum(z["counts"])
            hands = np.split(z["hands"], ends[:-1]) if len(ends) else []
            pos = z["pos"].tolist()
    except (OSError, ValueError, KeyError):
        return None
    track = HandTrack([np.asarray(x, np.float64) for x in hands], meta["how"], meta["track_seconds"])
    return AutoLayer(dict(zip(pos, masks)), (w, h), track, meta["leaked"], meta["seconds"])


def work_size(size: tuple[int, int], long_side: int = WORK_LONG_SIDE) -> tuple[int, int]:
    s = min(1.0, long_side / max(size))
    return max(1, round(size[0] * s)), max(1, round(size[1] * s))


def propose(load: Callable[[int], np.ndarray], n: int, size: tuple[int, int], *, progress: bool = False,
            clock: Callable[[], float] = time.perf_counter) -> AutoLayer:
    """The auto layer of frames 0..n-1 of size `size` (w, h); `load(pos)` -> RGB uint8. Needs the hand model
    (`hands.model_problem()` is None)."""
    wsize = work_size(size)
    last: dict[int, np.ndarray] = {}

    def full(pos: int) -> np.ndarray:
        if pos not in last:  # frames are read in order, twice at most (the static pass, then growing): keep one
            last.clear()
            last[pos] = load(pos)
        return last[pos]

    def small(pos: int) -> np.ndarray:
        img = full(pos)
        return img if (img.shape[1], img.shape[0]) == wsize else cv2.resize(img, wsize, interpolation=cv2.INTER_AREA)

    # the hand model on the full frames (a hand far away is a few pixels at the work size); landmarks to work pixels
    track = find_hands(full, n, progress=progress, clock=clock)
    scale = np.array([wsize[0] / size[0], wsize[1] / size[1]])
    track.hands = [h * scale for h in track.hands]
    masks: dict[int, np.ndarray] = {}
    leaked: list[int] = []
    t0 = clock()
    for pos in tqdm(range(n), desc="transients", unit="frame", disable=not progress):
        if not len(track.hands[pos]):
            continue
        core, reach = seeds(track.hands[pos], (wsize[1], wsize[0]))
        grown = grow_rounds(small(pos), core, reach)
        if grown.mean() > MAX_SHARE:
            leaked.append(pos)
            grown = hulls(track.hands[pos], (wsize[1], wsize[0]))
        if grown.any():
            masks[pos] = grown
    return AutoLayer(masks, wsize, track, leaked, {**track.seconds, "grow": round(clock() - t0, 3)})


def seeds(hands: np.ndarray, hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(core, reach) (H, W) bool masks of hands (k, 21, 2) landmark pixels: see the module's docstring."""
    core = np.zeros(hw, np.uint8)
    reach = np.zeros(hw, np.uint8)
    for hand in hands:
        hull = _hull(hand, hw)
        inner = cv2.erode(hull, _disk(max(1, round(CORE_ERODE * hand_scale(hand)))))
        core |= inner if inner.any() else hull
        reach |= hull | _forearm(hand, hw)
    return core > 0, reach > 0


def hulls(hands: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """The convex hulls of the hands' landmarks, (H, W) bool: the hands themselves, no arm."""
    out = np.zeros(hw, np.uint8)
    for hand in hands:
        out |= _hull(hand, hw)
    return out > 0


def _hull(hand: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    hull = np.zeros(hw, np.uint8)
    cv2.fillConvexPoly(hull, cv2.convexHull(np.round(hand).astype(np.int32)), 1)
    return hull


def _forearm(hand: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """A band from the wrist, away from the middle knuckle, to past the image edge, BAND_WIDTH hand lengths wide."""
    band = np.zeros(hw, np.uint8)
    d = hand[WRIST] - hand[MIDDLE_MCP]
    norm = float(np.linalg.norm(d))
    if norm < 1e-6:
        return band
    far = hand[WRIST] + d / norm * 2 * (hw[0] + hw[1])
    cv2.line(band, tuple(int(v) for v in np.round(hand[WRIST])), tuple(int(v) for v in np.round(far)), 1,
             max(2, round(BAND_WIDTH * hand_length(hand))))
    return band


def grow_rounds(img: np.ndarray, core: np.ndarray, reach: np.ndarray, rounds: int = ROUNDS) -> np.ndarray:
    """`grow` repeated from its own result (plus the reach) until the region settles."""
    region = grow(img, core, reach)
    for _ in range(rounds - 1):
        nxt = grow(img, core, region | reach)
        changed = int((nxt ^ region).sum())
        region = nxt
        if changed <= SETTLED * max(int(region.sum()), 1):
            break
    return region


def grow(img: np.ndarray, core: np.ndarray, reach: np.ndarray, iters: int = GRABCUT_ITERS) -> np.ndarray:
    """GrabCut of `img` (H, W, 3) uint8 from core (sure), reach (probable) and a margin around it (probably not),
    run on the box around them; the grown region connected to the core, (H, W) bool."""
    if not core.any():
        return core
    size = max(4.0, float(np.sqrt(core.sum())))
    near = cv2.dilate(reach.astype(np.uint8), _disk(max(2, round(AROUND * size)))) > 0
    ys, xs = np.nonzero(near)
    pad = max(4, round(CONTEXT * size))
    y0, y1 = max(0, ys.min() - pad), min(img.shape[0], ys.max() + pad + 1)
    x0, x1 = max(0, xs.min() - pad), min(img.shape[1], xs.max() + pad + 1)
    box = np.s_[y0:y1, x0:x1]
    label = np.full((y1 - y0, x1 - x0), cv2.GC_BGD, np.uint8)
    label[near[box]] = cv2.GC_PR_BGD
    label[reach[box]] = cv2.GC_PR_FGD
    label[core[box]] = cv2.GC_FGD
    if not (label == cv2.GC_BGD).any() and not (label == cv2.GC_PR_BGD).any():
        return reach.copy()  # nothing left to learn the background from (the reach is the whole box)
    bgd, fgd = np.zeros((1, 65)), np.zeros((1, 65))
    cv2.grabCut(np.ascontiguousarray(img[box]), label, None, bgd, fgd, iters, cv2.GC_INIT_WITH_MASK)
    fg = ((label == cv2.GC_FGD) | (label == cv2.GC_PR_FGD)).astype(np.uint8)
    n, comp = cv2.connectedComponents(fg)
    keep = np.unique(comp[core[box] & (fg > 0)])
    out = np.zeros(core.shape, bool)
    out[box] = np.isin(comp, keep[keep > 0])
    return out


def _disk(r: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
