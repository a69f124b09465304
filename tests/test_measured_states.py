"""Measured states as Lvar's targets: `interreal motions` writes each registered frame's state into
articulation.json (`frame_states`), and training fits the per-frame states to them in place of that frame's
eyeballed label (on the shared laptop video the learned states were 0.42 RMS from the geometry without it)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_livescene_toy import toy_dataset  # noqa: E402

from interreal.dataset import Articulation, load_dataset, read_articulation, write_articulation  # noqa: E402
from livescene.config import load_preset  # noqa: E402


def test_measured_states_read_by_frame_id_and_nan_elsewhere():
    a = Articulation("hinge", np.array([0.0, 0, 1]), np.zeros(3), 1.0,
                     {"frame_states": {"00003": 0.25, "00006": 1.02, "00009": "x", "00012": float("nan")}})
    m = a.measured_states(["00000", "00003", "00006", "00009", "00012"])
    assert np.isnan(m[[0, 3, 4]]).all() and m[1] == 0.25 and m[2] == 1.02
    assert np.isnan(Articulation("slide", np.array([1.0, 0, 0]), np.zeros(3), 0.3).measured_states(["00000"])).all()


def _with_measured(tmp_path: Path) -> tuple[Path, list[str], dict[str, float]]:
    ds = toy_dataset(tmp_path / "ds", n_frames=16)
    fids = [f.fid for f in load_dataset(ds).frames]
    measured = {fid: round(0.05 * i, 3) for i, fid in enumerate(fids) if i % 3 != 2}
    measured[fids[0]] = 1.04  # a measurement past the labelled end: clipped to the state range
    write_articulation(ds, {"door": Articulation("hinge", np.array([0.0, 0, 1]), np.zeros(3), 1.5,
                                                 {"frame_states": measured})}, {})
    return ds, fids, measured


def test_training_targets_are_the_measured_states_over_the_labels(tmp_path):
    from livescene.data import load_views, measured_counts

    ds, fids, measured = _with_measured(tmp_path)
    assert read_articulation(ds)["door"].extra["frame_states"] == measured  # the file round-trips them
    cfg = load_preset("tiny")
    views = load_views(ds, cfg)
    labels, given = views.dataset.label_matrix()
    for i, fid in enumerate(fids):
        if i in views.held_out:
            assert not views.given[i, 0]  # held out: never a target, measured or labelled
        elif fid in measured:
            assert views.given[i, 0] and views.labels[i, 0] == pytest.approx(min(measured[fid], 1.0))
        else:
            assert views.given[i, 0] == given[i, 0]
            if given[i, 0]:
                assert views.labels[i, 0] == labels[i, 0]  # no measurement: the label stays
    assert measured_counts(views) == {"door": sum(1 for i, f in enumerate(fids) if f in measured and i in views.train)}
    # the dataset's own labels are untouched (evaluation and the label checks read those)
    assert np.array_equal(views.dataset.label_matrix()[0], labels)
    cfg.measured_states = False
    plain = load_views(ds, cfg)
    assert np.array_equal(plain.given, np.where(np.isin(np.arange(len(fids)), plain.held_out)[:, None], False, given))
    assert measured_counts(plain) == measured_counts(views)  # what there is, whether used or not


def test_eval_scores_the_learned_states_against_the_measured_ones_on_held_out_frames(tmp_path):
    from livescene.data import load_views
    from livescene.evaluate import measured_state_errors

    ds, fids, measured = _with_measured(tmp_path)
    views = load_views(ds, load_preset("tiny"))
    truth = np.array([[min(measured.get(f, np.nan), 1.0)] for f in fids])
    learned = np.where(np.isfinite(truth), truth, 0.5)
    learned[views.train] = 0.0  # training frames are not scored: only the held-out ones
    scored = [i for i in views.held_out if fids[i] in measured]
    assert scored  # the split holds out measured frames
    assert measured_state_errors(learned, views) == {"state_mae_measured_held_out": 0.0,
                                                     "state_measured_held_out": len(scored)}
    learned[scored] += 0.1
    assert measured_state_errors(learned, views)["state_mae_measured_held_out"] == pytest.approx(0.1)
    plain = load_views(toy_dataset(tmp_path / "plain", n_frames=8), load_preset("tiny"))
    assert measured_state_errors(np.zeros((8, 1)), plain) == {}


def test_states_that_follow_the_measurement_are_no_failed_fit(tmp_path):
    """Learned states on the measured states, away from eyeballed labels that disagree with them: no warning (the
    labels are `interreal motions`' to flag); states off the measurement: the warning."""
    from livescene.data import load_views
    from livescene.fitcheck import state_warnings

    ds, fids, measured = _with_measured(tmp_path)
    views = load_views(ds, load_preset("tiny"))
    labels, given = views.dataset.label_matrix()
    follow = np.array([[min(measured[f], 1.0) if f in measured else labels[i, 0]] for i, f in enumerate(fids)])
    both = [i for i, f in enumerate(fids) if f in measured and given[i, 0]]
    assert np.abs(follow[both, 0] - labels[both, 0]).mean() > 0.1  # the labels disagree with the geometry
    assert state_warnings(follow, views) == []
    off = follow.copy()
    off[views.train] += 0.3
    warned = state_warnings(np.clip(off, 0, 1), views)
    assert warned and "labelled or measured training" in warned[0][0]
    cfg = load_preset("tiny")
    cfg.measured_states = False  # a run fitted to the labels alone is checked against the labels
    warned = state_warnings(follow, load_views(ds, cfg))
    assert warned and "labelled training" in warned[0][0]
