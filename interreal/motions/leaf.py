"""The leaf a door or lid turns: a slab hinged on a 3D line, its size fitted to the masks, then the line, size and
thickness refined together on every frame's best angle.

`edge` finds the line (the one straight stretch of the keyframes' outlines that stays put) and `prism` uses a leaf
on it as the door a drawer's slide must beat; both read the leaf from here. The line is triangulated from two
keyframes' outlines, a few pixels off where a plain door meets its plain body; seen from close by, 3 cm and 1 deg
off the hinge turns every frame's best angle 10-17 deg (a half-open door read at 0.3 of its range where it is at
0.45, simulated plain captures), so `refine_leaf` moves the line's two ends with the leaf's size and thickness until
the frames' best silhouettes overlap their masks most.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize, minimize_scalar

from .silhouette import Silhouettes

SIZE_ANGLES = 36      # the size search's angle grid (10 deg), the best two peaks on it then climbed (`crest`)
CREST_TOL = np.radians(0.2)  # ... to within this
KEEP = 0.6            # the share of frames (best first) a fit is judged on: masks fail, hands cover
REFINE_FRAMES = 20    # about this many frames besides the keyframes refine the leaf (spread over the video)
REFINE_STEPS = 120    # Nelder-Mead steps a round; three rounds, each frame's angle re-centred between them
LOCAL = np.radians(6.0)  # each frame's angle climbed within this of its last best in a round
STEP = 0.01           # the refinement's unit: the line's ends and span move in hundredths of its length, the width
#                       and thickness in hundredths of the width
THICK_STARTS = (0.0, 8.0, -8.0)  # thicknesses (hundredths of the width) the refinement starts from, on either side:
#                                  a door is 2-10 % as thick as it is wide. It descends twice: from the line as it
#                                  came, and from the line moved that far across itself (the best of four ways):
#                                  where the cabinet's edge hides a door's hinge, the keyframes' outlines agree on
#                                  that edge, a thickness behind the hinge, and one descent from there stops short


@dataclass
class Line:
    """A 3D segment P -> Q (world), its mean outline distance (px) over the frames kept, the keyframe it came
    from, and a direction in the scene (`toward`: to that keyframe's camera) that a leaf's angle 0 points along."""

    p: np.ndarray
    q: np.ndarray
    cost: float
    key: int
    toward: np.ndarray | None = field(default=None, repr=False)

    @classmethod
    def seen_from(cls, p: np.ndarray, q: np.ndarray, cost: float, key: int, camera: np.ndarray) -> Line:
        """The segment P -> Q as keyframe `key`'s camera centre `camera` (3,) saw it: angle 0 points to it."""
        return cls(p, q, cost, key, camera - 0.5 * (p + q))

    @property
    def axis(self) -> np.ndarray:
        d = self.q - self.p
        return d / np.linalg.norm(d)


class Leaf:
    """A slab hinged on `line`: its front's corners at angle phi about it (radians from the basis vector `b1`), and
    `thickness` (in widths; its sign the side) behind them. Why a slab: seen from its side, an open door's edge
    widens its silhouette, and a thin leaf fitted there turns too little (on the true hinge, a simulated 6 cm
    thick door read 5 deg short at 45 and at 100 deg)."""

    def __init__(self, line: Line, thickness: float = 0.0):
        self.line = line
        self.thickness = thickness
        self.b1, self.b2 = basis(line)
        self.length = float(np.linalg.norm(line.q - line.p))
        self.axis = line.axis  # made once: `corners` runs a few hundred thousand times a part

    def corners(self, width: float, h0: float, h1: float, phi: float) -> np.ndarray:
        """(4, 3) world corners of the front at angle phi, then (4, 3) of the back where the slab is thick."""
        return self.turning(width, h0, h1)(phi)

    def turning(self, width: float, h0: float, h1: float) -> Callable[[float], np.ndarray]:
        """`corners` of the leaf of this size as a function of its angle: what does not turn is made once (a climb
        asks for a few hundred thousand angles a part)."""
        a, p = self.axis, self.line.p
        lo, hi = p + h0 * self.length * a, p + h1 * self.length * a
        wide = width * self.length
        deep = self.thickness * width * self.length

        def at(phi: float) -> np.ndarray:
            cos, sin = np.cos(phi), np.sin(phi)
            out = wide * (cos * self.b1 + sin * self.b2)
            front = np.array([lo, hi, hi + out, lo + out])
            if not self.thickness:
                return front
            return np.concatenate([front, front + deep * (cos * self.b2 - sin * self.b1)])  # axis x out
        return at

    def corners_at(self, width: float, h0: float, h1: float, phis: np.ndarray) -> np.ndarray:
        """(A, 4 or 8, 3): `corners` at each of the angles phis (A,)."""
        at = self.turning(width, h0, h1)
        return np.stack([at(phi) for phi in phis])


def basis(line: Line) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (3,) across the line, angle 0 along the first: the line's `toward` direction (the scene's,
    so a fit reads the same in any world frame SfM hands us: on a plain door, the world turned 20 or 45 deg moved
    the fitted range 7 % -> 2 % / 29 % when angle 0 was a world axis), else a world axis."""
    a = line.axis
    ref = np.zeros(3) if line.toward is None else line.toward - (line.toward @ a) * a
    if np.linalg.norm(ref) < 1e-9:  # none given, or along the line
        ref = np.cross(a, np.eye(3)[int(np.argmin(np.abs(a)))])
    b1 = ref / np.linalg.norm(ref)
    return b1, np.cross(a, b1)


def iou_curves(sil: Silhouettes, leaf: Leaf, size: np.ndarray, frames: list[int], angles: np.ndarray) -> np.ndarray:
    """(F, A) overlap of each frame's mask with the leaf of `size` (width, h0, h1) at each angle."""
    shapes = leaf.corners_at(*size, angles)
    return np.array([sil.ious(shapes, i) for i in frames]).reshape(len(frames), len(angles))


def crest(overlap: Callable[[float], float], grid: np.ndarray, values: np.ndarray) -> tuple[float, float]:
    """(overlap, angle) at the top of `overlap`, climbed from the two highest peaks of its `values` on the evenly
    spaced circular `grid`, each within a grid step. Why climbed: a leaf's size read off the grid's best moves with
    where the grid happens to fall (angle 0 turned 2.5-7.5 deg moved a plain door's range 2-28 %); why two: a leaf
    and its mirror image about the plane through the line and the camera cast the same silhouette, near-ties."""
    step = float(grid[1] - grid[0])
    peaks = np.flatnonzero((values >= np.roll(values, 1)) & (values >= np.roll(values, -1)))
    top = (float(values.max()), float(grid[int(values.argmax())]))
    for j in peaks[np.argsort(values[peaks])[::-1][:2]]:
        top = max(top, climb(overlap, grid[j] - step, grid[j] + step), key=lambda r: r[0])
    return top


def climb(overlap: Callable[[float], float], lo: float, hi: float) -> tuple[float, float]:
    """(overlap, angle) at the top of `overlap` between angles lo and hi, to within `CREST_TOL`."""
    res = minimize_scalar(lambda a: -overlap(a), bounds=(lo, hi), method="bounded", options={"xatol": CREST_TOL})
    return float(-res.fun), float(res.x)


def overlap_at(sil: Silhouettes, leaf: Leaf, size: np.ndarray, frames: list[int]) -> Callable[[float], float]:
    """The mean overlap of `frames`' masks with the leaf of `size` as a function of its angle: what `crest` climbs."""
    at = leaf.turning(*size)
    if len(frames) == 1:  # one frame's curve, as `crest` and the refinement climb it: their inner loop
        return lambda phi: sil.iou(at(phi), frames[0])
    return lambda phi: float(np.mean([sil.iou(at(phi), i) for i in frames]))


def halves(keyed: np.ndarray, rest: np.ndarray) -> list[float]:
    """The keyframes' mean overlap (a person's masks) and the mean of the best `KEEP` of the other frames' (propagated
    masks lose a plain door on whole stretches), each where there are any: what a leaf's fit is scored on."""
    parts = [float(keyed.mean())] if len(keyed) else []
    if len(rest):
        parts.append(float(np.sort(rest)[::-1][:max(1, int(KEEP * len(rest)))].mean()))
    return parts


def fit_leaf(sil: Silhouettes, line: Line, frames: list[int], keys: list[int],
             ends: list[list[int]] | None = None) -> tuple[np.ndarray, float]:
    """(width, h0, h1) of the leaf whose best silhouettes overlap the masks most, and that overlap: the keyframes'
    mean (a person's masks), the best `KEEP` of at most 16 other frames (propagated masks lose a plain door on whole
    stretches) and, for each of `ends` (the frames labelled closed, those labelled fully open), the best overlap
    its frames share at one angle, in equal parts. Why the ends: where the door's top and bottom lie outside the
    image, a wider leaf turned further casts the same silhouette in any one view; only views of one state from
    different places pin its free edge. Widths and spans in lengths of the line's segment."""
    leaf = Leaf(line)
    coarse = np.linspace(-np.pi, np.pi, SIZE_ANGLES, endpoint=False)
    groups = [g for g in (ends or []) if len(g) >= 2]
    some = sorted(set(frames[::max(1, len(frames) // 16)]) - set(keys))

    def best(size: np.ndarray, group: list[int]) -> np.ndarray:
        curves = iou_curves(sil, leaf, size, group, coarse)
        return np.array([crest(overlap_at(sil, leaf, size, [i]), coarse, c)[0] for i, c in zip(group, curves)])

    def score(size: np.ndarray) -> float:
        if size[0] <= 0.05 or size[2] - size[1] < 0.2:
            return 0.0
        parts = halves(best(size, keys), best(size, some) if some else np.zeros(0))
        for g in groups:  # one angle shared by the frames at one end
            mean = iou_curves(sil, leaf, size, g, coarse).mean(0)
            parts.append(crest(overlap_at(sil, leaf, size, g), coarse, mean)[0])
        return float(np.mean(parts))

    start = max((np.array([w, 0.0, 1.0]) for w in np.geomspace(0.1, 3.0, 12)), key=score)
    start = max((start + np.array([0.0, lo, hi]) for lo in (0.0, -0.5) for hi in (0.0, 0.5)), key=score)
    res = minimize(lambda x: -score(x), start, method="Nelder-Mead",
                   options={"xatol": 1e-3, "fatol": 1e-4, "maxiter": 60,
                            "initial_simplex": start + np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]])})
    return res.x, -float(res.fun)


def _moved(line: Line, leaf: Leaf, x: np.ndarray) -> Line:
    """`line` with its ends moved x[0:2] and x[2:4] (`STEP`s of its length) across it, along `leaf`'s b1 and b2."""
    d = STEP * leaf.length
    return Line(line.p + d * (x[0] * leaf.b1 + x[1] * leaf.b2), line.q + d * (x[2] * leaf.b1 + x[3] * leaf.b2),
                line.cost, line.key, line.toward)


def _resized(size: np.ndarray, x: np.ndarray) -> np.ndarray:
    """`size` (width, h0, h1) with the width scaled by 1 + x[4] `STEP`s and the span's ends moved x[5], x[6]."""
    return size * np.array([1.0 + STEP * x[4], 1.0, 1.0]) + STEP * np.array([0.0, x[5], x[6]])


def refine_leaf(sil: Silhouettes, line: Line, size: np.ndarray, frames: list[int], keys: list[int]
                ) -> tuple[Line, np.ndarray, float, float]:
    """(line, size, thickness, overlap) of the slab whose best silhouettes overlap the masks most: the line's two
    ends moved across it, the width, span and thickness with them, each frame's angle re-maximised near its last
    best, descending from the line as it came and from it moved a slab's thickness across itself. Scored as
    `fit_leaf` scores (the keyframes' mean and the best `KEEP` of the other frames, in equal parts); the thin leaf as
    it came where nothing scores better."""
    leaf = Leaf(line)
    others = sorted(set(frames[::max(1, len(frames) // REFINE_FRAMES)]) - set(keys))
    some = [k for k in keys if k in frames] + others
    n = len(some) - len(others)  # the keyframes lead
    grid = np.linspace(-np.pi, np.pi, 72, endpoint=False)
    phis = grid[iou_curves(sil, leaf, size, some, grid).argmax(1)]

    def score(x: np.ndarray, phis: np.ndarray) -> tuple[float, np.ndarray]:
        sz = _resized(size, x)
        if sz[0] <= 0.05 or sz[2] - sz[1] < 0.2:
            return 0.0, phis
        slab = Leaf(_moved(line, leaf, x), STEP * x[7])
        best, at = np.array([climb(overlap_at(sil, slab, sz, [i]), p - LOCAL, p + LOCAL)
                             for i, p in zip(some, phis)]).T
        return float(np.mean(halves(best[:n], best[n:]))), at

    def descend(x: np.ndarray, phis: np.ndarray) -> tuple[np.ndarray, float]:
        for _ in range(3):
            res = minimize(lambda z: -score(z, phis)[0], x, method="Nelder-Mead",
                           options={"maxiter": REFINE_STEPS, "xatol": 0.05, "fatol": 1e-4,
                                    "initial_simplex": x + np.vstack([np.zeros(8), 1.5 * np.eye(8)])})
            x = res.x
            phis = score(x, phis)[1]
        return x, score(x, phis)[0]

    start = score(np.zeros(8), phis)[0]
    d = THICK_STARTS[1] * size[0]  # a slab's thickness, in `STEP`s of the line's length
    here = [np.r_[np.zeros(7), t] for t in THICK_STARTS]
    behind = [np.r_[u * d, v * d, u * d, v * d, 0.0, 0.0, 0.0, t] for u, v in ((1, 0), (-1, 0), (0, 1), (0, -1))
              for t in THICK_STARTS[1:]]
    x, end = max((descend(max(group, key=lambda z: score(z, phis)[0]), phis) for group in (here, behind)),
                 key=lambda r: r[1])
    if end <= start:
        return line, size, 0.0, start
    return _moved(line, leaf, x), _resized(size, x), STEP * float(x[7]), end
