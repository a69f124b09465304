"""A plain drawer: its front at rest, pulled out along its normal, each frame's pull read from its mask.

A drawer's front has nothing to match when it is painted plain (SfM and PnP register nothing), and its corners are
cut or hidden as often as a door's. What its masks show is the prism the front sweeps as it comes out (front, sides
and top), and the front at rest has a straight edge that stays put (where it meets the cabinet): the edge route's
hinge candidates. So:
1. the front: for each candidate static line (`edge.hinge_lines`, from the keyframes' outlines), the leaf on it that
   best covers the masks (`leaf.fit_leaf`), at the angle most frames agree with (a front does not turn), then the
   plane give or take 10 deg, which side it comes out on and how far in front of or behind the line it lies, by
   the overlap of each frame's best pull; each line's front then has its size, angle and shift refined (the
   leaf's size was fitted to a turning leaf, which an open drawer's top and sides bend). Its plane is what the
   masks pin least (a pull's top and sides bend as a tilted plane's would: fronts 3-30 deg off on simulated plain
   drawers even with exact masks), so where the cameras tell up the best front is then held level, as drawers
   slide, and refined so (`refine_level`: 0.2-1 deg with exact masks);
2. each frame's pull by dynamic programming over the frames in time order (a drawer moves smoothly; the keyframes,
   a person's masks, count `edge.KEY_WEIGHT` frames), the frames labelled at one end sharing one pull;
3. `judge`: the keyframes explained, and the slide explains the frames it moved in better than a leaf turning on
   one of those lines does (a door is the edge route's), so a door whose masks tie is not made a drawer.
Its limit: where the masks cannot tell a pulled drawer from a door turned a little, it refuses.
The pulls are the displacement `fit.articulate` reads: the geometry measures, the labels only orient.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from ..dataset import Articulation
from ..sfm.geometry import _rot_between, level_up
from . import edge
from .fit import Fit
from .leaf import Leaf, Line, fit_leaf, iou_curves
from .path import anchored_path, refine
from .silhouette import Silhouettes, Views

REACH = np.linspace(0.0, 1.5, 61)  # pulls searched, in widths of the front
SMOOTH = 0.5                       # overlap given up per front width pulled between neighbouring frames (a leaf
#                                    gives up 0.01 a degree: its free edge moving 1.7 % of its width)
TILT_DEG = (-10.0, 0.0, 10.0)      # the front's plane about the line, around the angle the frames agree on
SHIFTS = np.linspace(-1 / 3, 1 / 3, 5)  # ... and in front of or behind it, in widths
SAMPLE = 24                        # frames the front is chosen on (spread over the video)
REFINE_STEPS = 80                  # Nelder-Mead steps refining each line's front
LEVEL_STEPS = 300                  # ... and the best front once levelled (7 parameters)


@dataclass
class Front:
    """The front at rest (4, 3) world corners, the unit direction it comes out along, and its width (world)."""

    corners: np.ndarray
    normal: np.ndarray
    width: float

    def prism(self, pull: float) -> np.ndarray:
        """(8, 3): the front at rest and pulled out by `pull` (world units): the drawer's silhouette."""
        return np.concatenate([self.corners, self.corners + pull * self.normal])

    @property
    def centre(self) -> np.ndarray:
        return self.corners.mean(0)


def pull_curves(sil: Silhouettes, front: Front, frames: list[int], reach: np.ndarray = REACH) -> np.ndarray:
    """(F, len(reach)) overlap of each frame's mask with the front pulled by each of `reach` widths."""
    shapes = np.stack([front.prism(r * front.width) for r in reach])
    return np.array([sil.ious(shapes, i) for i in frames]).reshape(len(frames), len(reach))


def front_at(leaf: Leaf, x: np.ndarray, sign: float) -> Front:
    """The front of parameters x = (width, h0, h1 in lengths of the line, angle about it, shift along its normal
    in widths) on `leaf`'s line, coming out on the `sign` side."""
    base = leaf.corners(x[0], x[1], x[2], x[3])
    normal = np.cross(base[1] - base[0], base[3] - base[0])
    normal /= np.linalg.norm(normal)
    width = float(x[0] * leaf.length)
    return Front(base + x[4] * width * normal, sign * normal, width)


def front_score(sil: Silhouettes, front: Front, groups: list[list[int]], reach: np.ndarray = REACH) -> float:
    """The mean over `groups` (the keyframes, a spread of other frames) of each frame's best overlap at a pull."""
    if front.width <= 0:
        return 0.0
    return float(np.mean([pull_curves(sil, front, g, reach).max(1).mean() for g in groups if g]))


def front_groups(frames: list[int], keys: list[int]) -> list[list[int]]:
    """The frames a front is scored on: the keyframes (a person's masks), a spread of at most `SAMPLE` others."""
    return [[k for k in keys if k in frames], sorted(set(frames[::max(1, len(frames) // SAMPLE)]) - set(keys))]


def grid_front(sil: Silhouettes, leaf: Leaf, size: np.ndarray, rest: float, groups: list[list[int]]
               ) -> tuple[float, np.ndarray, float]:
    """(score, parameters, side) of the best front around the leaf of `size` at angle `rest`: tilted, shifted,
    coming out on either side (`front_at`), scored by `front_score` on `groups`."""
    best: tuple[float, np.ndarray, float] = (-1.0, np.zeros(5), 1.0)
    for phi in rest + np.radians(TILT_DEG):
        for sign in (1.0, -1.0):  # the drawer comes out on one side of its front
            for shift in SHIFTS:
                x = np.array([size[0], size[1], size[2], phi, shift])
                score = front_score(sil, front_at(leaf, x, sign), groups, REACH[::2])
                if score > best[0]:
                    best = (score, x, sign)
    return best


def refine_front(sil: Silhouettes, leaf: Leaf, x0: np.ndarray, sign: float, groups: list[list[int]]
                 ) -> tuple[Front, float]:
    """The front's size, angle and shift refined from `x0` (the leaf's size was fitted to a turning leaf, which an
    open drawer's top and sides bend), and its score."""
    steps = np.array([0.1 * x0[0], 0.1, 0.1, np.radians(3.0), 0.05])
    res = minimize(lambda x: -front_score(sil, front_at(leaf, x, sign), groups, REACH[::2]), x0, method="Nelder-Mead",
                   options={"xatol": 1e-3, "fatol": 1e-4, "maxiter": REFINE_STEPS,
                            "initial_simplex": x0 + np.vstack([np.zeros(5), np.diag(steps)])})
    front = front_at(leaf, res.x, sign)
    return front, front_score(sil, front, groups)


def resting_angle(sil: Silhouettes, leaf: Leaf, size: np.ndarray, frames: list[int]) -> float:
    """The leaf's angle the frames agree on most (their summed overlap): a front slides, it does not turn."""
    angles = np.linspace(-np.pi, np.pi, 72, endpoint=False)
    some = frames[::max(1, len(frames) // SAMPLE)]
    return float(angles[int(np.argmax(iou_curves(sil, leaf, size, some, angles).sum(0)))])


def gravity(views: Views) -> np.ndarray | None:
    """World up from the cameras (`sfm.geometry.level_up`), or None where they do not tell it."""
    return level_up(np.linalg.inv(views.w2c))


def _turned(corners: np.ndarray, centre: np.ndarray, rot: np.ndarray) -> np.ndarray:
    return (corners - centre) @ rot.T + centre


def level_front(front: Front, up: np.ndarray) -> Front:
    """`front` turned about its centre by the least rotation that makes its normal level: a drawer slides level."""
    flat = front.normal - (front.normal @ up) * up
    if np.linalg.norm(flat) < 1e-6:  # a front facing straight up or down: no level pull near it
        return front
    flat /= np.linalg.norm(flat)
    return Front(_turned(front.corners, front.centre, _rot_between(front.normal, flat)), flat, front.width)


def levelled(front: Front, up: np.ndarray, x: np.ndarray) -> Front:
    """The level `front` of parameters x = (turn about `up`, roll about its normal, shift (3, in widths), log scales
    of its two edges): its normal stays level."""
    e1 = (front.corners[1] - front.corners[0]) * np.exp(x[5])
    e2 = (front.corners[3] - front.corners[0]) * np.exp(x[6])
    base = front.centre - 0.5 * (e1 + e2)
    corners = np.stack([base, base + e1, base + e1 + e2, base + e2])
    rot = Rotation.from_rotvec(up * x[0]).as_matrix() @ Rotation.from_rotvec(front.normal * x[1]).as_matrix()
    width = front.width * float(np.linalg.norm(e2) / max(np.linalg.norm(front.corners[3] - front.corners[0]), 1e-12))
    return Front(_turned(corners, front.centre, rot) + x[2:5] * front.width, rot @ front.normal, width)


def refine_level(sil: Silhouettes, front: Front, up: np.ndarray, groups: list[list[int]]) -> tuple[Front, float]:
    """The level front (`level_front`) refined by `levelled`'s parameters, and its score (`front_score`). Its
    plane's tilt is what the masks pin least (its pull's sides bend as a tilted plane would); held level, its turn
    about up is pinned (simulated plain drawers: 0.3-3 deg off where the free front was 3-82)."""
    start = level_front(front, up)
    steps = np.diag([np.radians(5.0), np.radians(3.0), 0.1, 0.1, 0.1, 0.1, 0.1])
    res = minimize(lambda x: -front_score(sil, levelled(start, up, x), groups, REACH[::2]), np.zeros(7),
                   method="Nelder-Mead", options={"xatol": 1e-3, "fatol": 1e-4, "maxiter": LEVEL_STEPS,
                                                  "initial_simplex": np.vstack([np.zeros(7), steps])})
    out = levelled(start, up, res.x)
    return out, front_score(sil, out, groups)


def find_front(views: Views, frames: list[int], keys: list[int], coarse: Silhouettes, ends: list[list[int]]
               ) -> tuple[Front | None, list[tuple[Leaf, np.ndarray]], dict[str, Any]]:
    """The best front over the best static lines of the keyframes' outlines (`edge.hinge_lines`), or None and why;
    and the leaves fitted on those lines (`leaf.fit_leaf`: the door each line would hinge), the slide's rivals."""
    lines, _ = edge.hinge_lines(views, frames, keys)
    fig: dict[str, Any] = {"prism_lines": [round(ln.cost, 2) for ln in lines[:4]]}
    lines = [ln for ln in lines if ln.cost <= edge.MAX_LINE_PX]
    if not lines:
        fig["prism_reason"] = (f"no straight edge of its keyframe outlines stays put across the frames (best "
                               f"{min(fig['prism_lines'], default=float('nan'))} px from the outlines, need "
                               f"{edge.MAX_LINE_PX}): no front to pull")
        return None, [], fig
    shown = [i for i in frames if i in coarse.crop]
    groups = front_groups(shown, keys)
    leaves, grids = [], []
    for ln in lines[:4]:  # the front on each line searched on a grid, then refined
        leaf = Leaf(ln)
        size, _ = fit_leaf(coarse, ln, shown, keys, ends)
        leaves.append((leaf, size))
        grids.append(grid_front(coarse, leaf, size, resting_angle(coarse, leaf, size, shown), groups))
    front, score = max((refine_front(coarse, leaf, g[1], g[2], groups) for (leaf, _), g in zip(leaves, grids)),
                       key=lambda r: r[1])  # every line's: the grid's order is not the refined one's (seed 3)
    fig["prism_front_iou"] = round(score, 3)
    up = gravity(views)
    if up is not None:  # a drawer slides level: the level front kept unless a tilted one fits clearly better
        level, level_score = refine_level(coarse, front, up, groups)
        fig["prism_level_iou"] = round(level_score, 3)
        if level_score >= score - edge.SLIDE_MARGIN:
            front, fig["prism_levelled"] = level, True
    return front, leaves, fig


def pull_path(curves: np.ndarray, width: float, still: np.ndarray, ends: list[np.ndarray]) -> np.ndarray:
    """Each frame's pull (world units) by dynamic programming over `curves` (F, len(REACH)), refined by a parabola."""
    steps = REACH * width
    jump = SMOOTH * np.abs(REACH[:, None] - REACH[None, :])
    path = anchored_path(curves, steps, still, ends, jump=jump)
    return np.array([refine(curves[f], j, steps) if 0 < j < len(REACH) - 1 else float(steps[j])
                     for f, j in enumerate(path)])


def turning_leaf(sil: Silhouettes, leaf: Leaf, size: np.ndarray, shown: list[int], weight: np.ndarray,
                 still: np.ndarray, ends: list[np.ndarray]) -> np.ndarray:
    """(F,) each frame's overlap by `leaf` of `size` turning as the edge route follows it (smoothly, the frames
    labelled at one end at one angle)."""
    angles = np.linspace(-np.pi, np.pi, edge.ANGLES // 2, endpoint=False)
    turns = iou_curves(sil, leaf, size, shown, angles)
    path = anchored_path(turns * weight, angles, still, ends)
    return turns[np.arange(len(shown)), path]


def judge(fig: dict[str, Any], shown: list[int], pulls: np.ndarray, iou: np.ndarray, keys: list[int],
          leaf_best: np.ndarray) -> str | None:
    """Why the front pulled by `pulls` (over `shown`; `iou` its overlap there) is no drawer, or None; its figures
    into `fig`. leaf_best (F,): each frame's best overlap by a leaf turning on one of the static lines, or on the
    front's own edge (`turning_leaf`): the rival."""
    key = [f for f, i in enumerate(shown) if i in keys]
    key_iou = float(iou[key].mean()) if key else 0.0
    moved = pulls >= edge.MOVED * pulls.max() if pulls.max() > 0 else np.zeros(len(pulls), bool)
    slide_iou = float(iou[moved].mean()) if moved.any() else 0.0
    hinge_iou = float(leaf_best[moved].mean()) if moved.any() else 0.0
    fig.update(prism_key_iou=round(key_iou, 3), prism_slide_iou=round(slide_iou, 3),
               prism_hinge_iou=round(hinge_iou, 3), prism_moved_frames=int(moved.sum()))
    if key_iou < edge.MIN_KEY_IOU:
        return (f"a front pulled along its normal does not explain the keyframes' masks (overlap {key_iou:.2f}, need "
                f"{edge.MIN_KEY_IOU}): no plain drawer")
    if moved.all():
        return (f"the front found is pulled out in every frame ({pulls.min():.3g} at least): it is not where the drawer "
                f"rests, no plain drawer")
    if slide_iou < edge.MIN_FRAME_IOU:
        return (f"a front pulled along its normal overlaps the masks of the frames it moved in by {slide_iou:.2f} "
                f"(need {edge.MIN_FRAME_IOU}): no plain drawer")
    if slide_iou < hinge_iou + edge.SLIDE_MARGIN:
        return (f"a leaf turning on a static edge explains the masks of the frames it moved in as well as a front "
                f"pulled out (overlap {hinge_iou:.2f} against {slide_iou:.2f}, need {edge.SLIDE_MARGIN:g} less): a "
                f"door or lid, not a drawer")
    return None


def prism_motion(views: Views, frames: list[int], keys: list[int], states: np.ndarray | None = None,
                 known: np.ndarray | None = None) -> tuple[Fit | None, dict[str, Any]]:
    """The slide of the best front as a `Fit` over `frames` (the pull per frame, world units), or None and why."""
    keys = [k for k in keys if k in frames]
    if not keys:
        return None, {"prism_reason": "no keyframe mask shows the part (its front's static edge comes from "
                                      "keyframes)"}
    coarse, sil = Silhouettes(views, frames, edge.SEARCH_SIDE), Silhouettes(views, frames)
    shown = [i for i in frames if i in sil.crop]
    still, ends = edge.label_ends(shown, states, known)
    groups = edge.end_samples(shown, ends)
    front, leaves, fig = find_front(views, frames, keys, coarse, groups)
    if front is None:
        return None, fig
    curves = pull_curves(sil, front, shown)
    weight = np.array([edge.KEY_WEIGHT if i in keys else 1.0 for i in shown])[:, None]
    pulls = pull_path(curves * weight, front.width, still, ends)
    iou = np.array([sil.iou(front.prism(p), i) for p, i in zip(pulls, shown)])
    own = Leaf(Line(front.corners[0], front.corners[1], 0.0, keys[0], front.corners[3] - front.corners[0]))
    leaves.append((own, np.array([np.linalg.norm(front.corners[3] - front.corners[0]) / own.length, 0.0, 1.0])))
    leaf_best = np.max([turning_leaf(coarse, leaf, size, shown, weight, still, ends) for leaf, size in leaves], axis=0)
    reason = judge(fig, shown, pulls, iou, keys, leaf_best)
    if reason:
        fig["prism_reason"] = reason
        return None, fig
    measured = iou >= edge.MIN_FRAME_IOU
    fig.update(prism_mean_iou=round(float(iou.mean()), 3), prism_width=round(front.width, 4))
    pos = {i: n for n, i in enumerate(shown)}
    at = [pos.get(i) for i in frames]
    ok = np.array([n is not None and bool(measured[n]) for n in at])
    step = float(REACH[1] - REACH[0]) * front.width
    return Fit("slide", front.normal.copy(), front.centre, np.array([pulls[n] if n is not None else 0.0 for n in at]),
               ok, np.full(len(frames), step), 1.0, {}), fig


def contested_slide(edge_fig: dict[str, Any]) -> str | None:
    """Why a slide the prism route measured is not used, or None: the edge route's refined leaf explained the frames
    it turned in better than a slide of its front on both counts (outline and overlap), if not by its margins (so it
    was refused too). The prism's own rival, an unrefined leaf, can lose where the refined one wins: a plain door
    with three frames of it drawn open was made a drawer 89 deg off so (simulated, `--hard` seed 6)."""
    if not edge_fig.get("edge_contested"):
        return None
    return (f"the edge route's leaf explains the frames it turned in better than a slide of its front "
            f"({edge.rival_words(edge_fig)}), if not by its margins: a door or a drawer, the masks do not tell")


def measure_prism(ds, obj: int, states: np.ndarray, known: np.ndarray, labelled: np.ndarray, keys: list[int],
                  min_pixels: int = 400, trust_labels: bool = False, confidence: np.ndarray | None = None,
                  views: Views | None = None) -> tuple[Articulation | None, dict[str, Any]]:
    """Object `obj`'s slide from its front and masks over the dataset `ds` (arguments as `edge.measure_edge`);
    (None, figures with `prism_reason`) when the route cannot measure it."""
    return edge.measure_outlines("prism", prism_motion, "its front pulled out along its normal", ds, obj, states,
                                 known, labelled, keys, min_pixels, trust_labels, confidence, views)
