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
    import json

    from conftest import make_tiny_dataset

    from interreal.motions import estimate_motions, frames_asked
    from interreal.motions import part as motions

    ds = make_tiny_dataset(tmp_path / "ds", n_frames=12, size=(64, 48), n_objects=1)
    ids = [f.name.split("_")[-1].split(".")[0] for f in sorted((ds / "images").iterdir())]
    for decide in ([5, 7, 9], []):
        def refused(ds_, obj, states, known, labelled, keys, min_pixels, trust, conf, views, decide=decide):
            return None, {"edge_reason": "a slide of its front explains the masks ...", "edge_decide": decide}

        monkeypatch.setattr(motions, "OUTLINE_ROUTES", {"edge": ("static edge", refused)})
        monkeypatch.setattr(motions, "views_of", lambda ds_, obj: None)
        monkeypatch.setattr(motions, "ROUTES", ("edge",))
        monkeypatch.setattr(motions.MotionConfig, "route", "edge")
        estimate_motions(ds, min_pixels=10, min_registered=2, erode=0, force=True)
        report = json.loads((ds / "reports" / "motions.json").read_text())
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
