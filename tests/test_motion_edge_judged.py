"""The edge route's refusals and what it leaves out: a drawer, a part that never moves, no keyframe, a range no door
turns, and the frames whose masks the masks stage does not trust."""

from __future__ import annotations

import numpy as np
import pytest
from edge_scenes import KEYS, N, capture, off_deg

from interreal.motions.edge import measure_edge


def test_a_drawer_gets_no_hinge_from_its_static_edges():
    ds, truth, st, kn, labelled, _ = capture("slide")
    motion, fig = measure_edge(ds, 0, st, kn, labelled, KEYS, min_pixels=50)
    assert motion is None or not fig["accepted"] or motion.kind != "hinge", fig
    # refused by the slide rival: the frames where a drawn mask would decide are ones it moved in, no keyframe
    assert "a slide of its front explains" in fig["edge_reason"]
    assert 1 <= len(fig["edge_decide"]) <= 3 and not set(fig["edge_decide"]) & set(KEYS), fig["edge_decide"]
    assert all(truth[i] > 0.1 for i in fig["edge_decide"]), truth[fig["edge_decide"]]


def test_the_frames_that_decide_are_spread_over_those_it_moved_in_and_skip_the_keyframes():
    from interreal.motions.edge import ASK, deciding_frames

    moved = list(range(20, 50))
    picked = deciding_frames(moved, keys=[25, 35])
    assert len(picked) == ASK and not {25, 35} & set(picked) and picked == sorted(picked)
    assert picked[0] < 30 and picked[-1] > 40  # spread from its first turns to its last
    assert deciding_frames([3, 4], keys=[3, 4]) == [] and deciding_frames([7], keys=[]) == [7]


@pytest.mark.parametrize("kind", ["hinge", "slide"])
def test_a_part_that_never_moves_gets_no_motion(kind):
    ds, truth, st, kn, labelled, _ = capture(kind, moves=False)
    motion, fig = measure_edge(ds, 0, st, kn, labelled, KEYS, min_pixels=50)
    assert motion is None or not fig["accepted"], fig


def test_no_keyframe_is_one_clear_reason():
    ds, truth, st, kn, labelled, _ = capture("hinge")
    motion, fig = measure_edge(ds, 0, st, kn, labelled, [], min_pixels=50)
    assert motion is None and "keyframe" in fig["edge_reason"]


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


@pytest.mark.parametrize("drawn_keep", [True, False])
def test_a_leaf_kept_on_one_count_must_be_kept_on_the_keyframes_it_moved_in(monkeypatch, drawn_keep):
    """Where the leaf beats the slide of its front on one count only over the propagated frames it turned in, the
    keyframes among them (exact masks) judge again: kept there, the hinge is used with the frames that would confirm
    it named (`edge_confirm`); lost there (a drawer's leaf traced its propagated outlines better and lost its drawn
    ones), refused by name with the frames that decide (`edge_decide`)."""
    from interreal.motions import edge

    calls = []
    real = edge.rival_figures

    def rigged(sil, out, leaf, size, shown, phi, rest, frames):
        calls.append(list(frames))
        some = real(sil, out, leaf, size, shown, phi, rest, frames)[4]
        if len(calls) == 1:
            return 2.7, 2.6, 0.94, 0.78, some  # the propagated frames: overlap won, outline tied
        return (1.0, 3.0, 0.95, 0.80, some) if drawn_keep else (1.7, 3.7, 0.60, 0.90, some)

    monkeypatch.setattr(edge, "rival_figures", rigged)
    ds, truth, st, kn, labelled, _ = capture("hinge")
    motion, fig = measure_edge(ds, 0, st, kn, labelled, KEYS, min_pixels=50)
    assert len(calls) == 2 and set(calls[1]) <= set(KEYS) and calls[1], calls
    if drawn_keep:
        assert fig["accepted"] and motion.kind == "hinge", fig
        assert fig["edge_confirm"] and not set(fig["edge_confirm"]) & set(KEYS), fig
    else:
        assert motion is None and "the keyframes it moved in" in fig["edge_reason"], fig
        assert fig["edge_decide"] and "edge_confirm" not in fig, fig
