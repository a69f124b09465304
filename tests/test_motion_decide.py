"""Where a plain part's masks are explained as well by a drawer's slide as by a door's leaf: no motion is used, the
frames whose drawn masks decide are asked for (`edge.deciding_frames`, the report's `draw`), and the prism route's
slide does not win where the edge route's refined leaf explained the masks better."""

from __future__ import annotations

import numpy as np
import pytest

from interreal.dataset import Articulation


def test_a_part_no_route_could_tell_a_slide_from_a_leaf_asks_for_the_frames_that_decide(tmp_path, monkeypatch):
    """The edge route refused a door because a slide of its front explains its propagated masks as well: no motion
    is used, and the report asks for masks drawn on the frames it turned in (`edge_decide`), which the annotate app
    lists with why; a route that refused for another reason asks for nothing."""

    from conftest import make_tiny_dataset

    from interreal.motions import frames_asked

    ds = make_tiny_dataset(tmp_path / "ds", n_frames=12, size=(64, 48), n_objects=1)
    ids = [f.name.split("_")[-1].split(".")[0] for f in sorted((ds / "images").iterdir())]
    for decide in ([5, 7, 9], []):
        def refused(ds_, obj, states, known, labelled, keys, min_pixels, trust, conf, views, decide=decide):
            return None, {"edge_reason": "a slide of its front explains the masks ...", "edge_decide": decide}

        report = edge_only_report(monkeypatch, ds, refused)
        warned = [w for w in report["warnings"] if w.get("cause") == "motion-unregistered"]
        assert len(warned) == 1, report["warnings"]
        if not decide:
            assert "draw" not in warned[0] and frames_asked(ds) == [] and "label more frames" in warned[0]["message"]
            continue
        assert warned[0]["draw"] == [ids[5], ids[7], ids[9]], warned
        assert f"draw its mask on frames {ids[5]}, {ids[7]}, {ids[9]}" in warned[0]["message"]
        assert [(a["fid"], "decides" in a["why"]) for a in frames_asked(ds)] == [(ids[i], True) for i in decide]


@pytest.mark.parametrize("contested", [True, False])
def test_a_slide_is_not_used_where_the_edge_routes_leaf_explained_the_masks_better(tmp_path, monkeypatch, contested):
    """The edge route refused a door's leaf only by the margins it must beat a slide by, though it beat it on both
    counts: the prism route's slide (its own rival leaf unrefined) is then not used either, and the frames that
    decide are asked for; where the slide explained the masks better on a count, the prism's slide stands."""
    from conftest import make_tiny_dataset

    from interreal.dataset import load_dataset
    from interreal.motions import part as motions

    ds = load_dataset(make_tiny_dataset(tmp_path / "ds", n_frames=12, size=(64, 48), n_objects=1))
    edge_fig = {"edge_reason": "a slide of its front explains ...", "edge_decide": [4, 6, 8],
                "edge_contested": contested, "edge_outline_px": 1.4, "edge_slide_outline_px": 4.7,
                "edge_hinge_iou": 0.93, "edge_slide_iou": 0.9}
    slide_fig = {"accepted": True, "reason": "", "registered": 10, "flagged_labels": [], "label_check": [],
                 "ends_from": "closed end 0: labelled; open end 1: labelled"}
    routes = {"edge": ("static edge", lambda *a: (None, dict(edge_fig))),
              "prism": ("front pulled out", lambda *a: (Articulation("slide", np.array([1.0, 0, 0]), np.zeros(3), 0.3),
                                                        dict(slide_fig)))}
    monkeypatch.setattr(motions, "OUTLINE_ROUTES", routes)
    monkeypatch.setattr(motions, "views_of", lambda ds_, obj: None)
    st, kn = np.zeros(12), np.zeros(12, bool)
    motion, fig = motions.measure_part(None, ds, [], tmp_path / "part", st, kn, motions.MotionConfig(), obj=0,
                                       routes=("edge", "prism"))
    assert motion.kind == "slide" and fig["accepted"] is not contested, fig
    if contested:
        assert "the masks do not tell" in fig["reason"] and fig["draw_frames"] == [4, 6, 8]
        assert fig["routes"]["prism"]["accepted"] is False
    else:
        assert "draw_frames" not in fig


def test_the_summary_line_ends_cleanly_when_no_object_was_measured(tmp_path, monkeypatch, capsys):
    import argparse

    from interreal.motions import stage

    monkeypatch.setattr(stage, "estimate_motions", lambda ds, force=False, **kw: {"measured": 0, "total": 2,
                                                                                  "objects": {}, "parts": {}})
    monkeypatch.setattr(stage, "values_from_args", lambda cls, args: {})
    stage.main(argparse.Namespace(dataset=tmp_path, force=False))
    assert capsys.readouterr().out.strip().splitlines()[-1] == "motions: 0 of 2 objects measured"


def test_a_leaf_is_kept_where_it_wins_one_count_and_loses_neither():
    """Propagated masks of a plain door stray, so the leaf may tie with a slide of its front on one count and beat it
    clearly on the other (the simulated plain doors' figures): kept, not on both counts (a drawn mask confirms it);
    a leaf that loses one count by its margin is refused whatever it wins on the other."""
    from interreal.motions.edge import leaf_beats_slide

    assert leaf_beats_slide(2.7, 2.6, 0.94, 0.78) == (True, False)   # overlap won, outline tied
    assert leaf_beats_slide(1.4, 4.7, 0.93, 0.90) == (True, False)   # outline won, overlap tied
    assert leaf_beats_slide(1.0, 4.0, 0.95, 0.80) == (True, True)    # both won
    assert leaf_beats_slide(1.0, 4.0, 0.80, 0.90)[0] is False        # outline won, overlap lost
    assert leaf_beats_slide(5.0, 2.0, 0.95, 0.80)[0] is False        # overlap won, outline lost
    assert leaf_beats_slide(3.2, 3.7, 0.77, 0.84)[0] is False        # a drawer: the slide better on both


def test_a_leaf_kept_on_one_count_is_used_and_the_frames_that_confirm_it_are_asked_for(tmp_path, monkeypatch):
    """The edge route's leaf beat the slide of its front on one count only: the hinge is used, the report says a
    slide explains its masks nearly as well and asks for masks drawn where it turned (`edge_confirm`, the warning's
    `draw`), which the annotate app lists as confirming it; a leaf that won on both counts asks for nothing."""

    from conftest import make_tiny_dataset

    from interreal.motions import frames_asked

    ds = make_tiny_dataset(tmp_path / "ds", n_frames=12, size=(64, 48), n_objects=1)
    ids = [f.name.split("_")[-1].split(".")[0] for f in sorted((ds / "images").iterdir())]
    for confirm in ([3, 6, 9], []):
        def used(ds_, obj, states, known, labelled, keys, min_pixels, trust, conf, views, confirm=confirm):
            fig = {"accepted": True, "reason": "", "registered": 10, "flagged_labels": [], "label_check": [],
                   "ends_from": "closed end 0: labelled; open end 1: labelled", "frame_states": [],
                   "edge_outline_px": 2.7, "edge_slide_outline_px": 2.6, "edge_hinge_iou": 0.94,
                   "edge_slide_iou": 0.78}
            return Articulation("hinge", np.array([0.0, 0, 1]), np.zeros(3), 1.4), dict(fig, edge_confirm=confirm)

        report = edge_only_report(monkeypatch, ds, used)
        warned = [w for w in report["warnings"] if w.get("cause") == "motion-contested"]
        assert report["figures"]["measured"] == 1, report["figures"]
        if not confirm:
            assert warned == [] and frames_asked(ds) == [], report["warnings"]
            continue
        assert len(warned) == 1 and warned[0]["draw"] == [ids[3], ids[6], ids[9]], report["warnings"]
        assert "is used, but a slide of its front explains" in warned[0]["message"]
        assert "overlap 0.94 against 0.78" in warned[0]["message"]
        assert [(a["fid"], "confirms" in a["why"]) for a in frames_asked(ds)] == [(ids[i], True) for i in confirm]


def edge_only_report(monkeypatch, ds, measure) -> dict:
    """The motions report of `ds` when the edge route alone runs, as `measure` (the route's signature) says."""
    import json

    from interreal.motions import estimate_motions
    from interreal.motions import part as motions

    monkeypatch.setattr(motions, "OUTLINE_ROUTES", {"edge": ("static edge", measure)})
    monkeypatch.setattr(motions, "views_of", lambda ds_, obj: None)
    monkeypatch.setattr(motions, "ROUTES", ("edge",))
    monkeypatch.setattr(motions.MotionConfig, "route", "edge")
    estimate_motions(ds, min_pixels=10, min_registered=2, erode=0, force=True)
    return json.loads((ds / "reports" / "motions.json").read_text())
