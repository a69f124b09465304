"""What a masks run concludes about its own masks: the cues gathered per frame as the chains produce them (`Cues`),
health's verdict on them (`assess_run`), and the lost stretches that are not losses (an object hidden behind the
transient layer, or out of the view over the image border).

`health` holds the per-frame judgement (pure functions over arrays); this module applies it to one run's frames and
files, for `stage`.
"""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from ..conventions import mask_file
from ..transients import read_transient
from . import health as H
from .confidence import keyframe_reach, next_keyframes, reach_suggestion
from .redetect import Event, RedetectConfig, reach_from_sides
from .soft import argmax_labels
from .track import Propagator

# Farthest a propagated frame may lie from its nearest keyframe, in image widths of view motion. Measured (mean
# IoU of the worst object): 0.05-0.09 -> 0.89-0.94 (DAVIS every 10th frame, simulated captures at normal speed);
# 0.135 -> 0.84 (3x camera speed); 0.25-0.27 -> 0.74-0.80; DAVIS first frame only: 0.49 -> 0.91, 0.54 -> 0.81.
MAX_REACH = 0.10
REACH_SHARE = 0.99  # a mask's far edge from a side: the 99th percentile of its pixels (`Cues.reach`)


class Cues:
    """Per frame and object, what `health` judges a mask by, gathered as the frames come out of the chains."""

    def __init__(self, n: int, k: int):
        self.area = np.zeros((n, k))
        self.appearance = np.ones((n, k))
        self.edges = np.ones((n, k))
        self.trust = np.ones((n, k))
        self.agree = np.full((n, k), np.nan)
        self.centroid = np.full((n, k, 2), np.nan)
        self.thin = np.zeros((n, k))
        self.moved = np.full((n, k), np.nan)  # area share the object's own motion predicts (one-sided chains)
        self.border = np.zeros((n, k), bool)  # the mask reaches the image border (`health.touches_border`)
        # ... and which sides (left, top, right, bottom) it reaches within `border_band` (`redetect.border_sides`)
        self.sides = np.zeros((n, k, 4), bool)
        # ... and how far it reaches from each side, in long sides of the image (NaN where it reaches none or was
        # not measured): its far edge from the side, not where most of it lies (a door turning changes that)
        self.reach = np.full((n, k, 4), np.nan)

    def rows(self, frames: list[int]) -> dict[str, np.ndarray]:
        """Every cue's rows of these frames, by name (`reuse` stores them with the frames' labels)."""
        return {name: v[frames] for name, v in vars(self).items()}

    def put(self, pos: int, row: dict[str, np.ndarray]) -> None:
        """One frame's cues as `rows` gave them, in place of `add`."""
        for name, v in row.items():
            getattr(self, name)[pos] = v

    def add(self, res, work: np.ndarray | None, refs: Future) -> None:
        """One frame's cues; `work`: its work-size image (None for a keyframe); `refs`: `key_refs`. Runs on the
        writer thread."""
        key_refs: dict[int, H.KeyRef] = refs.result()
        pos = res.pos
        self.border[pos] = H.touches_border(res.labels, self.border.shape[1])
        band = border_band(res.labels.shape)
        lab = res.labels
        strips = [np.unique(x) for x in (lab[:, :band], lab[:band], lab[:, -band:], lab[-band:])]
        for k in range(self.sides.shape[1]):
            self.sides[pos, k] = [k + 1 in x for x in strips]  # as `redetect.border_sides`, from the strips alone
            if self.sides[pos, k].any():
                self.reach[pos, k] = reach_from_sides(lab == k + 1, REACH_SHARE) / max(lab.shape)
        if res.keyframe:
            self.area[pos], self.centroid[pos], self.thin[pos] = key_refs[pos].area, key_refs[pos].centroid, \
                key_refs[pos].thin
            return
        labels = argmax_labels(res.soft)
        near = min(key_refs, key=lambda k: abs(k - pos))
        around = [k for k in key_refs if k < pos][-1:] + [k for k in key_refs if k > pos][:1]  # keys are sorted
        cue, self.centroid[pos] = H.frame_cues(labels, work, key_refs[near], [key_refs[k] for k in around])
        self.area[pos], self.appearance[pos], self.edges[pos] = cue[:, 0], cue[:, 1], cue[:, 2]
        self.thin[pos] = key_refs[near].thin
        if res.scale is not None:  # a one-sided chain: its keyframe is the nearest
            self.moved[pos] = key_refs[near].area * res.scale
        for k in range(cue.shape[0]):
            m = labels == k + 1
            self.trust[pos, k] = float(res.trust[m].mean()) if m.any() else float(res.trust.mean())
            if res.fwd is not None and res.bwd is not None:
                f, b = res.fwd == k + 1, res.bwd == k + 1
                u = int((f | b).sum())
                self.agree[pos, k] = (f & b).sum() / u if u else 1.0


def key_refs(anchors: dict[int, np.ndarray], load, wsize: tuple[int, int], n_track: int) -> dict[int, H.KeyRef]:
    """Each keyframe's `health.KeyRef` at the work size, by position."""
    return {p: H.key_reference(cv2.resize(load(p), wsize, interpolation=cv2.INTER_AREA), work_labels(m, wsize),
                               n_track) for p, m in sorted(anchors.items())}


def fine_shares(anchors: dict[int, np.ndarray], n_obj: int, radius: int) -> tuple[np.ndarray, list[int | None]]:
    """(K,) share of each object's pixels over all its keyframes in parts too fine to propagate (`health.fine_share`),
    and the keyframe holding most of each object's such pixels (None where it has none)."""
    fine, total = np.zeros(n_obj), np.zeros(n_obj)
    most: list[tuple[float, int | None]] = [(0.0, None)] * n_obj
    for pos, labels in sorted(anchors.items()):
        for k in range(n_obj):
            m = labels == k + 1
            n = int(m.sum())
            if n:
                px = H.fine_share(m, radius) * n
                fine[k] += px
                total[k] += n
                if px > most[k][0]:
                    most[k] = (px, pos)
    return fine / np.maximum(total, 1), [pos for _, pos in most]


def occluded_by_transients(ds: Path, fids: list[str], hl: H.Health, n_obj: int,
                            share: float = 0.7) -> dict[int, list[tuple[int, int]]]:
    """Lost stretches where a person / hand stands in front of the object: on every frame of the stretch, the
    object's mask on a frame beside the stretch (before or after it: the side the person hid it from; a frame
    flagged only as jumped still shows the object) is, for at least `share` of its pixels, either still the object
    or covered by the transient layer; or the transient layer hides more of it than neither accounts for, and that
    rest is under `health.LOST_AREA` of the object's size beside the stretch (the larger of the two sides), the size
    under which a mask counts as lost: then even a perfect mask would be a sliver, and an empty one is explained by
    the occluder (a keyframe taken while the person already hid most of the object leaves only a sliver as the
    reference, a few of whose pixels the person uncovers again as it moves). They are occluded, not lost: taken out
    of the lost state (no warning, no suggested keyframe), their confidence that of the frame the object was seen
    on. Returns object -> the stretches so relabelled."""
    out: dict[int, list[tuple[int, int]]] = {}
    lost = H.STATES.index("lost")
    for k in range(n_obj):
        kept = []
        for a, b in hl.stretches["lost"][k]:
            seen = [i for i in (a - 1, b + 1) if 0 <= i < len(fids) and hl.state[i, k] != lost]
            stretch = stretch_masks(ds, fids, range(a, b + 1), k) if seen else []
            cover = {i: covered(np.load(mask_file(ds, fids[i]))[..., k], stretch) for i in seen}
            size = max((c.area for c in cover.values()), default=0)
            ok = [i for i, c in cover.items() if c.area and (c.share >= share or (
                c.hidden >= c.unexplained and c.unexplained <= H.LOST_AREA * size))]
            if ok:
                ref = max(ok, key=lambda i: cover[i].share)
                hl.state[a:b + 1, k] = 0
                hl.predicted[a:b + 1, k] = hl.predicted[ref, k]
                out.setdefault(k, []).append((a, b))
            else:
                kept.append((a, b))
        hl.stretches["lost"][k] = kept
    return out


def border_band(shape: tuple[int, ...]) -> int:
    """Px from the image border within which a mask counts as at a side of it (`Cues.sides`): the band the
    re-detection of an object that left the view looks for its return in (`redetect`), at this image's size."""
    return max(2, round(RedetectConfig.smooth * max(shape[:2])))


def left_view(hl: H.Health, cues: Cues, n_obj: int, is_key: np.ndarray, exits: list[Event], ref: np.ndarray
              ) -> tuple[dict[int, list[tuple[int, int]]], dict[int, list[int]]]:
    """Stretches where the object is out of the view, taken out of the lost state (no warning, no suggested
    keyframe) with confidence 1. Returns object -> the stretches, and object -> the frames of them whose masks the
    stage blanks: after an exit the chain measured, all; in a lost stretch, those whose mask is a remnant (under
    `health.LOST_AREA` of the area `ref` (n, K) the keyframes give), not one lost by its colours alone.

    A lost stretch is out of the view when its masks beside it (the frames that are not lost) reach the image
    border, each on its way out over a side (`heads_out`: into the stretch, or back from it), and inside it is empty
    or still at the border: the keyframes around show the object, but the camera turned away between them (or the
    part left the view itself). A mask at the border is not enough: a tall plain door is cut by it all along, and
    where its mask collapses while it stays in view a false 'out of the view' hides a failure (blanked masks
    trusted), where a false 'lost' asks for a keyframe. And where a chain no keyframe corrects saw the object
    leave over a side of the image (`exits`: most of what its mask lost went out there, `redetect`), the object is
    out of the view from the first frame its mask is lost or off that side until it reaches that side again (it
    comes back over the border it left by) or a keyframe: a mask in mid-view there is a look-alike the chain moved
    to (a door that swung out of the view given to the rim of the cabinet of its colour), not the object."""
    lost = H.STATES.index("lost")
    n = len(cues.area)
    keys = np.flatnonzero(is_key)
    out: dict[int, list[tuple[int, int]]] = {}
    blank: dict[int, list[int]] = {}
    for k in range(min(n_obj, cues.area.shape[1])):
        taken, wipe = [], set()
        for a, b in hl.stretches["lost"][k]:
            beside = [(i, d) for i, d in ((a - 1, -1), (b + 1, 1)) if 0 <= i < n and hl.state[i, k] != lost]
            if beside and all(cues.border[i, k] and heads_out(cues, hl.state[:, k] != lost, k, i, d)
                              for i, d in beside) and \
                    all(cues.area[i, k] <= 0 or cues.border[i, k] for i in range(a, b + 1)):
                taken.append((a, b))
                wipe |= {i for i in range(a, b + 1) if cues.area[i, k] < H.LOST_AREA * ref[i, k]}
        for e in exits:
            if e.obj == k and len(keys) and not keys[0] < e.pos < keys[-1]:
                after = _out_after(hl, cues, k, e, 1 if e.pos > keys[-1] else -1, is_key)
                taken.extend(after)
                wipe |= {i for a, b in after for i in range(a, b + 1)}
        if not taken:
            continue
        blank[k] = sorted(wipe)
        frames = np.unique(np.concatenate([np.arange(a, b + 1) for a, b in taken]))
        hl.state[frames, k] = 0
        hl.predicted[frames, k] = 1.0
        out[k] = H.ranges(frames)
        for st, runs in hl.stretches.items():  # frames out of the view are in no other state
            runs[k] = H.ranges(np.flatnonzero(hl.state[:, k] == H.STATES.index(st)))
    return out, blank


def heads_out(cues: Cues, held: np.ndarray, k: int, i: int, away: int) -> bool:
    """Whether object k's mask on frame i, beside a stretch where it is lost, is on its way out over a side it
    reaches: over the `RedetectConfig.window` frames from i in the direction `away` where it was held (`held`
    (n,): not lost), both its area and its reach from such a side shrank, the reach by more than the band a mask
    counts at a side within (`border_band`). A mask that leaves the view shrinks into the side it leaves by; a
    tall door that swings open while cut by the top and bottom border does not, and where its chain lost it the
    stretch is a loss to annotate. True with no such frame measured (a run reused from before the reach was kept)."""
    sides, now = cues.sides[i, k], cues.reach[i, k]
    if not sides.any():
        return False
    frames = [j for j in range(i + away, i + away * (RedetectConfig.window + 1), away)
              if 0 <= j < len(held) and held[j] and cues.area[j, k] > 0 and not np.isnan(cues.reach[j, k]).any()]
    if np.isnan(now).any() or not frames:
        return True
    before = np.nanmax(cues.reach[frames, k], axis=0)
    shrank = sides & (before - now > RedetectConfig.smooth)
    return bool(shrank.any() and cues.area[i, k] < max(cues.area[j, k] for j in frames))


def _out_after(hl: H.Health, cues: Cues, k: int, gone: Event, step: int,
               is_key: np.ndarray) -> list[tuple[int, int]]:
    """The frames (one stretch, or none) object k is out of the view after it left over `gone.sides`, walking
    from the exit in the chain's direction `step` (+1 forward after the last keyframe, -1 backward before the
    first): from the first frame its mask is lost or off those sides (none when it grows back first: it did not
    leave) until it is at one of them again, not lost, or a keyframe."""
    sides = np.array(gone.sides, bool)
    lost = H.STATES.index("lost")
    start, size = None, cues.area[gone.pos, k]
    i = gone.pos
    while 0 <= i < len(is_key) and not is_key[i]:
        back = cues.area[i, k] > 0 and hl.state[i, k] != lost and bool((cues.sides[i, k] & sides).any())
        if start is None and not back:
            start = i
        elif start is None and cues.area[i, k] > size:
            return []
        elif start is not None and back:
            break
        i += step
    if start is None:
        return []
    last = i - step
    return [(min(start, last), max(start, last))]


class Cover(NamedTuple):
    """What accounts for object k's mask on a reference frame over a stretch (`covered`), in pixels of that mask."""

    share: float       # least share, over the stretch, that the object's mask there or the transient layer covers
    area: int          # the reference mask's area
    hidden: int        # least, over the stretch, that the transient layer hides

    @property
    def unexplained(self) -> float:
        """Most, over the stretch, that neither the object's mask nor the transient layer covers."""
        return self.area * max(1.0 - self.share, 0.0)


def stretch_masks(ds: Path, fids: list[str], frames: range, k: int) -> list[tuple[int, np.ndarray | None]]:
    """Object k's mask area and the transient layer (None where there is none) on each frame of a stretch."""
    out = []
    for i in frames:
        mask = np.load(mask_file(ds, fids[i]))[..., k]
        out.append((int(mask.sum()), read_transient(ds, fids[i], mask.shape)))
    return out


def covered(obj: np.ndarray, stretch: list[tuple[int, np.ndarray | None]]) -> Cover:
    """How much of an object's mask `obj` on a reference frame its mask on each frame of the stretch (`stretch_masks`:
    its area there) or the transient layer there accounts for (the pixels still shown, plus those a person / hand now
    hides)."""
    area = int(obj.sum())
    if not area:
        return Cover(0.0, 0, 0)
    least, hidden_min = 1.0, area
    for shown, tr in stretch:
        hidden = int((tr & obj).sum()) if tr is not None else 0
        least = min(least, (shown + hidden) / area)
        hidden_min = min(hidden_min, hidden)
    return Cover(least, area, hidden_min)


def work_labels(index_map: np.ndarray, wsize: tuple[int, int]) -> np.ndarray:
    if (index_map.shape[1], index_map.shape[0]) == wsize:
        return index_map
    return cv2.resize(index_map, wsize, interpolation=cv2.INTER_NEAREST)


def expected_objects(ref: dict[int, np.ndarray], n: int) -> np.ndarray:
    """(n, K): every keyframe around the frame (the one before and the one after) shows the object."""
    keys = sorted(ref)
    out = np.zeros((n, len(ref[keys[0]])), bool)
    for i in range(n):
        around = [k for k in keys if k <= i][-1:] + [k for k in keys if k >= i][:1]
        out[i] = np.all([ref[k] > 0 for k in around], axis=0)
    return out


def ref_area(ref: dict[int, np.ndarray], pos: int) -> np.ndarray:
    """Area each object 'should' have at pos: linear between the surrounding keyframes."""
    keys = sorted(ref)
    before = [k for k in keys if k <= pos]
    after = [k for k in keys if k >= pos]
    if not before:
        return ref[after[0]]
    if not after:
        return ref[before[-1]]
    a, b = before[-1], after[0]
    if a == b:
        return ref[a]
    w = (pos - a) / (b - a)
    return (1 - w) * ref[a] + w * ref[b]


@dataclass
class RunHealth:
    """Health's verdict beyond `health.Health`: the cues, what each frame should show, where keyframes are, the view
    motion, the stretches relabelled occluded / out of view, and where to annotate next."""

    feats: np.ndarray
    ref_area: np.ndarray
    expected: np.ndarray
    is_key: np.ndarray
    motion: np.ndarray
    occluded: dict[int, list[tuple[int, int]]]
    left: dict[int, list[tuple[int, int]]]
    blank: dict[int, list[int]]  # per object, the frames out of the view whose masks the stage blanks
    reach: list[tuple[int, int, float]]
    far: list[tuple[int, int, float]]
    picks: list[int]
    mean_pred: np.ndarray


def assess_run(ds: Path, fids: list[str], anchors: dict[int, np.ndarray], n_obj: int, cues: Cues,
               ref: dict[int, np.ndarray], prop: Propagator, transients: bool,
               suggest: int) -> tuple[H.Health, RunHealth]:
    """Each frame's state and predicted J per object, the stretches that are occluded (`transients`: the run wrote a
    transient layer) or out of the view rather than lost, and the frames to annotate next."""
    n = len(fids)
    is_key = np.zeros(n, bool)
    is_key[list(anchors)] = True
    motion = np.array([prop.motion.get(t, 0.0) for t in range(n - 1)])
    keys = sorted(anchors)
    areas = np.stack([ref_area(ref, i) for i in range(n)])
    feats = H.build_features(cues.area, areas, cues.appearance, cues.edges, cues.trust, cues.agree,
                             cues.centroid, H.reach_per_frame(motion, keys, n), cues.thin, cues.moved)
    expected = expected_objects(ref, n)
    hl = H.assess(feats, cues.area, areas, expected, is_key)
    occluded = occluded_by_transients(ds, fids, hl, n_obj) if transients else {}
    left, blank = left_view(hl, cues, n_obj, is_key, prop.exits, areas)
    reach = keyframe_reach(motion, keys) if n > 1 else []
    far = sorted((x for x in reach if x[2] > MAX_REACH), key=lambda x: -x[2])
    # where a mask collapsed (and was found again, or a look-alike of it was refused) the stage could not hold the
    # object either: after the lost stretches, the first frames to annotate
    # (not where the object is out of the view: a collapse there is right)
    collapsed = [[(e.since, e.pos) for e in prop.redetections + prop.refusals
                  if e.obj == k and not any(a <= e.since <= b for a, b in left.get(k, []))] for k in range(n_obj)]
    picks = next_keyframes(hl.predicted[:, :n_obj], is_key, suggest,
                           [lost + col for lost, col in zip(hl.stretches["lost"][:n_obj], collapsed)],
                           [reach_suggestion(motion, a, b, keys) for a, b, _ in far[:3]])
    return hl, RunHealth(feats, areas, expected, is_key, motion, occluded, left, blank, reach, far, picks,
                         hl.mean_predicted(is_key))
