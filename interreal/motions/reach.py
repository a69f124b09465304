"""A measured hinge carried into the frames its route never registered: the leaf turning on the measured axis,
each such frame's angle read from its mask.

A part's own reconstruction registers the frames whose texture it matches; once a door or cover turns its plain
side or its edge to the camera, nothing registers, and the open end of the motion was the labels' guess (simulated
textured doors with eyeballed labels: the registered frames reach 0.26-0.52 of the way open, the range then 24-79 %
off). The masks still show the part there. With the axis measured, one rectangle hinged on it (`leaf.fit_leaf`)
casts each frame's silhouette at each angle; the registered frames pin the leaf's angle at rest (their measured
angles, shifted by one offset that fits their masks best) and every other frame's angle follows its mask along a
smooth path through them (`edge`'s dynamic programming). The route's measured frames are kept as they are; the
reached frames only add states, and the whole is judged again (`fit.articulate`), so the measured ends of the
motion, not the labels' line, become its states 0 and 1.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from ..dataset import Articulation
from .edge import (ANGLES, MIN_FRAME_IOU, SEARCH_SIDE, SMOOTH, end_samples, label_ends, refine, turn_degrees,
                   viterbi)
from .fit import Fit, articulate
from .leaf import Leaf, Line, crest, fit_leaf, iou_curves
from .silhouette import Silhouettes, Views

SPAN = (5.0, 95.0)   # the leaf's extent along the axis: these percentiles of where the keyframes' mask rays pass it
RAYS = 400           # ... over about this many mask pixels a keyframe
PIN = 0.2            # overlap a registered frame's path loses per degree away from its measured angle
MIN_AGREE = 0.6      # the leaf at the registered frames' measured angles must overlap their masks this well (mean)
BEYOND = np.radians(2.5)  # a frame adds a state only this far past the measured angles: within them the route's
#                           own states stand (a propagated mask that kept an old shape fits an old angle well)
MIN_BEYOND = 3       # ... and only where this many frames do (one frame past the end is a stray mask)


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
    p, q = axis_segment(views, keys, motion.axis, motion.origin)
    cam = -views.w2c[keys[0]][:3, :3].T @ views.w2c[keys[0]][:3, 3]
    line = Line.seen_from(p, q, 0.0, keys[0], cam)
    coarse, sil = Silhouettes(views, frames, SEARCH_SIDE), Silhouettes(views, frames)
    shown = [i for i in frames if i in sil.crop]
    still, ends = label_ends(shown, states, known)
    size, size_fit = fit_leaf(coarse, line, shown, keys, end_samples(shown, ends))
    leaf = Leaf(line)
    reg = [i for i in shown if i in measured]
    if not reg:
        return None, {"reach_reason": "no frame it measured has a mask the masks stage trusts"}
    rel = motion.range * np.array([measured[i] for i in reg])
    theta, agree = rest_offset(sil, leaf, size, reg, rel)
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
    beyond = ~pinned & (iou >= MIN_FRAME_IOU) & ((d > rel.max() + BEYOND) | (d < rel.min() - BEYOND))
    out.update(reach_beyond=int(beyond.sum()),
               reach_mean_iou=round(float(iou[beyond].mean()), 3) if beyond.any() else None)
    if beyond.sum() < MIN_BEYOND:
        out["reach_reason"] = (f"{int(beyond.sum())} frames it did not register overlap the leaf by {MIN_FRAME_IOU} "
                               f"or more beyond the measured angles (need {MIN_BEYOND})")
        return None, out
    added = {i: float(v) for i, v, b in zip(shown, d, beyond) if b}
    at = np.array(sorted(set(measured) | set(added)))
    dd = np.array([motion.range * measured[i] if i in measured else added[i] for i in at])
    fit = Fit("hinge", motion.axis.copy(), motion.origin.copy(), dd, np.ones(len(at), bool), np.zeros(len(at)),
              1.0, {})
    extra = {k: v for k, v in fig.items() if k not in ("frame_states", "label_check", "flagged_labels")}
    extra.update(out)
    return articulate(fit, at, states[at], known[at], labelled[at], extra, trust_labels)
