"""Is a propagated mask still its object? Per object and frame: lost, jumped, drifting, and a predicted J.

Why: the chains' own cues (flow trust, forward/backward agreement) stay high on a mask that has collapsed to
nothing or slid onto the background, so they cannot tell a good sequence from a failed one. Here every frame
is compared with what the keyframes say the object looks like, with cues that hold on any footage:
- area: min/max of the mask's area and the keyframes' (interpolated), or of the mask's area and the one its
  object's own motion predicts from the keyframe (chains with one keyframe), whichever agrees better; an IoU can
  be no higher than this ratio when the object's size is known;
- trust: forward-backward flow consistency on the mask (low where the object deforms or is occluded);
- thin: the keyframe mask's outline length over its area, times 1 % of the image width: the share of the
  object a boundary error of that size costs (a kite's lines lose J that a car's body does not);
- edges: mean image gradient along the mask's outline relative to the keyframe's (a mask that drifted off
  its object has its outline on flat colour);
- agree, two_sided: IoU of the forward and backward chains where both exist.
A linear model maps them to a predicted J per frame, so a sequence's predicted J is the mean of its frames';
the weights were fit (ridge, each cue held to its sign) on the ten DAVIS-2016 sequences in ../shared/data, both
protocols, three settings of the stage, sequence by sequence: `recipes/bench_masks.py` refits them
leave-one-sequence-out and reports how well the warning predicts a mean J under 0.7 on sequences it did not see. Also recorded, for the states and the report:
appearance (the mask's colours under the nearest keyframe's colour model, relative to the keyframe), reach
(view motion from the nearest keyframe, image widths) and jump (change of area or centroid since the previous
frame, in units of a doubling or of half the object's size).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .appearance import AppearanceConfig, ColourModel, quantize
from .soft import disk

MODEL = ("area", "trust", "thin", "edges", "agree", "two_sided")  # the predicted J's inputs, in order
FEATURES = MODEL + ("appearance", "reach", "jump")
# linear weights on MODEL (+ bias last), fit (`fit`: small ridge, signs held) on the shared DAVIS sequences, both
# protocols, three settings of the stage (60 runs: several settings, so the warning holds for each, not only the
# default's masks); `python recipes/bench_masks.py --variants ours,ours-fast,baseline --fit` prints them
WEIGHTS = np.array([0.539, 0.104, -0.107, 0.167, 0.195, -0.035, 0.055])
RIDGE = 0.01
# the sign each MODEL cue's weight may take (`fit`): 1 = higher is better, -1 = higher is worse, 0 = either
SIGNS = np.array([1, 1, -1, 1, 1, 0])
EDGES_CAP = 1.2      # an outline sharper than the keyframe's is no better evidence than an equal one
# a sequence (object) whose predicted mean J over propagated frames is under this is warned about
WARN_J = 0.7
# an object whose keyframe masks have this share or more in parts too fine to propagate (`fine_share`) is warned
# about: with the rest perfect its J is at most 0.9, the level the benchmark counts a sequence as done at
FINE_WARN = 0.1
LOST_AREA = 0.1      # a mask under this share of the keyframes' area (or empty) where the object should be: lost
LOST_APPEARANCE = 0.4  # ... or whose colours fit the object's model under 0.4 x as well as on the keyframe: lost
JUMP_AREA = np.log(2.0)  # area doubling or halving in one frame ...
JUMP_SHIFT = 0.5     # ... or the centroid moving half the object's size in one frame: jumped
DRIFT_J = 0.5        # a frame predicted under this (neither lost nor jumped) is drifting
APPEARANCE = AppearanceConfig(weight=1.0)
STATES = ("ok", "drifting", "jumped", "lost")


@dataclass
class KeyRef:
    """What a keyframe says about each object: its area share, colour model and own appearance / edge scores."""

    area: np.ndarray            # (K,) share of the image
    model: ColourModel
    appearance: np.ndarray      # (K,) mean P(object | colour) on the keyframe's own mask
    edges: np.ndarray           # (K,) outline gradient on the keyframe's own mask
    thin: np.ndarray            # (K,) outline length / area x 1 % of the width (see the module's docstring)
    centroid: np.ndarray        # (K, 2) in image widths (NaN where absent)


def gradient(image: np.ndarray) -> np.ndarray:
    """Image gradient magnitude normalised by its mean: outline scores compare across frames and footage."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32)
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3)
    g = cv2.magnitude(gx, gy)
    return g / max(float(g.mean()), 1e-3)


def outline_score(mask: np.ndarray, grad: np.ndarray) -> float:
    """Mean normalised gradient on the mask's outline (0 for an empty mask)."""
    m = mask.astype(np.uint8)
    if not m.any():
        return 0.0
    edge = m - cv2.erode(m, np.ones((3, 3), np.uint8))
    return float(grad[edge > 0].mean()) if edge.any() else 0.0


def key_reference(image: np.ndarray, labels: np.ndarray, n_obj: int) -> KeyRef:
    """Reference scores from a keyframe's work-size image and index map (255 = unknown)."""
    known = (labels != 255).astype(np.float32)
    soft = np.zeros(labels.shape + (n_obj + 1,), np.float32)
    for k in range(n_obj):
        soft[..., k] = labels == k + 1
    soft[..., n_obj] = (labels == 0) | (labels == 255)
    model = ColourModel.fit(image, soft, known, APPEARANCE)
    bins = quantize(image, APPEARANCE.bins)
    grad = gradient(image)
    area = np.array([(labels == k + 1).mean() for k in range(n_obj)])
    app = np.array([_appearance(model, bins, labels == k + 1, k) for k in range(n_obj)])
    edges = np.array([outline_score(labels == k + 1, grad) for k in range(n_obj)])
    thin = np.array([thinness(labels == k + 1) for k in range(n_obj)])
    return KeyRef(area, model, app, edges, thin, centroids(labels, n_obj))


def thinness(mask: np.ndarray) -> float:
    """Outline pixels / mask pixels x 1 % of the width: the share of the object a 1 %-of-width error costs."""
    m = mask.astype(np.uint8)
    n = int(m.sum())
    if n == 0:
        return 0.0
    edge = m - cv2.erode(m, np.ones((3, 3), np.uint8))
    return float(edge.sum()) / n * 0.01 * mask.shape[1]


def fine_radius(full_width: int, work_width: int) -> int:
    """Radius (full-size px) of the opening that removes the parts of a mask propagation cannot carry: about two
    work-size pixels wide (full-size px per work px, rounded; 1 when the work size is the full size)."""
    return max(1, round(full_width / max(work_width, 1)))


def fine_share(mask: np.ndarray, radius: int) -> float:
    """Share of a mask's pixels in parts narrower than 2 radius + 1 px: what an opening by a disk of `radius`
    takes away (lines, cables, thin rods).

    Why: flow cannot follow such a part (a few pixels of it against a textured background move with the
    background) and the work grid and its guided filter blur it below one half, so the masks between keyframes
    leave it out. DAVIS, keyframe every 10 frames, radius 2 at 854 px: 2 % (paragliding-launch's lines) and 5 %
    (kite-surf's) of those pixels kept against 94 % and 89 % of the rest (26-44 % on three sequences where they
    are 1-2 % of the object). J between keyframes is then at most one minus this share.
    """
    m = mask.astype(np.uint8)
    n = int(m.sum())
    if n == 0:
        return 0.0
    opened = cv2.morphologyEx(m, cv2.MORPH_OPEN, disk(radius))
    return float(n - int(opened.sum())) / n


def touches_border(labels: np.ndarray, n_obj: int, margin: int = 2) -> np.ndarray:
    """(n_obj,) bool: object k's mask reaches within `margin` px of the image border (it may be leaving the view)."""
    ring = np.ones(labels.shape, bool)
    ring[margin:-margin, margin:-margin] = False
    present = np.unique(labels[ring])
    return np.isin(np.arange(1, n_obj + 1), present)


def centroids(labels: np.ndarray, n_obj: int) -> np.ndarray:
    """(K, 2) centroid of each object in image widths (NaN where absent)."""
    out = np.full((n_obj, 2), np.nan)
    for k in range(n_obj):
        ys, xs = np.nonzero(labels == k + 1)
        if len(xs):
            out[k] = xs.mean() / labels.shape[1], ys.mean() / labels.shape[1]
    return out


def _appearance(model: ColourModel, bins: np.ndarray, mask: np.ndarray, k: int) -> float:
    if not mask.any():
        return 0.0
    return float(model.table[bins[mask], k].mean())


def frame_cues(labels: np.ndarray, image: np.ndarray, near: KeyRef, around: list[KeyRef]) -> tuple[np.ndarray, np.ndarray]:
    """Per object: (K, 3) area share, appearance and outline scores, and the (K, 2) centroid in image widths (NaN
    when empty). labels: work-size index map of the frame.

    The outline is compared with the nearest keyframe `near`; the appearance with the best fitting of the
    keyframes `around` the frame: a part seen face-on at one keyframe and edge-on at the next fits one of them.
    """
    k_n = len(near.area)
    bins = quantize(image, APPEARANCE.bins)
    grad = gradient(image)
    out = np.zeros((k_n, 3))
    for k in range(k_n):
        m = labels == k + 1
        out[k, 0] = m.mean()
        if m.any():
            out[k, 1] = max(_appearance(r.model, bins, m, k) / max(r.appearance[k], 1e-3) for r in around)
            out[k, 2] = outline_score(m, grad) / max(near.edges[k], 1e-3)
    return out, centroids(labels, k_n)


@dataclass
class Health:
    """The verdict on one sequence: per frame and object, a state and a predicted J."""

    predicted: np.ndarray                 # (n, K) predicted J (keyframes 1)
    state: np.ndarray                     # (n, K) index into STATES
    features: np.ndarray                  # (n, K, len(FEATURES))
    stretches: dict[str, list[list[tuple[int, int]]]] = field(default_factory=dict)  # state -> per object ranges

    def mean_predicted(self, keyframe: np.ndarray) -> np.ndarray:
        free = ~keyframe
        if not free.any():
            return np.ones(self.predicted.shape[1])
        return self.predicted[free].mean(0)


def reach_per_frame(motion: np.ndarray, keys: list[int], n: int) -> np.ndarray:
    """(n,) view motion (image widths) from each frame to its nearest keyframe along the sequence."""
    cum = np.concatenate([[0.0], np.cumsum(motion)]) if n > 1 else np.zeros(1)
    kc = cum[np.array(sorted(keys))]
    return np.abs(cum[:, None] - kc[None, :]).min(1)


def area_ratio(area: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """min / max of two areas (1 where both are empty)."""
    hi, lo = np.maximum(area, ref), np.minimum(area, ref)
    return np.where(hi > 0, lo / np.maximum(hi, 1e-12), 1.0)


def build_features(area: np.ndarray, ref_area: np.ndarray, app: np.ndarray, edges: np.ndarray, trust: np.ndarray,
                   agree: np.ndarray, centroid: np.ndarray, reach: np.ndarray, thin: np.ndarray,
                   moved_area: np.ndarray | None = None) -> np.ndarray:
    """Per frame and object (n, K, len(FEATURES)) from the stage's per-frame cues.

    area, ref_area, app, edges, trust, thin: (n, K); agree: (n, K), NaN on one-sided frames; centroid (n, K, 2)
    in image widths; reach (n,); moved_area (n, K): the area the object's own motion predicts from its keyframe,
    NaN where no chain measured it. The area cue is the better of the two agreements: an object that comes closer
    has a right mask far larger than its keyframe's (scooter-black: 0.33 of it on average, J 0.79) but close to
    what its motion says; a deforming object's motion says little (its homographies drift), its keyframe more.
    """
    n, k = area.shape
    area_score = area_ratio(area, ref_area)
    if moved_area is not None:
        known = np.isfinite(moved_area)
        area_score = np.where(known, np.maximum(area_score, area_ratio(area, np.nan_to_num(moved_area))), area_score)
    two = np.isfinite(agree)
    size = np.sqrt(np.maximum(area, 1e-6))  # object size in image widths-ish (share of the image, square-rooted)
    jump = np.zeros((n, k))
    if n > 1:
        a0, a1 = area[:-1], area[1:]
        dlog = np.abs(np.log((a1 + 1e-6) / (a0 + 1e-6)))
        shift = np.linalg.norm(centroid[1:] - centroid[:-1], axis=-1) / np.maximum(np.maximum(size[1:], size[:-1]), 1e-3)
        shift = np.nan_to_num(shift, nan=0.0)
        step = np.maximum(dlog / JUMP_AREA, shift / JUMP_SHIFT) * ((a0 > 0) & (a1 > 0))  # empty: lost, not jumped
        jump[1:] = step  # the frame a sudden change leads into
    cues = {"area": area_score, "trust": trust, "thin": thin, "edges": np.clip(edges, 0, EDGES_CAP),
            "agree": np.where(two, agree, 0.0), "two_sided": two.astype(float), "appearance": np.clip(app, 0, 1.5),
            "reach": np.repeat(np.clip(reach, 0, 1)[:, None], k, 1), "jump": np.clip(jump, 0, 3)}
    return np.stack([cues[f] for f in FEATURES], -1)


def predict(features: np.ndarray, weights: np.ndarray = WEIGHTS) -> np.ndarray:
    """Predicted J in [0, 1] from (..., len(FEATURES)) features (linear in the MODEL columns)."""
    return np.clip(features[..., :len(MODEL)] @ weights[:-1] + weights[-1], 0.0, 1.0)


def fit(means: np.ndarray, j: np.ndarray, ridge: float = RIDGE) -> np.ndarray:
    """Weights (len(MODEL) + 1,): ridge regression of sequences' mean J on their mean features (R, len(FEATURES)),
    each weight held to its cue's sign (`SIGNS`; a cue fit against its sign is left out and the rest refit).

    One row per sequence (and protocol), not per frame: the warning is about sequences, and a long sequence
    must not outweigh the others. The signs: over a few dozen rows the cues are collinear (trust and agreement
    both fall where an object deforms), and an unconstrained fit on the default setting's 20 runs gave flow trust a
    negative weight, a rule ("the less the flow agrees with itself, the better the mask") that fits one benchmark
    and no new footage.
    """
    x = np.concatenate([means[:, :len(MODEL)], np.ones((len(means), 1))], 1)
    used = np.ones(x.shape[1], bool)
    while True:
        xs = x[:, used]
        reg = ridge * np.eye(xs.shape[1])
        reg[-1, -1] = 0.0  # the bias is not shrunk
        w = np.zeros(x.shape[1])
        w[used] = np.linalg.lstsq(xs.T @ xs + reg, xs.T @ j, rcond=None)[0]  # lstsq: a constant cue is no error
        wrong = used[:-1] & (np.sign(w[:-1]) * SIGNS < 0)
        if not wrong.any():
            return w
        # the cue furthest on the wrong side goes first; the others may come right without it
        used[int(np.argmin(np.where(wrong, w[:-1] * SIGNS, np.inf)))] = False


def assess(features: np.ndarray, area: np.ndarray, ref_area: np.ndarray, expected: np.ndarray,
           keyframe: np.ndarray, weights: np.ndarray = WEIGHTS) -> Health:
    """States and predicted J per frame and object.

    expected (n, K): the keyframes around the frame all show the object (so an empty mask there is a loss,
    not the object leaving the view as annotated); keyframe (n,): the frame was given.
    """
    pred = predict(features, weights)
    empty = area <= 0
    app = features[..., FEATURES.index("appearance")]
    lost = expected & (empty | (area < LOST_AREA * ref_area) | (app < LOST_APPEARANCE))
    pred = np.where(lost, np.minimum(pred, np.minimum(area / np.maximum(ref_area, 1e-12), app)), pred)
    pred = np.where(empty & ~expected, 1.0, pred)  # absent as annotated: nothing to get wrong
    jumped = features[..., FEATURES.index("jump")] >= 1.0
    drifting = pred < DRIFT_J
    state = np.zeros(area.shape, np.int8)
    state[drifting] = STATES.index("drifting")
    state[jumped & ~empty] = STATES.index("jumped")
    state[lost] = STATES.index("lost")
    state[keyframe] = 0
    pred[keyframe] = 1.0
    stretches = {s: [ranges(np.nonzero(state[:, k] == i)[0]) for k in range(area.shape[1])]
                 for i, s in enumerate(STATES) if s != "ok"}
    return Health(pred, state, features, stretches)


def ranges(idx: np.ndarray) -> list[tuple[int, int]]:
    """Sorted positions -> [(first, last)] runs of consecutive positions."""
    out: list[tuple[int, int]] = []
    for i in idx.tolist():
        if out and i == out[-1][1] + 1:
            out[-1] = (out[-1][0], i)
        else:
            out.append((i, i))
    return out
