"""`--transients auto`: the transient layer proposed without painting, from the hands the hand model finds.

The model finds where a hand is, never the forearm or the sleeve. What joins them is the body: the forearm leaves the
wrist on the side away from the fingers and runs to the image edge (whoever opens a drawer reaches in from outside
the frame). So each hand gives
- a core: the convex hull of its landmarks, eroded (surely the hand),
- a reach: that hull plus a band from the wrist to the image edge (probably hand or arm), in the direction of the
  knuckles-to-wrist line turned as far as the frame shows a limb there (`forearm_direction`: a wrist bends),
and a GrabCut of the frame (colour models of the core and of the pixels around the reach) decides which of the
reach and its surroundings is hand, arm or sleeve, kept only where connected to the core. Object pixels are taken
out when the layer is written (a part in motion is not a transient).

Measured against careful hand-and-arm polygons of the shared laptop video (`recipes/bench_transients_auto.py`): the
hull alone 0.03-0.46 IoU, grown 0.77-0.88; on simulated captures with a sleeved arm (`--synth`), grown with the
forearm turned by the frame 0.354 mean IoU over seeds 1-10 (straight on: 0.235), 0.418 once the masks stage carries
it into the frames where the model finds no hand (`masks.carry`); most of what is left is the sleeve. A person
standing in view with no hand in sight (legs at the image edge) is not found: the pose model's person mask fires on
too few frames of such videos to seed it.
"""

from __future__ import annotations

import json
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
from tqdm import tqdm

from .. import __version__, atomic
from ..images import at_size
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
FOREARM_TURNS = (0, -15, 15, -30, 30, -45, 45, -60, 60, -75, 75)  # deg from the knuckles-to-wrist line
SPINE = np.arange(0.5, 4.01, 0.1)  # hand lengths from the wrist: a forearm and a little of what follows
FLANKS = (0.5, 0.8, 1.2)  # palm widths from the spine: a forearm's side, whether bare or in a wide sleeve
TURN_COST = 0.1  # Lab units a degree: straight on wins unless the image says otherwise
MIN_SPINE = 10  # spine points in view to judge a direction by
GRABCUT_ITERS = 2
ROUNDS = 3  # GrabCuts at most, each from the last one's region (an arm that bends leaves the band: the next follows)
SETTLED = 0.05  # ... stopping once the region changes by less than this share of its area
GROW_THREADS = 2  # frames grown at once: GrabCut lets go of Python's lock, so a second core halves the growth's time


@dataclass
class AutoLayer:
    """The proposed layer: per frame position a (h, w) bool mask at `work_size` (absent = nothing found)."""

    masks: dict[int, np.ndarray]
    work_size: tuple[int, int]  # (w, h)
    track: HandTrack
    leaked: list[int] = field(default_factory=list)  # frames where growing leaked (the hull was kept)
    seconds: dict[str, float] = field(default_factory=dict)
    carried: list[int] = field(default_factory=list)  # frames with no hand found, their mask carried from others

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
    meta = {"key": key, "work_size": list(layer.work_size), "leaked": layer.leaked, "carried": layer.carried,
            "seconds": layer.seconds, "how": layer.track.how, "track_seconds": layer.track.seconds}
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
    return AutoLayer(dict(zip(pos, masks)), (w, h), track, meta["leaked"], meta["seconds"],
                     meta.get("carried", []))


def work_size(size: tuple[int, int], long_side: int = WORK_LONG_SIDE) -> tuple[int, int]:
    s = min(1.0, long_side / max(size))
    return max(1, round(size[0] * s)), max(1, round(size[1] * s))


def propose(load: Callable[[int], np.ndarray], n: int, size: tuple[int, int], *, progress: bool = False,
            clock: Callable[[], float] = time.perf_counter) -> AutoLayer:
    """The auto layer of frames 0..n-1 of size `size` (w, h); `load(pos)` -> RGB uint8 (called from `GROW_THREADS`
    threads at once). Needs the hand model (`hands.model_problem()` is None)."""
    wsize = work_size(size)
    last: dict[int, np.ndarray] = {}

    def full(pos: int) -> np.ndarray:
        if pos not in last:  # the hand model reads the frames in order, twice at most: keep one
            last.clear()
            last[pos] = load(pos)
        return last[pos]

    # the hand model on the full frames (a hand far away is a few pixels at the work size); landmarks to work pixels
    track = find_hands(full, n, progress=progress, clock=clock)
    last.clear()
    scale = np.array([wsize[0] / size[0], wsize[1] / size[1]])
    track.hands = [h * scale for h in track.hands]
    t0 = clock()

    def one(pos: int) -> tuple[int, np.ndarray, bool]:
        img = at_size(load(pos), wsize)
        core, reach = seeds(track.hands[pos], (wsize[1], wsize[0]), img)
        grown = grow_rounds(img, core, reach)
        if grown.mean() > MAX_SHARE:
            return pos, hulls(track.hands[pos], (wsize[1], wsize[0])), True
        return pos, grown, False

    masks: dict[int, np.ndarray] = {}
    leaked: list[int] = []
    todo = [pos for pos in range(n) if len(track.hands[pos])]
    with ThreadPoolExecutor(GROW_THREADS, thread_name_prefix="grow") as pool:
        for pos, grown, leak in tqdm(pool.map(one, todo), total=len(todo), desc="transients", unit="frame",
                                     disable=not progress):
            if leak:
                leaked.append(pos)
            if grown.any():
                masks[pos] = grown
    return AutoLayer(masks, wsize, track, leaked, {**track.seconds, "grow": round(clock() - t0, 3)})


def seeds(hands: np.ndarray, hw: tuple[int, int], img: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(core, reach) (H, W) bool masks of hands (k, 21, 2) landmark pixels: see the module's docstring. With the
    frame `img` (H, W, 3) RGB, each forearm's direction is the one its pixels look like a limb along
    (`forearm_direction`); without it, straight on from the knuckles through the wrist."""
    core = np.zeros(hw, np.uint8)
    reach = np.zeros(hw, np.uint8)
    lab = None if img is None else cv2.cvtColor(cv2.GaussianBlur(img, (5, 5), 0), cv2.COLOR_RGB2LAB).astype(np.float32)
    for hand in hands:
        hull = _hull(hand, hw)
        inner = cv2.erode(hull, _disk(max(1, round(CORE_ERODE * hand_scale(hand)))))
        core |= inner if inner.any() else hull
        reach |= hull | _forearm(hand, hw, None if lab is None else forearm_direction(lab, hand))
    return core > 0, reach > 0


def forearm_direction(lab: np.ndarray, hand: np.ndarray) -> np.ndarray:
    """The unit image direction (x, y) the forearm leaves the wrist in.

    Why not the knuckles-to-wrist line alone: a wrist bends, and the model's landmarks on a hand seen side-on put it
    15-30 deg off, so a spine along it misses a sleeve a palm wide. A forearm is a limb: along it the colour holds (a
    sleeve, skin), across it the colour changes at its sides. So of the directions within `FOREARM_TURN` of that line,
    the one whose spine (`SPINE` hand lengths from the wrist) is most uniform and most unlike its flanks (at
    `FLANKS` palm widths on both sides) wins, each degree off the line costing `TURN_COST`. A line that leaves the
    image at once is kept: the arm comes from the edge, and there is nothing in view to judge it by."""
    d0 = hand[WRIST] - hand[MIDDLE_MCP]
    d0 = d0 / max(float(np.linalg.norm(d0)), 1e-6)
    length, palm = hand_length(hand), hand_scale(hand)
    best, best_dir = -np.inf, d0
    for deg in FOREARM_TURNS:
        a = np.radians(deg)
        d = np.array([np.cos(a) * d0[0] - np.sin(a) * d0[1], np.sin(a) * d0[0] + np.cos(a) * d0[1]])
        spine = hand[WRIST][None] + np.outer(SPINE * length, d)
        inside = _inside(spine, lab.shape)
        if deg == 0 and inside.sum() < MIN_SPINE:
            return d0
        if inside.sum() < MIN_SPINE:
            continue
        score = _limb_score(lab, spine[inside], np.array([-d[1], d[0]]) * palm) - TURN_COST * abs(deg)
        if score > best:
            best, best_dir = score, d
    return best_dir


def _limb_score(lab: np.ndarray, spine: np.ndarray, across: np.ndarray) -> float:
    """How much a spine of points (n, 2) looks like a limb: its flanks' colour distance (the nearer side's, at the
    best of `FLANKS` offsets `across`), less the spread of its own colour (Lab units, medians: robust to a crossing)."""
    on = _sample(lab, spine)
    spread = float(np.median(np.linalg.norm(on - np.median(on, axis=0), axis=1)))
    contrast = 0.0
    for k in FLANKS:
        sides = [spine + k * across, spine - k * across]
        ok = _inside(sides[0], lab.shape) & _inside(sides[1], lab.shape)
        if ok.sum() < MIN_SPINE:
            continue
        near = np.minimum(*(np.linalg.norm(_sample(lab, side[ok]) - on[ok], axis=1) for side in sides))
        contrast = max(contrast, float(np.median(near)))
    return contrast - spread


def _inside(pts: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    return (pts[:, 0] >= 0) & (pts[:, 0] <= shape[1] - 1) & (pts[:, 1] >= 0) & (pts[:, 1] <= shape[0] - 1)


def _sample(img: np.ndarray, pts: np.ndarray) -> np.ndarray:
    q = np.round(pts).astype(np.intp)
    return img[q[:, 1], q[:, 0]]


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


def _forearm(hand: np.ndarray, hw: tuple[int, int], direction: np.ndarray | None = None) -> np.ndarray:
    """A band from the wrist, along `direction` (default: away from the middle knuckle), to past the image edge,
    BAND_WIDTH hand lengths wide."""
    band = np.zeros(hw, np.uint8)
    d = hand[WRIST] - hand[MIDDLE_MCP] if direction is None else direction
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
    cv2.setRNGSeed(0)  # its colour models start from a k-means: the same frame grows alike on any thread, in any order
    cv2.grabCut(np.ascontiguousarray(img[box]), label, None, bgd, fgd, iters, cv2.GC_INIT_WITH_MASK)
    fg = ((label == cv2.GC_FGD) | (label == cv2.GC_PR_FGD)).astype(np.uint8)
    n, comp = cv2.connectedComponents(fg)
    keep = np.unique(comp[core[box] & (fg > 0)])
    out = np.zeros(core.shape, bool)
    out[box] = np.isin(comp, keep[keep > 0])
    return out


def _disk(r: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
