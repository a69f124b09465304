"""The prism route of `interreal motions`: a plain drawer's front at rest, pulled out along its normal, each
frame's pull read from its mask; a door, a part that never moves and a capture without keyframes get no slide."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from conftest import arc_camera, moved_front, silhouette, views_dataset
from edge_scenes import KEYS, K, H, N, W, off_deg, truth_states

from interreal.dataset import known_states
from interreal.motions.prism import judge, measure_prism

# a drawer front 0.5 wide and 0.2 tall, z up, facing -y, wholly in view from 1.3 away (above it: its top shows)
DRAWER = np.array([[-0.25, 0.0, 0.1], [0.25, 0.0, 0.1], [0.25, 0.0, -0.1], [-0.25, 0.0, -0.1]])
SLIDE = 0.3  # pulled out this far at state 1 (along -y)


def capture(kind: str, moves: bool = True, tilt_deg: float = 0.0):
    """A duck-typed dataset (as `edge_scenes.capture`): the drawer front pulled out `SLIDE` (the prism it
    sweeps), or the same front as a flap turned 80 deg about its left edge, seen from an arc of 50 deg above it.
    `tilt_deg`: the part and its motion turned about x, so a drawer comes out that much above level."""
    states = truth_states(N) if moves else np.zeros(N)
    c2ws = [arc_camera(-25 + 50 * i / (N - 1), 1.3, 0.4) for i in range(N)]
    tilt = Rotation.from_rotvec([np.radians(tilt_deg), 0.0, 0.0]).as_matrix()
    masks = [silhouette(moved_front(DRAWER, kind, s, SLIDE, 80.0) @ tilt.T, c, K, (W, H))[0]
             for s, c in zip(states, c2ws)]
    labelled = np.zeros(N, bool)
    labelled[[0, 6, 11, 22, 27, 31, 42, 49]] = True
    st, kn = known_states(np.arange(N, dtype=float), np.where(labelled, states, 0)[:, None], labelled[:, None])
    return views_dataset(c2ws, masks, K), states, st[:, 0], kn[:, 0], labelled


def test_a_plain_drawer_is_pulled_out_along_its_normal():
    ds, truth, st, kn, labelled = capture("slide")
    motion, fig = measure_prism(ds, 0, st, kn, labelled, KEYS, min_pixels=50)
    assert motion is not None and fig["accepted"], fig
    assert motion.kind == "slide" and fig["route"] == "prism"
    assert fig["prism_levelled"]  # held level (the cameras tell up): the free front here is 2.6 deg off, 4.5 % short
    assert off_deg(motion.axis, [0.0, -1.0, 0.0]) < 1.0, motion.axis
    assert motion.axis @ [0.0, -1.0, 0.0] > 0  # out of the cabinet as the state grows
    assert abs(motion.range - SLIDE) < 0.03 * SLIDE, motion.range
    rows = np.array(fig["frame_states"])
    assert len(rows) >= 40
    assert np.sqrt(np.mean((rows[:, 1] - truth[rows[:, 0].astype(int)]) ** 2)) < 0.06
    assert fig["prism_slide_iou"] >= fig["prism_hinge_iou"] + 0.05


def test_a_front_the_level_fits_clearly_worse_is_not_levelled():
    ds, truth, st, kn, labelled = capture("slide", tilt_deg=-25.0)  # comes out 25 deg below level
    motion, fig = measure_prism(ds, 0, st, kn, labelled, KEYS, min_pixels=50)
    assert fig["prism_level_iou"] < fig["prism_front_iou"] - 0.05 and "prism_levelled" not in fig, fig


def test_a_flap_is_not_made_a_drawer():
    ds, truth, st, kn, labelled = capture("hinge")
    motion, fig = measure_prism(ds, 0, st, kn, labelled, KEYS, min_pixels=50)
    assert motion is None or not fig["accepted"], fig


@pytest.mark.parametrize("kind", ["hinge", "slide"])
def test_a_part_that_never_moves_gets_no_slide(kind):
    ds, truth, st, kn, labelled = capture(kind, moves=False)
    motion, fig = measure_prism(ds, 0, st, kn, labelled, KEYS, min_pixels=50)
    assert motion is None or not fig["accepted"], fig


def test_no_keyframe_is_one_clear_reason():
    ds, truth, st, kn, labelled = capture("slide")
    motion, fig = measure_prism(ds, 0, st, kn, labelled, [], min_pixels=50)
    assert motion is None and "keyframe" in fig["prism_reason"]


def test_a_front_pulled_out_in_every_frame_is_not_at_rest():
    """A front that explains the masks only pulled out in every frame (never back at rest) was not found where the
    drawer closes: refused, with the least pull named; the same front with frames at rest passes this check."""
    shown = list(range(10))
    iou = np.full(10, 0.9)
    leaf = np.full(10, 0.5)
    fig: dict = {}
    reason = judge(fig, shown, np.linspace(0.06, 0.14, 10), iou, [0, 9], leaf)
    assert reason is not None and "every frame" in reason and "0.06" in reason
    assert judge({}, shown, np.linspace(0.0, 0.14, 10), iou, [0, 9], leaf) is None
