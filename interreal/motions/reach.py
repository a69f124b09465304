"""A measured hinge carried into the frames its route never registered: the leaf turning on the measured axis,
each such frame's angle read from its mask.

A part's own reconstruction registers the frames whose texture it matches; once a door or cover turns its plain
side or its edge to the camera, nothing registers, and the open end of the motion was the labels' guess (simulated
textured doors with eyeballed labels: the registered frames reach 0.26-0.52 of the way open, the range then 24-79 %
off). The masks still show the part there. With the axis measured, one rectangle hinged on it (`leaf.fit_leaf`)
casts each frame's silhouette at each angle; the registered frames pin the leaf's angle at rest (their measured
angles, shifted by one offset that fits their masks best) and, with it, its size (`fit_measured`), and every other
frame's angle follows its mask along a smooth path through them (`edge`'s dynamic programming). The route's measured frames are kept as they are; only
frames well past its angles, joined to them at a pace the part keeps (`connected`), add states, and the whole is
judged again (`fit.articulate`), so the measured ends of the motion, not the labels' line, become its states 0 and
1. Only where an end is not one the route measured (`unmeasured`): where it measured both, its poses read them
better than a rectangle fitted to masks. Where an end stays the labels' guess (the masks lost the part there),
`frames_to_draw` names the frames a person's masks would let this reading reach.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from scipy.optimize import minimize

from ..dataset import Articulation
from .edge import ANGLES, ASK, MIN_FRAME_IOU, SEARCH_SIDE, end_samples, label_ends
from .path import SMOOTH, refine, turn_degrees, viterbi
from .fit import JUMP, LABELS_LINE, UNLABELLED_END, Fit, articulate
from .leaf import Leaf, Line, crest, fit_leaf, iou_curves
from .silhouette import Silhouettes, Views

SPAN = (5.0, 95.0)   # the leaf's extent along the axis: these percentiles of where the keyframes' mask rays pass it
RAYS = 400           # ... over about this many mask pixels a keyframe
PIN = 0.2            # overlap a registered frame's path loses per degree away from its measured angle
MIN_AGREE = 0.6      # the leaf at the registered frames' measured angles must overlap their masks this well (mean)
BEYOND = np.radians(2.5)  # a frame adds a state only this far past the measured angles, or PAST_SHARE of their
PAST_SHARE = 0.1          # span if more: within them the route's own states stand (a propagated mask that kept an
#                           old shape fits an old angle well), and a frame just past them gains little and may be a
#                           mask running ahead of the part
FIT_FRAMES = 24      # registered frames, evenly spread, the leaf's size is refined on
MIN_BEYOND = 3       # ... and only where this many frames do (one frame past the end is a stray mask)
AWAY = 0.1           # frames to draw (`ASK` at most, where an end is the labels' guess) are among those no route
#                      measured, unless every neighbour rests within this share of the span of the other end (the
#                      masks lost it there, not on its way to the end)
GAP = 6              # a frame joins the measured ones through neighbours at most this many frames apart ...
FASTER = 2.0         # ... turning at most this many times as fast as between neighbouring measured frames


def axis_segment(views: Views, keys: list[int], axis: np.ndarray, point: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P, Q) on the axis spanning where the rays through the keyframes' mask pixels pass closest to it: the
    stretch of the axis the part hangs on (the leaf's size search moves its ends from there)."""
    ts = []
    for k in keys:
        ys, xs = np.nonzero(views.masks[k])
        if not len(xs):
            continue
        pick = np.linspace(0, len(xs) - 1, min(RAYS, len(xs))).astype(int)
        uv = np.stack([xs[pick], ys[pick]], 1).astype(np.float64)[:, None]
        xy = cv2.undistortPoints(uv, views.K, None if views.dist is None else np.asarray(views.dist, float))
        r, t = views.w2c[k][:3, :3], views.w2c[k][:3, 3]
        centre = -r.T @ t
        dirs = np.concatenate([xy.reshape(-1, 2), np.ones((len(pick), 1))], 1) @ r
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        b, w = dirs @ axis, point - centre
        good = np.abs(b) < 0.99  # a ray along the axis passes it nowhere in particular
        ts.append(((b * (dirs @ w) - w @ axis) / (1 - b ** 2))[good])
    t = np.concatenate(ts) if ts else np.zeros(1)
    lo, hi = np.percentile(t, SPAN)
    if hi - lo < 1e-6:
        hi = lo + 1.0
    return point + lo * axis, point + hi * axis


def rest_offset(sil: Silhouettes, leaf: Leaf, size: np.ndarray, frames: list[int], rel: np.ndarray
                ) -> tuple[float, float]:
    """(offset, overlap): the leaf's angle at state 0 that makes the registered `frames`, each at its measured
    angle `rel` (F,) from there, overlap their masks most on average."""
    grid = np.linspace(-np.pi, np.pi, 2 * ANGLES, endpoint=False)
    at = leaf.turning(*size)

    def mean(theta: float) -> float:
        return float(np.mean([sil.iou(at(theta + r), i) for i, r in zip(frames, rel)]))

    values = np.array([mean(g) for g in grid])
    best, theta = crest(mean, grid, values)
    return theta, best


def fit_measured(sil: Silhouettes, leaf: Leaf, size: np.ndarray, theta: float, frames: list[int], rel: np.ndarray
                 ) -> tuple[np.ndarray, float, float]:
    """(size, offset, overlap): the leaf's size and its angle at state 0 refined together so the registered `frames`,
    each at its measured angle `rel` from there, overlap their masks most on average. Why: a size fitted to masks
    alone leaves the free edge loose where the keyframes show the leaf closed and cut by the image border (a wider
    leaf turned less casts the same silhouette); frames at several measured angles pin it."""
    pick = frames if len(frames) <= FIT_FRAMES else [frames[i] for i in
                                                     np.linspace(0, len(frames) - 1, FIT_FRAMES).round().astype(int)]
    at_rel = dict(zip(frames, rel))

    def mean(x: np.ndarray) -> float:
        if x[0] <= 0.05 or x[2] - x[1] < 0.2:
            return 0.0
        at = leaf.turning(*x[:3])
        return float(np.mean([sil.iou(at(x[3] + at_rel[i]), i) for i in pick]))

    x0 = np.array([*size, theta])
    res = minimize(lambda x: -mean(x), x0, method="Nelder-Mead",
                   options={"xatol": 1e-3, "fatol": 1e-4, "maxiter": 150,
                            "initial_simplex": x0 + np.diag([0.1 * size[0], 0.1, 0.1, np.radians(3), 0.0])[:, :4]})
    return res.x[:3], float(res.x[3]), mean(res.x)


def unmeasured(fig: dict[str, Any]) -> bool:
    """Whether an end of the motion in `fig` is the labels' guess or the measured extent with no label near it
    (`fit.end_state`): where reading the masks past the measured angles can measure it."""
    ends = fig.get("ends_from", "")
    return LABELS_LINE in ends or UNLABELLED_END in ends


def guessed_ends(fig: dict[str, Any]) -> list[str]:
    """The ends ('closed', 'open') of the motion in `fig` whose state is the labels' line: no route measured the
    part there (`fit.end_state`)."""
    parts = [p.strip() for p in fig.get("ends_from", "").split(";")]
    return [end for end in ("closed", "open") if any(p.startswith(f"{end} end") and LABELS_LINE in p for p in parts)]


def frames_to_draw(fig: dict[str, Any], n: int, keys: list[int], prefer: list[int]) -> list[int]:
    """Dataset positions (at most `ASK`) where a mask a person draws would let the masks carry the motion to the end
    its routes did not measure (`guessed_ends`): inside the runs of frames no route measured (at least `MIN_BEYOND`
    long) but those between frames resting at the other end (`AWAY`; the part may have gone on to the end in any
    other), the masks stage's own suggestions there first (`prefer`), else each run's middle, longest run first; [] where both
    ends were measured or no such run is left (a route that read every frame from its masks). Why: with the masks of
    a door whose open side turned from every camera lost, the labels' guess scales its range (simulated doors 24-79 %
    off); a few drawn masks there are what lets reading the masks measure it."""
    guessed = guessed_ends(fig)
    measured = {int(f): float(s) for f, s in fig.get("frame_states", [])}
    if not guessed or not measured:
        return []
    at = np.array(sorted(measured))
    s = np.array([measured[f] for f in at])
    band = AWAY * float(np.ptp(s))
    far: set[int] = set(at.tolist())
    for end in guessed:  # the frames resting at the other end (the closed end is the states' low side)
        far &= set((at[s >= s.max() - band] if end == "closed" else at[s <= s.min() + band]).tolist())
    runs = [list(range(a + 1, b)) for a, b in zip([-1, *at.tolist()], [*at.tolist(), n])  # the video's ends too
            if b - a - 1 >= MIN_BEYOND and any(0 <= x < n and x not in far for x in (a, b))]
    wanted, skip = [], set(keys)
    for run in sorted(runs, key=len, reverse=True):
        middle = run[len(run) // 2]
        wanted += [f for f in prefer if f in run and f not in skip] or ([middle] if middle not in skip else [])
    return sorted(wanted[:ASK])


def connected(frames: np.ndarray, d: np.ndarray, pinned: np.ndarray, candidate: np.ndarray) -> np.ndarray:
    """(F,) bool: the `candidate` frames joined to a `pinned` one through frames kept: each at most `GAP` frames
    from the nearest kept on either side and turned from each at most `FASTER` times as fast as the part turns
    between neighbouring pinned frames (a quarter of the span a frame where none are neighbours: `fit.jumpy_frames`'
    bound). Why: a propagated mask that runs ahead of the part reads far past the measured angles right after a
    registered frame near rest, and a run of such frames agrees with itself, so no single-frame check sees it; a
    person opens a part at one pace, not several times faster where the route lost it."""
    order = np.argsort(frames, kind="stable")
    at = order[pinned[order]]
    gaps = np.diff(frames[at]).astype(float)
    near = (gaps > 0) & (gaps <= GAP)
    speed = float(np.max(np.abs(np.diff(d[at]))[near] / gaps[near])) if near.any() else 0.0
    use = pinned | candidate
    limit = FASTER * speed if speed > 0 else JUMP * (float(np.ptp(d[use])) if use.any() else 0.0)
    keep = pinned.copy()
    grown = True
    while grown:
        grown = False
        for n in order[candidate[order] & ~keep[order]]:
            sides = [k for k in (_nearest(frames, keep, n, -1), _nearest(frames, keep, n, 1)) if k is not None]
            if sides and all(abs(d[n] - d[m]) <= limit * abs(int(frames[n]) - int(frames[m])) for m in sides):
                keep[n] = grown = True
    return keep & candidate


def _nearest(frames: np.ndarray, keep: np.ndarray, n: int, side: int) -> int | None:
    """The kept frame nearest frame n on one side (-1 before, +1 after), within `GAP` frames, or None."""
    gap = (frames - frames[n]) * side
    idx = np.flatnonzero(keep & (gap > 0) & (gap <= GAP))
    return int(idx[np.argmin(gap[idx])]) if len(idx) else None


def reach_hinge(views: Views, motion: Articulation, fig: dict[str, Any], frames: list[int], keys: list[int],
                states: np.ndarray, known: np.ndarray, labelled: np.ndarray, trust_labels: bool = False
                ) -> tuple[Articulation | None, dict[str, Any]]:
    """The hinge `motion` (its `fig`, with `frame_states`) with the states of the frames among `frames` (dataset
    positions whose mask shows the part) that it did not measure read from their masks; (None, why in
    `reach_reason`) where the leaf does not explain the registered frames' masks or no frame is added."""
    measured = {int(f): float(s) for f, s in fig.get("frame_states", [])}
    keys = [k for k in keys if k in frames]
    if not keys or not measured:
        return None, {"reach_reason": "no keyframe mask or no measured frame to start from"}
    sil = Silhouettes(views, frames)
    shown = [i for i in frames if i in sil.crop]
    reg = [i for i in shown if i in measured]
    if not reg:
        return None, {"reach_reason": "no frame it measured has a mask the masks stage trusts"}
    p, q = axis_segment(views, keys, motion.axis, motion.origin)
    cam = -views.w2c[keys[0]][:3, :3].T @ views.w2c[keys[0]][:3, 3]
    line = Line.seen_from(p, q, 0.0, keys[0], cam)
    still, ends = label_ends(shown, states, known)
    size, size_fit = fit_leaf(Silhouettes(views, frames, SEARCH_SIDE), line, shown, keys, end_samples(shown, ends))
    leaf = Leaf(line)
    rel = motion.range * np.array([measured[i] for i in reg])
    theta, agree = rest_offset(sil, leaf, size, reg, rel)
    size, theta, agree = fit_measured(sil, leaf, size, theta, reg, rel)
    out: dict[str, Any] = {"reach_leaf": [round(float(v), 3) for v in size], "reach_leaf_iou": round(size_fit, 3),
                           "reach_agree_iou": round(agree, 3)}
    if agree < MIN_AGREE:
        out["reach_reason"] = (f"a leaf on the measured axis at the measured angles overlaps the registered frames' "
                               f"masks by {agree:.2f} (need {MIN_AGREE}): the masks cannot carry the motion further")
        return None, out
    angles = np.linspace(-np.pi, np.pi, ANGLES, endpoint=False)
    raw = iou_curves(sil, leaf, size, shown, angles)
    curves, turns = raw.copy(), turn_degrees(angles)
    pinned = np.isin(shown, reg)
    at_rel = dict(zip(reg, rel))
    for n in np.flatnonzero(pinned):  # a registered frame's path passes its measured angle
        j = int(np.argmin(np.abs(np.angle(np.exp(1j * (angles - theta - at_rel[shown[n]]))))))
        curves[n] = raw[n, j] - PIN * turns[j]
    path, _ = viterbi(curves, SMOOTH * turns, still)
    phi = np.unwrap(np.array([refine(raw[f], j, angles) for f, j in enumerate(path)]))
    iou = raw[np.arange(len(shown)), path]
    first = int(np.flatnonzero(pinned)[0])
    phi -= 2 * np.pi * np.round((phi[first] - theta - at_rel[shown[first]]) / (2 * np.pi))  # the turn it is on
    d = phi - theta
    past = max(BEYOND, PAST_SHARE * float(np.ptp(rel)))
    beyond = ~pinned & (iou >= MIN_FRAME_IOU) & ((d > rel.max() + past) | (d < rel.min() - past))
    beyond &= connected(np.array(shown), np.array([at_rel.get(i, v) for i, v in zip(shown, d)]), pinned, beyond)
    out.update(reach_beyond=int(beyond.sum()),
               reach_mean_iou=round(float(iou[beyond].mean()), 3) if beyond.any() else None)
    if beyond.sum() < MIN_BEYOND:
        out["reach_reason"] = (f"{int(beyond.sum())} of the frames it did not register show it {np.degrees(past):.1f}"
                               f" deg or more beyond the measured angles (a leaf on its axis overlapping their masks "
                               f"by {MIN_FRAME_IOU} or more, at the pace it keeps; need {MIN_BEYOND})")
        return None, out
    added = {i: float(v) for i, v, b in zip(shown, d, beyond) if b}
    at = np.array(sorted(set(measured) | set(added)))
    dd = np.array([motion.range * measured[i] if i in measured else added[i] for i in at])
    fit = Fit("hinge", motion.axis.copy(), motion.origin.copy(), dd, np.ones(len(at), bool), np.zeros(len(at)),
              1.0, {})
    extra = {k: v for k, v in fig.items() if k not in ("frame_states", "label_check", "flagged_labels")}
    extra.update(out)
    return articulate(fit, at, states[at], known[at], labelled[at], extra, trust_labels)
