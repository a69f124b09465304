"""A hinge measured from poses in the frames a route registered, carried by the masks past its measured angles
(`motions.reach`): the tall plain door of `edge_scenes`, a pose route that registered it only up to half open."""

from __future__ import annotations

import numpy as np
from edge_scenes import KEYS, TALL, capture

from interreal.dataset import Articulation
from interreal.motions import part_line, part_summary
from interreal.motions.edge import trusted_frames
from interreal.motions.fit import LABELS_LINE
from interreal.motions.reach import MIN_BEYOND, reach_hinge
from interreal.motions.silhouette import views_of

TURN = np.radians(80.0)  # the scene's door turns this far at state 1, about -z through its left edge


def _half_measured(truth: np.ndarray, reach: float = 0.5) -> tuple[Articulation, dict]:
    """What a pose route gives where it registered only the frames up to `reach` of the way open and nothing labels
    the end it measured: its states 0 to 1 over what it saw, so its range is `reach` of the truth."""
    seen = np.flatnonzero(truth <= reach)
    fig = {"frame_states": [[int(i), float(truth[i] / reach)] for i in seen], "accepted": True, "route": "sfm",
           "rot_noise_deg": 0.3, "reason": "", "ends_from": f"closed end 0: labelled; open end 1: {LABELS_LINE} (no "
                                                              f"label says 1)"}
    return Articulation("hinge", np.array([0.0, 0.0, -1.0]), TALL[0].copy(), reach * TURN, dict(fig)), fig


def _reach(ds, motion, fig, st, kn, labelled):
    views = views_of(ds, 0)
    frames = trusted_frames(views, KEYS, 50, None)
    return reach_hinge(views, motion, fig, frames, KEYS, st, kn, labelled)


def test_the_frames_past_the_measured_angles_are_read_by_their_masks_and_give_the_range():
    ds, truth, st, kn, labelled, _ = capture("hinge")
    motion, fig = _half_measured(truth)
    reached, out = _reach(ds, motion, fig, st, kn, labelled)
    assert reached is not None and out["accepted"], out
    assert out["reach_beyond"] >= 0.6 * (truth > 0.5).sum() and out["reach_agree_iou"] > 0.9
    assert abs(np.degrees(reached.range) - 80) < 3, np.degrees(reached.range)
    assert np.allclose(reached.axis, motion.axis) and np.allclose(reached.origin, motion.origin)
    rows = np.array(out["frame_states"])
    assert len(rows) > len(fig["frame_states"])
    assert np.sqrt(np.mean((rows[:, 1] - truth[rows[:, 0].astype(int)]) ** 2)) < 0.04
    opened = rows[truth[rows[:, 0].astype(int)] == 1.0, 1]
    assert len(opened) >= 6 and np.all(np.abs(opened - 1.0) < 0.06), opened
    assert "the labels' line" not in out["ends_from"]


def test_two_frames_past_the_measured_angles_are_not_enough():
    """The masks lost the door as it opened further (a propagated mask that let go), but for two frames: one or two
    frames past the end could be stray masks, so the route's motion stands as it was, with why."""
    ds, truth, st, kn, labelled, masks = capture("hinge")
    kept = np.flatnonzero(truth > 0.5)[:MIN_BEYOND - 1]
    for i in np.flatnonzero(truth > 0.5):
        if i not in kept:
            masks[i] = np.zeros_like(masks[i])
    ds.load_mask = lambda f: masks[f.index]
    motion, fig = _half_measured(truth)
    reached, out = _reach(ds, motion, fig, st, kn, labelled)
    assert reached is None and out["reach_beyond"] < MIN_BEYOND, out
    assert "beyond the measured angles" in out["reach_reason"]


def test_masks_that_run_ahead_of_the_part_right_after_it_rests_are_not_joined_to_the_measured_frames():
    """The masks of the frames as the door starts to open show it at the open end (a propagated mask running ahead):
    they read far past the measured angles and agree with one another, but none is a plausible step from the
    registered frame beside them; the open stretch's own frames still are."""
    ds, truth, st, kn, labelled, masks = capture("hinge")
    moving = np.flatnonzero((truth > 0.0) & (truth < 0.5) & (np.arange(len(truth)) < 20))
    for i in moving:
        masks[i] = masks[22]
    ds.load_mask = lambda f: masks[f.index]
    motion, fig = _half_measured(truth)
    fig["frame_states"] = [row for row in fig["frame_states"] if row[0] not in moving]
    reached, out = _reach(ds, motion, fig, st, kn, labelled)
    assert reached is not None, out
    rows = dict((int(f), s) for f, s in out["frame_states"])
    assert not any(i in rows for i in moving), [(i, rows.get(i)) for i in moving]
    assert abs(np.degrees(reached.range) - 80) < 3


def test_a_leaf_sized_too_wide_by_the_masks_alone_is_pinned_by_the_registered_frames_angles(monkeypatch):
    """The masks alone sized the leaf 40 % too wide and 20 % too short (a closed door cut by the image border leaves
    its free edge loose): the registered frames at their measured angles pin the size again, and the open end is read
    at the door's true angle, not short of it."""
    from interreal.motions import reach

    fitted = reach.fit_leaf

    def loose(*args, **kwargs):
        size, score = fitted(*args, **kwargs)
        return size * np.array([1.4, 1.0, 0.8]), score

    monkeypatch.setattr(reach, "fit_leaf", loose)
    ds, truth, st, kn, labelled, _ = capture("hinge")
    motion, fig = _half_measured(truth)
    reached, out = _reach(ds, motion, fig, st, kn, labelled)
    assert reached is not None and out["accepted"], out
    assert abs(np.degrees(reached.range) - 80) < 3, np.degrees(reached.range)
    monkeypatch.setattr(reach, "fit_measured", lambda sil, leaf, size, theta, frames, rel: (size, theta, 0.9))
    unpinned, out = _reach(ds, motion, fig, st, kn, labelled)  # the check itself: the loose leaf alone reads it off
    assert unpinned is None or abs(np.degrees(unpinned.range) - 80) > 3, np.degrees(unpinned.range)


def test_a_leaf_that_does_not_explain_the_registered_frames_carries_nothing():
    """The measured axis far from the door's edge (a wrong hinge): the leaf on it cannot overlap the registered
    frames' masks at their measured angles, and nothing is read."""
    ds, truth, st, kn, labelled, _ = capture("hinge")
    motion, fig = _half_measured(truth)
    motion.origin = TALL[0] + np.array([1.5, -1.0, 0.0])
    reached, out = _reach(ds, motion, fig, st, kn, labelled)
    assert reached is None and "registered frames' masks" in out["reach_reason"], out


def test_the_summary_says_how_many_frames_the_masks_read():
    ds, truth, st, kn, labelled, _ = capture("hinge")
    motion, fig = _half_measured(truth)
    reached, out = _reach(ds, motion, fig, st, kn, labelled)
    line = part_line("door", part_summary(reached, out, shown=50))
    assert f"({out['reach_beyond']} past its measured angles read by their masks)" in line, line


def test_a_pose_routes_hinge_is_reached_from_the_keyframes_the_dataset_lists(tmp_path):
    """`part.reached`, as `measure_part` calls it after an accepted sfm or pnp hinge: the keyframes are those the
    dataset lists; without a frame past the measured angles the route's motion stands, with why, in its figures."""
    from interreal.conventions import fid_of_index
    from interreal.layout import KEYFRAMES_DIR
    from interreal.motions.part import MotionConfig, reached

    ds, truth, st, kn, labelled, masks = capture("hinge", root=tmp_path)
    ds.object_names = ["door"]
    (tmp_path / KEYFRAMES_DIR).mkdir()
    for k in KEYS:
        (tmp_path / KEYFRAMES_DIR / f"{fid_of_index(k)}.png").write_bytes(b"")
    cfg = MotionConfig(min_pixels=50)
    motion, fig = _half_measured(truth)
    got, out = reached(views_of(ds, 0), (motion, fig), ds, 0, st, kn, labelled, cfg)
    assert got is not motion and out["accepted"] and abs(np.degrees(got.range) - 80) < 3
    motion, fig = _half_measured(truth, reach=1.0)  # it registered every frame: nothing past its angles
    got, out = reached(views_of(ds, 0), (motion, fig), ds, 0, st, kn, labelled, cfg)
    assert got is motion and out["accepted"] and "beyond the measured angles" in out["reach_reason"]
    motion, fig = _half_measured(truth)
    fig["ends_from"] = "closed end 0: labelled; open end 1: labelled"  # the route measured both ends: its own stand
    got, out = reached(views_of(ds, 0), (motion, fig), ds, 0, st, kn, labelled, cfg)
    assert got is motion and out is fig and "reach_beyond" not in out


def test_the_warning_that_a_range_rests_on_the_labels_says_why_the_masks_did_not_carry_it():
    from interreal.motions.stage import ends_warnings

    ds, truth, st, kn, labelled, masks = capture("hinge")
    for i in np.flatnonzero(truth > 0.5):
        masks[i] = np.zeros_like(masks[i])  # the masks lost the door as it opened further
    ds.load_mask = lambda f: masks[f.index]
    motion, fig = _half_measured(truth)
    reached, out = _reach(ds, motion, fig, st, kn, labelled)
    assert reached is None
    (text, cause), = ends_warnings("door", {**fig, **out})
    assert cause == "ends-from-labels" and "its masks past there: 0 of the frames it did not register" in text, text


def test_where_an_end_is_the_labels_guess_the_person_is_asked_to_draw_frames_past_the_measured_ones():
    """A door its route registered up to half open, then lost for frames 8-31 (it opened further there) and
    measured again from frame 32 as it closed: the frames to draw lie in that run, the masks stage's own suggestions
    there first, keyframes never; none where both ends were measured or the run is next only to closed frames."""
    from interreal.motions.reach import ASK, frames_to_draw, guessed_ends

    states = {**{i: i / 14 for i in range(8)}, 32: 1.0, **{i: max(0.0, 1.0 - (i - 32) / 5) for i in range(33, 60)}}
    fig = {"frame_states": [[i, s] for i, s in states.items()],
           "ends_from": f"oriented by the labels; closed end 0: labelled; open end 0.6: {LABELS_LINE} (the frames "
                        f"measured there are labelled 0.4)"}
    assert guessed_ends(fig) == ["open"]
    asked = frames_to_draw(fig, 60, keys=[0, 59], prefer=[45, 29, 12, 20, 3])
    assert asked == [12, 20, 29]  # the stage's suggestions inside the run, not 45 or 3 (measured) beyond ASK
    assert len(frames_to_draw(fig, 60, keys=[], prefer=[29, 12, 20, 25])) == ASK
    assert frames_to_draw(fig, 60, keys=[0, 59], prefer=[]) == [20]  # no suggestion there: the run's middle
    assert frames_to_draw(fig, 60, keys=[20], prefer=[]) == []  # ... which is a keyframe already
    both = dict(fig, ends_from="closed end 0: labelled; open end 1: labelled")
    assert guessed_ends(both) == [] and frames_to_draw(both, 60, [], [12]) == []
    shut = dict(fig, ends_from=f"closed end 0.3: {LABELS_LINE} (no label says 0); open end 1: labelled")
    assert guessed_ends(shut) == ["closed"] and frames_to_draw(shut, 60, [], [12, 20]) == [12, 20]  # from 0.5 on
    high = {**{i: 0.8 + i / 50 for i in range(8)}, **{i: 1.0 - (i - 32) / 30 for i in range(32, 60)}}
    shut["frame_states"] = [[i, s] for i, s in high.items()]
    assert frames_to_draw(shut, 60, [], [12, 20]) == []  # the run lies between frames near the open end only
    every = dict(fig, frame_states=[[i, min(i, 30) / 30] for i in range(60)])  # a route that read every frame
    assert frames_to_draw(every, 60, [], [45]) == []
    # the masks lost the door over its whole opening (frames 8-53): it was measured only closed before, and from
    # part way on its way back; a gap between two frames resting closed (the masks lost it there, at rest) is no ask
    back = {**{i: 0.0 for i in range(8)}, **{i: min(1.0, (i - 50) / 6) for i in range(54, 62)},
            **{i: max(0.0, 1.0 - (i - 62) / 6) for i in range(62, 70)}, **{i: 0.0 for i in (70, 71, 80, 81)}}
    lost = dict(fig, frame_states=[[i, s] for i, s in back.items()])
    assert frames_to_draw(lost, 82, [], []) == [31]  # the opening's middle; not 75, between closed frames


def test_the_warning_names_the_frames_to_draw_and_the_annotate_app_lists_them(tmp_path):
    import cv2

    from interreal.annotate.store import DatasetStore
    from interreal.motions import frames_asked
    from interreal.motions.stage import ends_warnings
    from interreal.report import StageReport

    fig = {"ends_from": f"closed end 0: labelled; open end 0.6: {LABELS_LINE} (no label says 1)",
           "draw_frames": [1, 2]}
    (text, cause), = ends_warnings("door", fig, ["00000", "00012", "00020"])
    assert cause == "ends-from-labels" and "draw its mask on frames 00012, 00020" in text, text
    assert "interreal masks" in text and "check the labels" in text
    (plain, _), = ends_warnings("door", dict(fig, draw_frames=[]), ["00000", "00012", "00020"])
    assert "draw" not in plain and "check the labels" in plain
    (tmp_path / "images").mkdir()
    for i in (0, 12, 20):
        cv2.imwrite(str(tmp_path / "images" / f"frame_{i:05d}.png"), np.zeros((8, 8, 3), np.uint8))
    with StageReport(tmp_path, "motions", inputs={}, settings={}) as rep:
        rep.warn(text, cause=cause, object="door", draw=["00012", "00020", "00031"])  # 00031: no such frame
    asked = [(a["fid"], a["object"]) for a in frames_asked(tmp_path)]
    assert asked == [(f, "door") for f in ("00012", "00020", "00031")]
    listed = [s for s in DatasetStore(tmp_path).suggested() if "draw 'door'" in s["reason"]]
    assert [s["fid"] for s in listed] == ["00012", "00020"] and "labels' guess" in listed[0]["reason"]


def test_the_motions_report_asks_for_the_frames_to_draw_whether_the_motion_is_used_or_refused(tmp_path, monkeypatch):
    """`interreal motions` on a dataset whose part's open end only the labels scale: the warning (used: the range
    rests on the labels; refused: the labels' line made it turn too far) names the frames the route asked for and
    the report holds them as `draw`, which the annotate app lists."""
    import json

    from conftest import make_tiny_dataset

    from interreal.motions import estimate_motions, frames_asked
    from interreal.motions import part as motions

    ds = make_tiny_dataset(tmp_path / "ds", n_frames=12, size=(64, 48), n_objects=1)
    for accepted in (True, False):
        def measured(pc, ds_, names, part, states, known, cfg, step, labelled=None, obj=None, accepted=accepted):
            fig = {"route": "sfm", "registered": 6, "accepted": accepted, "flagged_labels": [], "label_check": [],
                   "reason": "" if accepted else "its range comes to 185 deg, more than a door turns",
                   "frame_states": [[i, i / 10] for i in (0, 1, 2, 9, 10, 11)], "routes": {},
                   "ends_from": f"closed end 0: labelled; open end 0.4: {LABELS_LINE} (no label says 1)",
                   "draw_frames": [4, 6]}
            return Articulation("hinge", np.array([0.0, 0.0, 1.0]), np.zeros(3), 1.0), fig

        monkeypatch.setattr(motions, "measure_part", measured)
        estimate_motions(ds, min_pixels=10, min_registered=2, erode=0, force=True)
        warned = [w for w in json.loads((ds / "reports" / "motions.json").read_text())["warnings"] if w.get("draw")]
        ids = [f.name.split("_")[-1].split(".")[0] for f in sorted((ds / "images").iterdir())]
        assert len(warned) == 1 and warned[0]["draw"] == [ids[4], ids[6]], warned
        assert f"draw its mask on frames {ids[4]}, {ids[6]}" in warned[0]["message"]
        assert warned[0]["cause"] == ("ends-from-labels" if accepted else "motion-inconsistent")
        assert [a["fid"] for a in frames_asked(ds)] == [ids[4], ids[6]]
