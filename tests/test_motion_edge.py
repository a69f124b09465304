"""The edge route of `interreal motions`: a plain door cut by the image border, hinged on the one edge of its outline
that stays put; a drawer or a part that never moves gets no hinge from it."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import arc_camera, moved_front, silhouette, views_dataset

from interreal.conventions import fid_of_index
from interreal.dataset import known_states
from interreal.motions.edge import (MAX_LINE_PX, SEARCH_SIDE, anchored_path, hinge_lines, key_cost, measure_edge,
                                    segments, smooth_path, triangulate)
from interreal.motions.colour import SWEEP, ColourSilhouettes
from interreal.motions.leaf import Leaf, Line, iou_curves, refine_leaf
from interreal.motions.silhouette import Silhouettes, front_corners, views_of
from interreal.transients import clear_transients, write_transient

W, H = 480, 360
K = np.array([[420.0, 0, W / 2], [0, 420.0, H / 2], [0, 0, 1]])
# a door 0.5 wide and 2.0 tall seen from 1.3 away: its top and bottom are always outside the image
TALL = np.array([[-0.25, 0.0, 1.0], [0.25, 0.0, 1.0], [0.25, 0.0, -1.0], [-0.25, 0.0, -1.0]])  # z up, facing -y
N = 50
KEYS = [0, 27, 49]


def truth_states(n: int) -> np.ndarray:
    """Rests closed, opens, rests open, half closes, rests."""
    s = np.zeros(n)
    s[12:22] = np.linspace(0, 1, 10)
    s[22:32] = 1.0
    s[32:42] = np.linspace(1, 0.4, 10)
    s[42:] = 0.4
    return s


def capture(kind: str, n: int = N, moves: bool = True, root: Path = Path("no-such-dataset"), arm: bool = False,
            thick: float = 0.0, arc_from: float = -25.0):
    """A duck-typed dataset: cameras on a 50 deg arc 1.3 units away looking at the part's middle, and its masks:
    the tall door turned up to 80 deg about its left edge, or a drawer front (the prism it sweeps, 0.2 units).
    `arm`: while the part moves, an arm reaches up from the image's bottom to its far edge, cut from its masks and
    written to the transient layer under `root`, as the masks stage does. `thick`: the door a slab this thick behind
    its front (hinged on the front's edge, as a fridge door is); `arc_from`: where the 50 deg arc starts (deg)."""
    part = np.concatenate([TALL, TALL + [0.0, thick, 0.0]]) if thick else TALL
    states = truth_states(n) if moves else np.zeros(n)
    c2ws, masks = [], []
    for i, s in enumerate(states):
        c2ws.append(arc_camera(arc_from + 50 * i / (n - 1), 1.3, 0.15))
        m, uv = silhouette(moved_front(part, kind, s, 0.2, 80.0), c2ws[-1], K, (W, H))
        if arm and 8 <= i < 46:
            grip = 0.5 * (uv[1] + uv[2])  # the middle of the far edge
            band = np.zeros((H, W), np.uint8)
            cv2.fillConvexPoly(band, np.round([[grip[0] - 30, grip[1]], [grip[0] + 30, grip[1]], [grip[0] + 60, H],
                                               [grip[0] - 10, H]]).astype(np.int32), 1)
            m[band > 0] = 0
            write_transient(root, fid_of_index(i), band > 0)
        masks.append(m)
    ds = views_dataset(c2ws, masks, K, root=root)
    masks = [m[..., None] > 0 for m in masks]
    labelled = np.zeros(n, bool)
    labelled[[0, 6, 11, 22, 27, 31, 42, 49]] = True
    st, kn = known_states(np.arange(n, dtype=float), np.where(labelled, states, 0)[:, None], labelled[:, None])
    return ds, states, st[:, 0], kn[:, 0], labelled, masks


def off_deg(axis: np.ndarray, truth: list[float]) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(axis @ truth)))))


def test_a_tall_plain_door_cut_by_the_border_is_hinged_on_its_static_edge():
    ds, truth, st, kn, labelled, masks = capture("hinge")
    assert all(front_corners(m[..., 0]) is None for m in masks)  # no view shows its corners: the corners route can't
    motion, fig = measure_edge(ds, 0, st, kn, labelled, KEYS, min_pixels=50)
    assert motion is not None and fig["accepted"], fig
    assert motion.kind == "hinge"
    assert off_deg(motion.axis, [0.0, 0.0, 1.0]) < 2.0, motion.axis
    off = motion.origin - TALL[0]
    assert np.linalg.norm(off - (off @ motion.axis) * motion.axis) < 0.02  # on the left edge
    assert abs(np.degrees(motion.range) - 80) < 4, np.degrees(motion.range)
    rows = np.array(fig["frame_states"])
    assert len(rows) >= 40
    assert np.sqrt(np.mean((rows[:, 1] - truth[rows[:, 0].astype(int)]) ** 2)) < 0.06
    assert fig["edge_outline_px"] + 0.5 <= fig["edge_slide_outline_px"]
    assert fig["edge_hinge_iou"] >= fig["edge_slide_iou"] + 0.05


def test_the_leaf_refined_with_its_line_finds_a_thick_doors_hinge_and_thickness():
    """A door 0.06 thick (12 % of its width) filmed from the side it turns to, and a hinge line 2-4 cm off (what
    triangulating two outlines gives where a plain door meets its plain body): refining the line with the slab's
    size and thickness on every frame's best angle brings both ends within 1.2 cm and finds a slab."""
    ds, *_ = capture("hinge", thick=0.06, arc_from=0.0)
    frames = list(range(N))
    sil = Silhouettes(views_of(ds, 0), frames, SEARCH_SIDE)
    off = Line(TALL[0] + [0.02, -0.03, 0.0], TALL[3] + [-0.01, -0.02, 0.0], 0.0, 0)
    size = np.array([0.25, 0.0, 1.0])  # the front's width and span in lengths of the line
    line, fitted, thickness, _ = refine_leaf(sil, off, size, frames, KEYS)
    for end, hinge, was in ((line.p, TALL[0], 0.036), (line.q, TALL[3], 0.022)):
        assert np.linalg.norm((end - hinge)[:2]) < 0.012 < was, (end, hinge)
    assert 0.05 < abs(thickness) < 0.2 and abs(fitted[0] - 0.25) < 0.02, (thickness, fitted)
    grid = np.linspace(-np.pi, np.pi, 144, endpoint=False)  # the keyframes' best overlap, before and after
    before = iou_curves(sil, Leaf(off), size, KEYS, grid).max(1).mean()
    after = iou_curves(sil, Leaf(line, thickness), fitted, KEYS, grid).max(1).mean()
    assert after > before + 0.04 and after > 0.95, (before, after)


def test_the_refinement_also_starts_behind_a_line_on_the_slabs_back_edge():
    """Where a cabinet's edge hides a thick door's hinge, the keyframes' outlines agree on a line a slab's thickness
    behind it (a simulated fridge door: 5.4 cm). Descending from the line as it came stops 5 cm short; the second
    descent, from the line moved a thickness across itself, ends within 1.5 cm of the hinge."""
    ds, *_ = capture("hinge", thick=0.06, arc_from=0.0)
    frames = list(range(N))
    sil = Silhouettes(views_of(ds, 0), frames, SEARCH_SIDE)
    back = Line(TALL[0] + [0.0, 0.06, 0.0], TALL[3] + [0.0, 0.06, 0.0], 0.0, 0)
    line, fitted, thickness, _ = refine_leaf(sil, back, np.array([0.25, 0.0, 1.0]), frames, KEYS)
    for end, hinge in ((line.p, TALL[0]), (line.q, TALL[3])):
        assert np.linalg.norm((end - hinge)[:2]) < 0.015, (end, hinge)
    assert 0.05 < abs(thickness) < 0.2, thickness


def test_an_arm_in_front_of_the_door_is_no_evidence_against_the_leaf(tmp_path: Path):
    ds, truth, st, kn, labelled, _ = capture("hinge", root=tmp_path, arm=True)
    motion, fig = measure_edge(ds, 0, st, kn, labelled, KEYS, min_pixels=50)
    assert motion is not None and fig["accepted"], fig
    assert off_deg(motion.axis, [0.0, 0.0, 1.0]) < 2.0 and abs(np.degrees(motion.range) - 80) < 4
    rows = np.array(fig["frame_states"])
    assert np.sqrt(np.mean((rows[:, 1] - truth[rows[:, 0].astype(int)]) ** 2)) < 0.06
    clear_transients(tmp_path)  # the same masks without the layer: the arm's outline taken for the door's
    motion, blind = measure_edge(ds, 0, st, kn, labelled, KEYS, min_pixels=50)
    assert motion is None and blind["edge_outline_px"] > fig["edge_outline_px"] + 1.0, (blind, fig)


def test_a_drawer_gets_no_hinge_from_its_static_edges():
    ds, truth, st, kn, labelled, _ = capture("slide")
    motion, fig = measure_edge(ds, 0, st, kn, labelled, KEYS, min_pixels=50)
    assert motion is None or not fig["accepted"] or motion.kind != "hinge", fig


@pytest.mark.parametrize("kind", ["hinge", "slide"])
def test_a_part_that_never_moves_gets_no_motion(kind):
    ds, truth, st, kn, labelled, _ = capture(kind, moves=False)
    motion, fig = measure_edge(ds, 0, st, kn, labelled, KEYS, min_pixels=50)
    assert motion is None or not fig["accepted"], fig


def test_no_keyframe_is_one_clear_reason():
    ds, truth, st, kn, labelled, _ = capture("hinge")
    motion, fig = measure_edge(ds, 0, st, kn, labelled, [], min_pixels=50)
    assert motion is None and "keyframe" in fig["edge_reason"]


def test_segments_leave_out_the_image_border():
    m = np.zeros((100, 200), bool)
    m[:, :80] = True  # a part cut by the left, top and bottom borders: one edge of its own
    segs = segments(m, 20)
    assert len(segs) == 1 and np.allclose(segs[0][:, 0], 79, atol=1.5)


def test_smooth_path_follows_its_neighbours_through_a_frame_without_evidence():
    angles = np.radians(np.arange(-180, 180, 5.0))
    want = np.radians([0, 10, 20, 30, 40])
    curves = np.array([np.exp(-((angles - a) / 0.1) ** 2) for a in want])
    curves[2] = np.exp(-((angles - np.radians(-120)) / 0.1) ** 2) * 0.3  # a bad mask points elsewhere, weakly
    path = smooth_path(curves, angles)
    got = np.degrees(angles[path])
    assert abs(got[2] - 20) <= 10 and np.allclose(got[[0, 1, 3, 4]], [0, 10, 30, 40])


def test_frames_labelled_at_one_end_share_one_angle_where_the_mirror_turns_with_the_camera():
    angles = np.radians(np.arange(-180, 180, 2.5))
    n = 30
    mirror = np.radians(40.0 + 2.0 * np.arange(n))  # the leaf's mirror image turns as the camera moves ...

    def peak(a: np.ndarray) -> np.ndarray:
        return np.exp(-((angles[None, :] - a[:, None]) / 0.05) ** 2)

    curves = 0.9 * peak(np.zeros(n)) + 1.0 * peak(mirror)  # ... and overlaps the masks a little better
    closed = np.zeros(n, bool)
    closed[[0, 15, 29]] = True  # a door labelled closed at the start, in the middle and at the end
    free = np.degrees(angles[smooth_path(curves, angles)])
    held = np.degrees(angles[anchored_path(curves, angles, np.zeros(n, bool), [closed])])
    assert np.ptp(free[closed]) > 50  # alone, the path follows the mirror away
    assert np.allclose(held[closed], 0.0)  # the frames labelled closed stay at one angle: the leaf's


def test_a_range_no_door_can_turn_is_not_used(monkeypatch):
    from interreal.dataset import Articulation
    from interreal.motions import edge

    def scaled_past(fit, frames, states, known, labelled, fig, trust_labels=False):  # labels that scale 80 deg to 200
        return Articulation("hinge", fit.axis, fit.point, np.radians(200.0), {}), dict(fig, accepted=True, reason="")

    monkeypatch.setattr(edge, "articulate", scaled_past)
    ds, truth, st, kn, labelled, _ = capture("hinge")
    motion, fig = measure_edge(ds, 0, st, kn, labelled, KEYS, min_pixels=50)
    assert not fig["accepted"] and "more than a door" in fig["reason"], fig


def test_frames_the_masks_stage_does_not_trust_are_left_out():
    ds, truth, st, kn, labelled, masks = capture("hinge")
    conf = np.ones(N)
    for i in range(13, 21):  # propagation left the mask where the door rested while it opened
        masks[i] = masks[12]
        conf[i] = 0.1
    ds.load_mask = lambda f: masks[f.index]
    motion, fig = measure_edge(ds, 0, st, kn, labelled, KEYS, min_pixels=50, confidence=conf)
    assert motion is not None and fig["accepted"], fig
    assert off_deg(motion.axis, [0.0, 0.0, 1.0]) < 2.0 and abs(np.degrees(motion.range) - 80) < 4
    assert not {f for f, _ in fig["frame_states"]} & set(range(13, 21))  # no state read from a mask it distrusts


def test_two_keyframes_outline_stretches_triangulate_to_the_hinge():
    ds, *_ = capture("hinge")
    views = views_of(ds, 0)
    keys = [0, 49]
    lines, out = hinge_lines(views, list(range(N)), keys)
    stretches = [segments(views.masks[k], 50) for k in keys]
    left = [min(s, key=lambda seg: seg[:, 0].mean()) for s in stretches]  # the hinge side, seen from both ends
    line = triangulate(views, out, keys[0], left[0], keys[1], left[1])
    assert line is not None and off_deg(line.axis, [0.0, 0.0, 1.0]) < 1.0
    assert np.linalg.norm((line.p - TALL[0])[:2]) < 0.01


def test_the_hinge_comes_from_the_keyframes_where_propagated_outlines_stray():
    """Between keyframes a plain door's propagated outline strays along its hinge side (where it meets a plain
    body): each frame's mask there grown or cut by up to 25 px. The keyframes (a person's masks) still give the
    hinge, and the leaf turning on it is measured."""
    ds, truth, st, kn, labelled, masks = capture("hinge")
    rng = np.random.default_rng(0)
    for i in set(range(N)) - set(KEYS):
        k, m = int(rng.integers(-25, 26)), masks[i]
        masks[i] = (m | np.roll(m, -k, axis=1)) if k > 0 else (m & np.roll(m, -k, axis=1))
    ds.load_mask = lambda f: masks[f.index]
    lines, _ = hinge_lines(views_of(ds, 0), list(range(N)), KEYS)
    assert off_deg(lines[0].axis, [0.0, 0.0, 1.0]) < 1.0 and np.linalg.norm((lines[0].p - TALL[0])[:2]) < 0.01
    motion, fig = measure_edge(ds, 0, st, kn, labelled, KEYS, min_pixels=50)
    assert motion is not None and fig["accepted"], fig
    assert off_deg(motion.axis, [0.0, 0.0, 1.0]) < 2.0 and abs(np.degrees(motion.range) - 80) < 12


def test_a_line_is_costed_on_its_own_keyframes_and_the_best_of_the_others():
    on_keys = np.array([0.0, 12.0, 0.5, np.nan, 12.0, 0.0, 1.0])
    assert key_cost(on_keys, [0, 5]) == pytest.approx((0.0 + 0.0 + 0.5 + 1.0 + 12.0) / 5)  # best 3 of 4 seen
    assert key_cost(np.array([0.0, 0.0, 6.0]), [0, 1]) == pytest.approx(2.0)  # three keyframes: all of them


def test_more_keyframes_with_the_hinge_edge_hidden_in_some_still_give_the_hinge():
    """A user who adds keyframes as the masks stage asks gets some where an arm (left out of the mask, not painted)
    or the door's own thickness hides the hinge's edge: two of seven keyframes' masks lose 40 px on the hinge side.
    The hinge is still the line, and the door is measured."""
    ds, truth, st, kn, labelled, masks = capture("hinge")
    keys = [0, 8, 16, 24, 32, 40, 49]
    for k in (8, 16):  # the hinge on their outline's left
        m = masks[k][..., 0]
        left = int(np.flatnonzero(m.any(0)).min())
        m[:, : left + 40] = False
    ds.load_mask = lambda f: masks[f.index]
    lines, _ = hinge_lines(views_of(ds, 0), list(range(N)), keys)
    assert lines[0].cost <= MAX_LINE_PX, [ln.cost for ln in lines[:3]]
    assert off_deg(lines[0].axis, [0.0, 0.0, 1.0]) < 1.0 and np.linalg.norm((lines[0].p - TALL[0])[:2]) < 0.01
    motion, fig = measure_edge(ds, 0, st, kn, labelled, keys, min_pixels=50)
    assert motion is not None and fig["accepted"], fig
    assert off_deg(motion.axis, [0.0, 0.0, 1.0]) < 2.0 and abs(np.degrees(motion.range) - 80) < 4


def painted(masks: list[np.ndarray], seed: int = 0) -> list[np.ndarray]:
    """RGB frames of the capture: a plain blue door (its masks) on a beige wall shaded left to right, both noisy."""
    rng = np.random.default_rng(seed)
    wall = np.dstack([np.broadcast_to(np.linspace(150, 210, W), (H, W)), np.full((H, W), 180.0), np.full((H, W), 150.0)])
    out = []
    for m in masks:
        img = np.where(m.reshape(H, W, 1) > 0, [40.0, 90.0, 200.0], wall) + rng.normal(0, 6, (H, W, 3))
        out.append(np.clip(img, 0, 255).astype(np.uint8))
    return out


def test_a_frame_without_a_mask_reads_the_doors_angle_by_its_colour():
    """The keyframes teach the door's colour; a frame whose mask is lost says which angle of the leaf its pixels
    agree with, closed or open."""
    ds, truth, st, kn, labelled, masks = capture("hinge")
    images = painted(masks)
    ds.load_image = lambda f: images[f.index]
    views = views_of(ds, 0)
    leaf = Leaf(Line(TALL[3].copy(), TALL[0].copy(), 0.0, 0))  # the true hinge: the left edge, bottom to top
    size = np.array([0.25, 0.0, 1.0])  # 0.5 wide on a 2.0 line
    colour = ColourSilhouettes(views, Silhouettes(views, KEYS), KEYS, [leaf.corners(*size, a) for a in SWEEP])
    angles = np.radians(np.arange(-180, 180, 2.5))
    curves = iou_curves(colour, leaf, size, [5, 25], angles)  # closed, fully open; neither a keyframe
    turned = np.degrees(angles[curves[1].argmax()] - angles[curves[0].argmax()])
    assert abs(abs((turned + 180) % 360 - 180) - 80.0) <= 5.0, turned
    assert curves.max(1).min() > 0.8, curves.max(1)


def test_frames_whose_mask_is_lost_steer_the_path_by_colour_but_measure_nothing():
    ds, truth, st, kn, labelled, masks = capture("hinge")
    images = painted(masks)
    lost = range(13, 27)  # the door lost while it opened and came to rest open
    for i in lost:
        masks[i] = np.zeros_like(masks[i])
    ds.load_mask = lambda f: masks[f.index]
    ds.load_image = lambda f: images[f.index]
    motion, fig = measure_edge(ds, 0, st, kn, labelled, KEYS, min_pixels=50)
    assert motion is not None and fig["accepted"], fig
    assert off_deg(motion.axis, [0.0, 0.0, 1.0]) < 2.0 and abs(np.degrees(motion.range) - 80) < 12
    assert fig["edge_read_by_colour"] == len(lost)
    assert not {f for f, _ in fig["frame_states"]} & set(lost)  # a state is only ever read from a mask
