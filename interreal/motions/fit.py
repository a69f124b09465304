"""A part's motion from its per-frame rigid poses, decided by the geometry and calibrated by the labels.

`interreal motions` gives, per frame that the part's own reconstruction registered, the part's pose in the world
(`PartViews`; the reconstruction's scale unknown). Both models are fitted to those poses without any label:
- hinge: the relative rotations share one axis; each frame's angle about it is measured, and the positions are
  then linear in the scale, the reference pose and a point on the axis;
- slide: the orientation stays; the positions lie on one line (scale and line found by alternating least squares).
The kind is the hinge when the part turns clearly beyond its rotation noise *and* the angle explains the positions
at least as well as a line does; otherwise a slide. Human state labels are eyeballed (off by 0.1-0.5 on real
captures), so they do not measure anything here: the measured displacement (angle or distance) gives every frame's
state; its two ends are states 0 and 1, and the labels only say which end is closed (and, where every label near an
end is clearly intermediate and none says that end's state, that the video stops short of it: the scale). Labels
that disagree with the measured state by more than `FLAG_TOL` are reported as likely mistakes, never a reason to
drop the motion: it is used when its own evidence holds (enough trusted frames, a range above its noise, states that
change smoothly from frame to frame, a reconstruction that does not turn with the camera). `trust_labels` restores
the labels as the judge (a line through them calibrates, and most of them disagreeing refuses the motion).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import kendalltau

from ..dataset import Articulation

SLIDE_MAX_DEG = 3.0  # a part whose angle spans less than this (or less than TURN_NOISE x its noise) does not turn
TURN_NOISE = 6.0  # a hinge's angle must span this many times the part's rotation noise
OFF_AXIS_DEG = 3.0  # a frame whose turn leaves the hinge axis by more than this is misregistered
POS_WORSE = 2.0  # a hinge whose positions fit this much worse than a line's (plus POS_FLOOR) is no hinge
POS_FLOOR = 0.01  # ... share of the camera-part distance that counts as position noise
END_SHARE = 0.05  # an end of the motion starts from the median of this share of the frames at that extreme
END_BAND = 0.1  # ... and is the middle of the frames within this share of the span from it (where the part rests)
SNAP = 0.2  # an end whose label fit lies within this of 0 or 1 is that state
FLAG_TOL = 0.25  # a label further than this from the measured state is a likely mistake
LABEL_TOL = 0.15  # with trust_labels: the motion is refused when the labels' median disagreement exceeds this ...
MAX_FLAGGED = 1 / 3  # ... or more than this share of the labels are flagged
END_NEAR = 0.25  # labels of one value orient the motion only when all lie within this share of the span of one end
ORDER_P = 0.01  # labels whose order along the measured motion is this unlikely by chance orient it by their trend
UNLABELLED_END = "no label near it"  # how `end_state` says an end's state is the geometry's alone ...
LABELS_LINE = "the labels' line"  # ... or the labels' guess, where no route measured the part further
JUMP = FLAG_TOL  # a frame whose state leaves its neighbours' median by more than this is misregistered ...
MAX_JUMPY = 1 / 3  # ... and a motion with more than this share of such frames is noise, not motion
MAX_RESIDUAL = 0.25  # a motion whose positions miss the part's by more than this share of how far it moves the
#                      part explains nothing (a reconstruction bent by a drifting scale)
MIN_MOVE = 4.0  # a slide must move this many times its position noise (else the part did not move)
FOLLOW = 0.6  # a part that turns this share of the camera's turn while the labels say it rests: a bad reconstruction
REST_FRAMES = 6  # ... judged over at least this many resting frames (stretches of 3 or more)
REST_NOISE_DEG = 1.0  # ... and only when it turns more than this (rotation noise) and the camera at least this much


@dataclass
class PartViews:
    """Per registered frame (dataset positions `frames`): the part's reconstruction seen from the world.

    rot (F, 3, 3): reconstruction -> world rotation at that frame; u (F, 3): the offset from the camera to the part's
    middle (`part_point`) rotated into the world (world units once multiplied by the reconstruction's unknown
    scale); centre (F, 3): camera centre; cam_rot (F, 3, 3): the camera's own rotation (camera -> world), when
    known, to tell a part that rests from a reconstruction that turns with the camera (`turns_with_camera`)."""

    frames: np.ndarray
    rot: np.ndarray
    u: np.ndarray
    centre: np.ndarray
    cam_rot: np.ndarray | None = None


def part_point(points: np.ndarray) -> np.ndarray:
    """(3,) the point of a part whose path is followed: the median of its points (N, 3), origin when none.

    A small part seen from afar has a poorly determined rotation relative to the camera (a few degrees); a point
    far from the part (a reconstruction's origin sits near its first camera, a metre away) swings with that error
    by centimetres, the middle of the part's own points hardly moves: on simulated drawers the slide direction
    went from 3.7-11 deg off to 0.7-2.6 deg, hinge axes' positions 30 % closer."""
    return np.median(points, 0) if len(points) else np.zeros(3)


# ----------------------------------------------------------------------------------------------------------------
# small robust tools
# ----------------------------------------------------------------------------------------------------------------
def rotvecs(r: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(r).as_rotvec()


def axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(np.outer(np.atleast_1d(angle), axis)).as_matrix()


def robust_line(x: np.ndarray, y: np.ndarray, iters: int = 20) -> tuple[float, float]:
    """(slope, intercept) of y = slope * x + intercept, Huber-weighted (a few wrong labels or frames)."""
    w = np.ones_like(x)
    slope, icpt = 0.0, float(np.median(y))
    for _ in range(iters):
        a = np.stack([x, np.ones_like(x)], 1) * w[:, None]
        slope, icpt = np.linalg.lstsq(a, y * w, rcond=None)[0]
        r = np.abs(y - slope * x - icpt)
        k = 1.345 * max(float(np.median(r)) / 0.6745, 1e-9)
        w = np.sqrt(np.where(r <= k, 1.0, k / np.maximum(r, 1e-12)))
    return float(slope), float(icpt)


def huber_weights(r: np.ndarray) -> np.ndarray:
    """(F,) IRLS weights of residual norms r (F,): 1 within 1.345 robust sigmas, falling as 1/r beyond."""
    k = 1.345 * max(float(np.median(r)) / 0.6745, 1e-12)
    return np.where(r <= k, 1.0, k / np.maximum(r, 1e-12))


def robust_lstsq(a: np.ndarray, b: np.ndarray, rows: int = 3, iters: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Huber IRLS of a x = b where each group of `rows` equations is one frame: (x, per-frame residual norms)."""
    w = np.ones(len(b) // rows)
    x = np.zeros(a.shape[1])
    r = np.zeros(len(w))
    for _ in range(iters):
        ww = np.repeat(np.sqrt(w), rows)
        x = np.linalg.lstsq(a * ww[:, None], b * ww, rcond=None)[0]
        r = np.linalg.norm((a @ x - b).reshape(-1, rows), axis=1)
        w = huber_weights(r)
    return x, r


def basis(axis: np.ndarray) -> np.ndarray:
    """(3, 2): two unit vectors perpendicular to `axis` and to each other."""
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(axis, e1)], 1)


def off_axis_deg(vecs: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(F,) how far each rotation vector (F, 3) turns about anything but `axis`, in degrees."""
    return np.degrees(np.linalg.norm(vecs - np.outer(vecs @ axis, axis), axis=1))


def principal(vecs: np.ndarray) -> np.ndarray:
    """The direction rotation vectors (F, 3) lie along, weighted by their size (small turns are mostly noise)."""
    turn = np.linalg.norm(vecs, axis=1)
    if turn.max() < 1e-9:
        return np.array([0.0, 0.0, 1.0])
    _, _, vt = np.linalg.svd(vecs * turn[:, None])
    return vt[0]


def vote_axis(vecs: np.ndarray, candidates: int = 64) -> np.ndarray:
    """The turn direction of one of the frames that turn clearly, the one the most frames agree with."""
    turn = np.degrees(np.linalg.norm(vecs, axis=1))
    big = np.flatnonzero(turn > 2 * OFF_AXIS_DEG)
    if not len(big):
        return principal(vecs)  # nothing turns beyond the noise: any axis will do (a slide)
    big = big[np.linspace(0, len(big) - 1, min(candidates, len(big))).round().astype(int)]
    axes = vecs[big] / np.linalg.norm(vecs[big], axis=1, keepdims=True)
    votes = [int((off_axis_deg(vecs, a) < OFF_AXIS_DEG).sum()) for a in axes]
    return axes[int(np.argmax(votes))]


def consensus(rot: np.ndarray, tries: int = 12) -> tuple[int, np.ndarray, np.ndarray]:
    """(reference frame, hinge axis, inliers (F,) bool): the relative rotations of a rigid part's frames share one
    axis; a misregistered frame does not. Up to `tries` frames are tried as the reference (it may be misregistered
    itself); the axis is the one most frames agree with (within OFF_AXIS_DEG), refitted on those."""
    best: tuple[int, int, np.ndarray, np.ndarray] | None = None
    cands = np.linspace(0, len(rot) - 1, min(tries, len(rot))).round().astype(int)
    for ref in cands:
        vecs = rotvecs(np.einsum("fij,kj->fik", rot, rot[ref]))
        axis = vote_axis(vecs)
        inl = np.ones(len(vecs), bool)
        for _ in range(3):
            inl = off_axis_deg(vecs, axis) < OFF_AXIS_DEG
            axis = principal(vecs[inl]) if inl.sum() >= 2 else axis
        if best is None or inl.sum() > best[1]:
            best = (int(ref), int(inl.sum()), axis, inl)
    assert best is not None
    return best[0], best[2], best[3]


def spread_deg(rot: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
    """(F,) degrees each rotation (F, 3, 3) turns from the mean orientation (of the `keep` ones, default all)."""
    rots = Rotation.from_matrix(rot)
    return np.degrees((rots * (rots if keep is None else rots[keep]).mean().inv()).magnitude())


def still_frames(rot: np.ndarray) -> np.ndarray:
    """(F,) bool: frames whose rotation stays within max(SLIDE_MAX_DEG, 3 x the median) of the mean orientation
    (recomputed on the kept frames, so a flipped frame does not pull it)."""
    keep = np.ones(len(rot), bool)
    for _ in range(3):
        dev = spread_deg(rot, keep)
        keep = dev <= max(SLIDE_MAX_DEG, 3 * float(np.median(dev)))
    return keep


def ends(d: np.ndarray, iters: int = 3) -> tuple[float, float]:
    """The two ends of a displacement (F,). A part rests at its ends (closed, open) for many frames, so an end is
    the middle of the frames within END_BAND of the span from it, re-centred a few times, starting from the median
    of the END_SHARE most extreme frames: the extremes alone sit ~2 noise widths beyond the true end (a noisy
    drawer's range came out 15 % long)."""
    k = max(1, int(round(END_SHARE * len(d))))
    s = np.sort(d)
    lo, hi = float(np.median(s[:k])), float(np.median(s[-k:]))
    band = END_BAND * (hi - lo)
    for _ in range(iters):
        lo, hi = float(np.median(s[s <= lo + band])), float(np.median(s[s >= hi - band]))
    return lo, hi


# ----------------------------------------------------------------------------------------------------------------
# the two models, fitted without labels
# ----------------------------------------------------------------------------------------------------------------
@dataclass
class Fit:
    """One model's fit: displacement d (F,) (radians about `axis` or world units along it), the frames it
    trusts (ok), per-frame position residual (world units), its scale, a point (hinge: on the axis; slide: the
    reference position) and figures for the report."""

    kind: str
    axis: np.ndarray
    point: np.ndarray
    d: np.ndarray
    ok: np.ndarray
    pos_resid: np.ndarray
    scale: float
    figures: dict[str, Any]


def rotation_noise_deg(vecs: np.ndarray, axis: np.ndarray, ok: np.ndarray) -> float:
    """Per-frame rotation noise: the off-axis turn between consecutive trusted frames (no hinge turns there)."""
    idx = np.flatnonzero(ok)
    if len(idx) < 3:
        return float(np.median(off_axis_deg(vecs[ok], axis))) if ok.any() else 0.0
    step = vecs[idx[1:]] - vecs[idx[:-1]]  # small turns: rotation vectors subtract
    return float(np.median(off_axis_deg(step, axis))) / np.sqrt(2)


def fit_hinge(pv: PartViews) -> Fit:
    """Axis and angle from the rotations alone; scale, reference position and axis point from the translations:
    sigma u_f + C_f = R_f b + (I - R_f) o, o = B w (linear), R_f the turn relative to the reference frame."""
    ref, axis, ok = consensus(pv.rot)
    vecs = rotvecs(np.einsum("fij,kj->fik", pv.rot, pv.rot[ref]))
    angle = vecs @ axis
    moved = axis_angle(axis, angle)
    bas = basis(axis)
    f = len(pv.frames)
    a = np.concatenate([pv.u[..., None], -moved, -((np.eye(3)[None] - moved) @ bas)], axis=2)
    sol, _ = robust_lstsq(a[ok].reshape(-1, 6), -pv.centre[ok].reshape(-1))
    resid = np.linalg.norm((a.reshape(3 * f, 6) @ sol + pv.centre.reshape(-1)).reshape(f, 3), axis=1)
    lo, hi = ends(angle[ok]) if ok.any() else (0.0, 0.0)
    fig = {"turn_deg": round(float(np.degrees(hi - lo)), 2),
           "rot_noise_deg": round(float(rotation_noise_deg(vecs, axis, ok)), 3),
           "off_axis_deg": round(float(np.median(off_axis_deg(vecs[ok], axis))), 3) if ok.any() else None,
           "hinge_rejected": int((~ok).sum())}
    return Fit("hinge", axis, bas @ sol[4:6], angle, ok, resid, float(sol[0]), fig)


def fit_slide(pv: PartViews, iters: int = 30) -> Fit:
    """Scale and line of p_f = sigma u_f + C_f = b + d_f v over the frames that keep the part's usual orientation
    (a slide does not turn): alternately the line of the points (PCA weighted by the last step's robust weights:
    a few misregistered frames tilted an unweighted line by degrees) and the scale with the line's direction held
    (linear once the direction is projected out)."""
    ok = still_frames(pv.rot)
    u, c = pv.u[ok], pv.centre[ok]
    uc, cc = u - u.mean(0), c - c.mean(0)
    sigma = -float((uc * cc).sum() / max((uc * uc).sum(), 1e-12))  # as if the part never moved
    v = np.array([1.0, 0.0, 0.0])
    b = np.zeros(3)
    w = np.ones(len(u))
    for it in range(iters):
        p = sigma * u + c
        mid = (p * w[:, None]).sum(0) / w.sum()
        _, _, vt = np.linalg.svd((p - mid) * np.sqrt(w)[:, None])
        v = vt[0]
        q = np.eye(3) - np.outer(v, v)
        a = np.concatenate([(u @ q)[..., None], -np.broadcast_to(q, (len(u), 3, 3))], axis=2).reshape(-1, 4)
        sol, r = robust_lstsq(a, -(c @ q).reshape(-1))
        sigma, b = float(sol[0]), sol[1:4]
        if it >= iters // 2:  # weights only near the solution: far from it they would favour the resting frames
            w = huber_weights(r)
    p = sigma * pv.u + pv.centre
    d = (p - b) @ v
    q = np.eye(3) - np.outer(v, v)
    resid = np.linalg.norm((p - b) @ q, axis=1)
    fig = {"slide_rejected": int((~ok).sum())}
    return Fit("slide", v, b, d, ok, resid, sigma, fig)


def choose(hinge: Fit, slide: Fit, pv: PartViews) -> tuple[Fit, dict[str, Any]]:
    """The hinge when the part turns clearly beyond its rotation noise and its angle explains the positions no
    worse than a line (POS_WORSE x, plus POS_FLOOR of the viewing distance); else the slide."""
    dist = float(np.median(np.linalg.norm(hinge.scale * pv.u, axis=1)))
    floor = POS_FLOOR * dist
    hp = float(np.median(hinge.pos_resid[hinge.ok])) if hinge.ok.any() else np.inf
    sp = float(np.median(slide.pos_resid[slide.ok])) if slide.ok.any() else np.inf
    noise = hinge.figures["rot_noise_deg"]
    turns = hinge.figures["turn_deg"] > max(SLIDE_MAX_DEG, TURN_NOISE * noise)
    explains = hp <= POS_WORSE * sp + floor
    evidence = {"turn_deg": hinge.figures["turn_deg"], "rot_noise_deg": noise, "turns": bool(turns),
                "hinge_pos_residual": round(hp, 6), "slide_pos_residual": round(sp, 6),
                "angle_explains_positions": bool(explains)}
    return (hinge if turns and explains else slide), evidence


def rest_stretches(states: np.ndarray, known: np.ndarray, least: int = 3) -> list[np.ndarray]:
    """Runs (positions) of at least `least` consecutive frames whose known state is one value: the part rests."""
    cut = np.flatnonzero(~known[1:] | ~known[:-1] | (np.abs(np.diff(states)) >= 1e-6)) + 1
    return [r for r in np.split(np.arange(len(states)), cut) if len(r) >= least and known[r[0]]]


def turns_with_camera(pv: PartViews, states: np.ndarray, known: np.ndarray) -> dict[str, Any] | None:
    """A nearly flat part's own reconstruction sometimes reads the camera's turn as a turn of the part (its cameras
    barely turn relative to it): the part then seems to turn with the camera even where the labels say it rests.
    Over those stretches: the part's median turn from its mean orientation against the camera's. On simulated
    drawers and doors the good reconstructions turned 0.04-0.35 of the camera's turn, the bad ones 0.95-1.12
    (they gave a door as a slide and drawers as hinges). None when it cannot be judged (no camera rotations, too
    few resting frames, a camera that hardly turns there)."""
    if pv.cam_rot is None:
        return None
    runs = rest_stretches(states, known)
    resting = sum(len(r) for r in runs)
    if resting < REST_FRAMES:
        return None
    part = float(np.median(np.concatenate([spread_deg(pv.rot[r]) for r in runs])))
    cam = float(np.median(np.concatenate([spread_deg(pv.cam_rot[r]) for r in runs])))
    if cam < REST_NOISE_DEG:
        return None
    return {"rest_frames": int(resting), "rest_turn_deg": round(part, 2),
            "camera_turn_deg": round(cam, 2), "follows_camera": bool(part > max(FOLLOW * cam, REST_NOISE_DEG))}


# ----------------------------------------------------------------------------------------------------------------
# states from the displacement, the labels fixing the ends
# ----------------------------------------------------------------------------------------------------------------
@dataclass
class Calibration:
    """state = (d - d0) / rate; `rate` the displacement per unit state (signed as measured)."""

    d0: float
    rate: float
    end_states: tuple[float, float]  # the states of the low and the high end of d
    source: str = ""  # what oriented (and scaled) it, for the report


def _snap(s: float) -> float:
    for target in (0.0, 1.0):
        if abs(s - target) <= SNAP:
            return target
    return float(np.clip(s, 0.0, 1.0))


def calibrate_by_labels(d: np.ndarray, ok: np.ndarray, labels: np.ndarray, labelled: np.ndarray
                        ) -> Calibration | None:
    """`trust_labels`: the displacement's ends (over the trusted frames) get the states a robust line through the
    labels gives them, snapped to 0 / 1 when near; None when the labels cannot orient the motion (fewer than two
    distinct labelled states on trusted frames, or the displacement does not vary)."""
    lab = ok & labelled
    if lab.sum() < 2 or np.ptp(labels[lab]) < 2 * SNAP or not ok.any():
        return None
    lo, hi = ends(d[ok])
    if hi - lo <= 1e-12:
        return None
    slope, icpt = robust_line(d[lab], labels[lab])
    if slope == 0:
        return None
    s_lo, s_hi = _snap(icpt + slope * lo), _snap(icpt + slope * hi)
    if s_lo == s_hi:  # both ends snapped alike: trust the order the labels give, the span they give
        s_lo, s_hi = (0.0, 1.0) if slope > 0 else (1.0, 0.0)
    rate = (hi - lo) / (s_hi - s_lo)
    return Calibration(lo - s_lo * rate, rate, (s_lo, s_hi), "labels (--trust-labels)")


def orientation(x: np.ndarray, y: np.ndarray) -> tuple[int, str]:
    """(+1: the high end of the displacement is open, -1: the low end, 0: cannot tell; why) from labels y at
    positions x (F,) along the measured motion (0 at its low end, 1 at its high end).

    Labels that vary orient by their trend (a robust line's slope: each may be off by 0.5, the order holds); labels
    of one value orient only when they all lie near one end and name a closed or open state (a part-way value
    there says nothing of which way the part went)."""
    if len(x) == 0:
        return 0, "no labelled frame was measured"
    if np.ptp(y) >= 2 * SNAP:
        slope, _ = robust_line(x, y)
        return (1 if slope > 0 else -1 if slope < 0 else 0), "the labels' trend"
    if order := _order(x, y):
        return order, "the labels' order along it"
    v, where = float(np.median(y)), float(np.median(x))
    said = f"every label says {v:.2f}" if np.ptp(y) == 0 else f"the labels say {y.min():.2f} to {y.max():.2f}"
    if not (x.max() <= END_NEAR or x.min() >= 1 - END_NEAR):
        return 0, (f"{said}, but the measurement puts those frames at positions {x.min():.2f} to {x.max():.2f} of "
                   f"its motion, not at one end nor in their order: label both ends, or the measurement is wrong")
    if SNAP < v < 1 - SNAP:  # part-way at one end: the other end could be closed or open
        return 0, f"{said}, part-way, at one end of the measured motion: label a frame at the other end"
    return (1 if (where > 0.5) == (v > 0.5) else -1), f"{said} near one end"


def _order(x: np.ndarray, y: np.ndarray) -> int:
    """+1 / -1: labels that change little but rise / fall along the measured motion beyond chance (Kendall's tau,
    one-sided, under `ORDER_P`), else 0. A video whose part was measured only part way open (its open frames never
    registered) is oriented by its labels' order, not refused as if they all said one value."""
    if len(x) < 3 or np.ptp(y) == 0 or np.ptp(x) == 0:
        return 0
    tau, p = kendalltau(x, y)
    return int(np.sign(tau)) if np.isfinite(p) and p / 2 < ORDER_P else 0


def end_state(x: np.ndarray, y: np.ndarray, end: float, state: float) -> tuple[float, str]:
    """(state, how) of the measured motion's end at position `end` (0 or 1 along it) whose nominal state is
    `state` (0 closed, 1 open): `state`, unless the labels say otherwise and their robust line puts that end clearly
    short of it (a video that only opens a door half way, labelled so on purpose). What the labels say of an end is
    the median label of the frames measured there (within END_BAND of it), not any one label: one eyeballed 0.95 on
    a half-open frame must not make fully open the end of a door no route measured further than 0.64 (its open
    frames turn the front away from every camera). With no frame measured there, any label near `state` says it."""
    how = f"the measured end ({UNLABELLED_END})" if not (np.abs(x - end) <= END_NEAR).any() else "labelled"
    there = np.abs(x - end) <= END_BAND
    told = float(np.median(y[there])) if there.any() else None  # what the labels of the frames there say together
    says = abs(told - state) <= SNAP if told is not None else bool((np.abs(y - state) <= SNAP).any())
    if says or len(x) < 2 or np.ptp(x) < END_NEAR:
        return state, how
    slope, icpt = robust_line(x, y)
    value = float(np.clip(icpt + slope * end, 0.0, 1.0))
    if abs(value - state) <= SNAP:
        return state, how
    said = f"the frames measured there are labelled {told:.2f}" if told is not None else f"no label says {state:g}"
    return round(value, 3), f"{LABELS_LINE} ({said})"


def calibrate(d: np.ndarray, ok: np.ndarray, labels: np.ndarray, labelled: np.ndarray
              ) -> tuple[Calibration | None, str]:
    """The measured displacement's ends (over the trusted frames) are states 0 and 1; the labels say which end is
    which (`orientation`) and, where they never name an end's state and put it clearly short, that end's state
    (`end_state`). (None, why) when the labels cannot orient the motion or the displacement does not vary."""
    if not ok.any():
        return None, "no frame was measured"
    lo, hi = ends(d[ok])
    if hi - lo <= 1e-12:
        return None, "the measured displacement does not vary"
    lab = ok & labelled
    x, y = (d[lab] - lo) / (hi - lo), labels[lab]
    sign, why = orientation(x, y)
    if sign == 0:
        return None, f"the labels do not orient the motion ({why})"
    open_end, closed_end = (1.0, 0.0) if sign > 0 else (0.0, 1.0)
    (s_open, how_open), (s_closed, how_closed) = end_state(x, y, open_end, 1.0), end_state(x, y, closed_end, 0.0)
    if s_open - s_closed <= SNAP / 2:  # ends that would meet or cross: the labels are too rough to scale by
        (s_open, how_open), (s_closed, how_closed) = (1.0, "the measured end"), (0.0, "the measured end")
    s_lo, s_hi = (s_closed, s_open) if sign > 0 else (s_open, s_closed)
    source = f"oriented by {why}; closed end {s_closed:g}: {how_closed}; open end {s_open:g}: {how_open}"
    rate = (hi - lo) / (s_hi - s_lo)
    return Calibration(lo - s_lo * rate, rate, (s_lo, s_hi), source), ""


def label_figures(frames: np.ndarray, measured: np.ndarray, labels: np.ndarray, labelled: np.ndarray
                  ) -> dict[str, Any]:
    """Each labelled frame's label next to its measured state; the likely mistakes; the agreement."""
    idx = [i for i in np.flatnonzero(labelled) if np.isfinite(measured[i])]
    check = [[int(frames[i]), round(float(labels[i]), 3), round(float(measured[i]), 3)] for i in idx]
    diff = np.array([abs(m - lab) for _, lab, m in check]) if check else np.zeros(0)
    flagged = [row for row, e in zip(check, diff) if e > FLAG_TOL]
    return {"label_check": check, "flagged_labels": flagged,
            "state_rmse_from_pose": round(float(np.sqrt(np.mean(diff ** 2))), 4) if len(diff) else float("inf"),
            "label_median_error": round(float(np.median(diff)), 4) if len(diff) else float("inf")}


def fit_motion(pv: PartViews, states: np.ndarray, known: np.ndarray, labelled: np.ndarray | None = None,
               trust_labels: bool = False) -> tuple[Articulation, dict[str, Any]]:
    """A hinge or a slide from the part's per-frame poses; states, known (F,) of the registered frames (labels and
    what `known_states` filled in); `labelled` (F,) the frames a person labelled (default: known).

    Returns the motion and what it measured: kind evidence, per-frame measured states (`frame_states`), label
    check, flagged labels, `accepted` (the geometry's own evidence holds; with `trust_labels`, also the labels
    mostly agree) and its `reason`."""
    labelled = known if labelled is None else labelled
    hinge, slide = fit_hinge(pv), fit_slide(pv)
    fit, evidence = choose(hinge, slide, pv)
    extra: dict[str, Any] = {"registered": int(len(pv.frames)), **hinge.figures, **slide.figures, **evidence,
                             "kind_from": "geometry", **(turns_with_camera(pv, states, known) or {}),
                             **residual_share(fit, pv)}
    return articulate(fit, pv.frames, states, known, labelled, extra, trust_labels)


def residual_share(fit: Fit, pv: PartViews) -> dict[str, Any]:
    """How far the motion moves the part's middle (world units: a slide's span, a hinge's angle span times the
    middle's distance from the axis) and the median position residual as a share of it (the rigidity check)."""
    if not fit.ok.any():
        return {}
    lo, hi = ends(fit.d[fit.ok])
    if fit.kind == "hinge":
        p = fit.scale * pv.u[fit.ok] + pv.centre[fit.ok] - fit.point
        radius = float(np.median(np.linalg.norm(p - np.outer(p @ fit.axis, fit.axis), axis=1)))
        amplitude = radius * (hi - lo)
    else:
        amplitude = hi - lo
    resid = float(np.median(fit.pos_resid[fit.ok]))
    return {"moves_part_by": round(amplitude, 6), "residual_share": round(resid / max(amplitude, 1e-12), 4)}


def jumpy_frames(frames: np.ndarray, d: np.ndarray, ok: np.ndarray, span: float) -> np.ndarray:
    """(F,) bool: trusted frames whose displacement d leaves both the median of the (up to) two trusted frames
    before it and of the two after it (in frame order) by more than JUMP x `span` (the motion's range): a
    misregistered frame, not motion (a part moves smoothly; at a fast move a frame still agrees with one side)."""
    out = np.zeros(len(d), bool)
    idx = np.flatnonzero(ok)
    idx = idx[np.argsort(frames[idx], kind="stable")]
    for k, i in enumerate(idx):
        sides = [d[idx[max(0, k - 2):k]], d[idx[k + 1:k + 3]]]
        sides = [v for v in sides if len(v)]
        if sides and all(abs(d[i] - float(np.median(v))) > JUMP * span for v in sides):
            out[i] = True
    return out


def articulate(fit: Fit, frames: np.ndarray, states: np.ndarray, known: np.ndarray, labelled: np.ndarray,
               extra: dict[str, Any], trust_labels: bool = False) -> tuple[Articulation, dict[str, Any]]:
    """A fitted motion (whatever measured it) oriented by the labels (`calibrate`; `calibrate_by_labels` with
    `trust_labels`), with its figures: per-frame measured states, the label check, flagged labels, `accepted` and
    its `reason` (`fit_motion`'s docstring). Frames whose state jumps from both neighbours' are left out."""
    ok = fit.ok.copy()
    lo, hi = ends(fit.d[ok]) if ok.any() else (0.0, 0.0)
    jump = jumpy_frames(np.asarray(frames), fit.d, ok, hi - lo)
    ok &= ~jump
    extra.update(jumpy_frames=int(jump.sum()), trusted_frames=int(fit.ok.sum()), trust_labels=bool(trust_labels))
    if trust_labels:
        cal = calibrate_by_labels(fit.d, ok, states, known)
        why = "the labels do not orient the motion (label both ends)"
    else:
        cal, why = calibrate(fit.d, ok, states, known)
    axis, d, point = fit.axis.copy(), fit.d.copy(), fit.point.copy()
    if cal is None:
        extra.update(accepted=False, reason=why, scale=fit.scale, state_rmse_from_pose=float("inf"),
                     label_median_error=float("inf"), label_check=[], flagged_labels=[])
        return Articulation(fit.kind, axis, point, 0.0, extra), extra
    rate, d0 = cal.rate, cal.d0
    if rate < 0:  # the axis points the way the state grows
        axis, d, rate, d0 = -axis, -d, -rate, -d0
    measured = np.where(ok, (d - d0) / rate, np.nan)
    extra.update(label_figures(frames, measured, states, labelled))
    extra.update(scale=float(fit.scale), end_states=list(cal.end_states), ends_from=cal.source,
                 frame_states=[[int(f), round(float(m), 4)] for f, m in zip(frames, measured) if np.isfinite(m)],
                 pos_residual=round(float(np.median(fit.pos_resid[fit.ok])), 6))
    origin = point if fit.kind == "hinge" else point + d0 * axis  # a slide's origin: where it is at state 0
    extra.update(_acceptance(fit, extra, rate * abs(cal.end_states[1] - cal.end_states[0]), trust_labels))
    return Articulation(fit.kind, axis, origin, float(rate), extra), extra


def displacement_noise(fit: Fit, extra: dict[str, Any]) -> float:
    """A fit's per-frame noise in its displacement's units: a hinge's rotation noise (radians) where measured,
    else its position residual (a slide's distance from its line; the silhouette route's search step)."""
    if fit.kind == "hinge" and extra.get("rot_noise_deg") is not None:
        return float(np.radians(extra["rot_noise_deg"]))
    return float(np.median(fit.pos_resid[fit.ok])) if fit.ok.any() else 0.0


def _acceptance(fit: Fit, extra: dict[str, Any], span: float, trust_labels: bool = False) -> dict[str, Any]:
    """accepted / reason from the geometry's own evidence: refused when the reconstruction turned with the camera,
    the part barely moves (its measured span within MIN_MOVE x its noise), its positions miss the part's by more
    than MAX_RESIDUAL of how far it moves it, or its states jump between neighbouring frames in more than MAX_JUMPY
    of them; with `trust_labels`, also when most labels disagree."""
    if extra.get("follows_camera"):
        return {"accepted": False, "reason": f"its reconstruction turned with the camera where the labels say the "
                                             f"part rests ({extra['rest_turn_deg']} deg against the camera's "
                                             f"{extra['camera_turn_deg']} deg over {extra['rest_frames']} frames)"}
    noise = displacement_noise(fit, extra)
    if span < MIN_MOVE * max(noise, 1e-12):
        unit = "rad" if fit.kind == "hinge" else "world units"
        return {"accepted": False, "reason": f"the part is at one state in every frame: nothing to measure (its "
                                             f"measured {fit.kind} spans {span:.3g} {unit}, within {MIN_MOVE:g} x "
                                             f"its noise {noise:.3g})"}
    if extra.get("residual_share", 0.0) > MAX_RESIDUAL:
        return {"accepted": False, "reason": f"its positions miss the part's by {extra['residual_share']:.0%} of how "
                                             f"far it moves the part (at most {MAX_RESIDUAL:.0%}): a bent "
                                             f"reconstruction, not a rigid {fit.kind}"}
    trusted = max(extra.get("trusted_frames", 0), 1)
    if extra.get("jumpy_frames", 0) > MAX_JUMPY * trusted:
        return {"accepted": False, "reason": f"its states jump between neighbouring frames in {extra['jumpy_frames']}"
                                             f" of {trusted} frames (more than {MAX_JUMPY:.0%}): noise, not motion"}
    n = len(extra["label_check"])
    if trust_labels and (extra["label_median_error"] > LABEL_TOL or len(extra["flagged_labels"]) > MAX_FLAGGED * n):
        return {"accepted": False, "reason": f"{len(extra['flagged_labels'])} of {n} labels disagree with the "
                                             f"measured states by more than {FLAG_TOL} (--trust-labels)"}
    return {"accepted": True, "reason": ""}
