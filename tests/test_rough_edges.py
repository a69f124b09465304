"""Rough edges a new user met (issue 24, item 6): each fixed where it lives, each checked here in seconds."""

from __future__ import annotations

import json

import pytest
import yaml

from interreal import cli
from interreal import process as proc
from interreal.errors import InputError
from interreal.report import StageReport


def _stage(ds, name, warning=None, **figures):
    with StageReport(ds, name) as rep:
        rep.figures.update(figures)
        if warning:
            rep.warn(warning, cause=f"{name}-cause")


def _fake_stages(monkeypatch, calls):
    def frames(src, ds, **kw):
        _stage(ds, "frames", "3 frames are black", selected=3, source_frames=10, size=[64, 48])
        return [1, 2, 3]

    def poses(ds, **kw):
        _stage(ds, "poses")
        return {"registered": 3, "total": 3}

    def import_labels(ds, f, **kw):
        calls.append(kw)
        _stage(ds, "labels", "1 label row names a missing frame", imported=2, labels=2, objects=["door"])

    monkeypatch.setattr(proc, "extract_frames", frames)
    monkeypatch.setattr(proc, "estimate_poses", poses)
    monkeypatch.setattr(proc, "import_labels", import_labels)


def test_process_collects_stage_warnings_prints_summaries_and_passes_units(tmp_path, monkeypatch, capsys):
    calls: list[dict] = []
    _fake_stages(monkeypatch, calls)
    states = tmp_path / "states.yaml"
    states.write_text(yaml.safe_dump({"frame_00002": {"door": 45}}))
    ds = tmp_path / "ds"
    assert cli.main(["process", "in.mp4", str(ds), "--labels", str(states), "--degrees", "0:90"]) == 0
    assert calls == [{"degrees": "0:90"}]  # the same meaning as `interreal label --degrees`
    rep = json.loads((ds / "reports" / "process.json").read_text())
    got = {(w["stage"], w["message"]) for w in rep["warnings"]}
    assert {("frames", "3 frames are black"), ("labels", "1 label row names a missing frame")} <= got
    out = capsys.readouterr().out
    assert "frames: 3 selected of 10 source frames" in out and "labels: 2 imported" in out
    assert "warning (frames): 3 frames are black" in out


def test_process_units_need_labels_and_a_valid_range(tmp_path):
    with pytest.raises(InputError, match="--labels"):
        proc.process("in.mp4", tmp_path / "ds", cm="0:40")
    states = tmp_path / "s.yaml"
    states.write_text(yaml.safe_dump({"frame_00002": {"door": 45}}))
    with pytest.raises(InputError, match="--degrees"):
        proc.process("in.mp4", tmp_path / "ds", labels=states, degrees="ninety")
    assert not (tmp_path / "ds" / "images").exists()


def test_validate_warns_of_too_few_labels_with_the_trainers_figures(tmp_path, capsys):
    from types import SimpleNamespace

    import numpy as np

    from conftest import make_tiny_dataset
    from interreal.dataset import validate
    from livescene.trainer import label_warnings

    ds = make_tiny_dataset(tmp_path / "ds", n_frames=30, size=(16, 12))  # 'door' labelled on 2 of 30 frames
    res = validate(ds, check_masks=False)
    assert res.ok, res.problems  # a warning, not a problem
    assert any("'door' has state labels on only 2 of 30 frames" in w for w in res.warnings)
    assert any("'drawer' has state labels on only 0 of 30" in w for w in res.warnings)
    assert cli.main(["validate", str(ds), "--no-masks"]) == 0
    assert "warning: 'door' has state labels on only 2 of 30 frames" in capsys.readouterr().out
    # the trainer checks its training frames against the same figures, before it trains
    given = np.zeros((30, 1), bool)
    given[[0, 29], 0] = True
    warned = label_warnings(SimpleNamespace(train=list(range(30)), names=["door"], given=given))
    assert warned and "only 2 of 30 training frames" in warned[0][0]


def test_train_warns_of_too_few_labels_before_it_trains(tmp_path, monkeypatch, capsys):
    from types import SimpleNamespace

    import numpy as np

    from livescene import trainer as T

    given = np.zeros((20, 1), bool)
    given[0, 0] = True
    seen = []

    def fit():
        seen.append(capsys.readouterr().err)  # what the user had been told when training began
        return {"steps": 1, "eval_psnr": 30.0, "eval_on": "held-out"}

    fake = SimpleNamespace(views=SimpleNamespace(train=list(range(20)), names=["door"], given=given),
                           dataset_path=tmp_path, cfg=SimpleNamespace(to_dict=dict), fit=fit)
    monkeypatch.setattr(T, "learned_states", lambda tr: (None, None))
    monkeypatch.setattr(T, "state_warnings", lambda *a: [])
    T._train(fake, tmp_path / "run")
    assert "only 1 of 20 training frames" in seen[0]
    assert "only 1 of 20" not in capsys.readouterr().err  # said once, not again at the end


def test_render_frames_index_the_chosen_camera_set_and_sweep_follows_it():
    from types import SimpleNamespace

    from livescene.errors import LiveSceneError
    from livescene.render import choose_cameras

    held_out = [{"name": f"{i:05d}"} for i in (7, 15, 23)]  # the held-out frames of a 24-frame dataset
    dataset = [{"name": f"{i:05d}"} for i in range(24)]

    def pick(jobs, cameras, frames="", sweep=None):
        return [j["name"] for j in choose_cameras(jobs, SimpleNamespace(cameras=cameras, frames=frames, sweep=sweep))]

    assert pick(held_out, "held-out", "0,2") == ["00007", "00023"]  # not dataset frames 0 and 2
    assert pick(held_out, "held-out") == ["00007", "00015", "00023"]
    assert pick(dataset, "dataset") == ["00000", "00008", "00016"]
    assert pick(dataset, "dataset", sweep="door=0:1:3") == ["00000"]
    assert pick(held_out, "held-out", "1", sweep="door=0:1:3") == ["00015"]  # the sweep's camera, by its set
    with pytest.raises(LiveSceneError, match="position 3 is not a frame of --cameras held-out"):
        pick(held_out, "held-out", "3")


def test_eval_splits_labelled_state_error_into_train_and_held_out():
    from types import SimpleNamespace

    import numpy as np

    from livescene.evaluate import labelled_state_errors

    labels = np.array([[0.0], [0.5], [1.0], [1.0]])
    given = np.array([[True], [True], [False], [True]])
    learned = np.array([[0.02], [0.46], [0.9], [0.7]])  # training labels fitted, the held-out one missed by 0.3
    res = labelled_state_errors(learned, labels, given, SimpleNamespace(train=[0, 1, 2], held_out=[3]))
    assert res["state_mae_labelled_train"] == pytest.approx(0.03)
    assert res["state_mae_labelled_held_out"] == pytest.approx(0.3)
    assert (res["state_labels_train"], res["state_labels_held_out"]) == (2, 1)
    none = labelled_state_errors(learned, labels, given, SimpleNamespace(train=[0, 1, 2, 3], held_out=[]))
    assert none["state_mae_labelled_held_out"] is None and none["state_labels_held_out"] == 0


def test_training_evaluations_render_the_same_held_out_frame_each_time():
    from types import SimpleNamespace

    from livescene.trainer import Trainer

    fake = SimpleNamespace(eval_pool=lambda: [7, 15, 23, 31], eval_cursor=0, _timed_psnr=lambda i: 20.0 + i)
    fake.quick_frame = Trainer.quick_frame.fget(fake)
    frames = [Trainer.quick_eval(fake)["frame"] for _ in range(3)]
    assert frames == [23, 23, 23] and fake.eval_cursor == 3


def test_thread_trial_keeps_the_faster_of_many_and_one_thread():
    import torch

    from livescene.device import ThreadTrial

    before = torch.get_num_threads()
    try:
        for slow, want in ((2, 1), (1, 2)):  # busy machine: 2 threads slow; idle one: 1 thread slow
            trial, used = ThreadTrial(2), []
            while not trial.done:
                n = trial.before_step()
                used.append(n)
                assert torch.get_num_threads() == n
                trial.after_step(0.5 if n == slow else 0.1)
            assert trial.chosen == want and torch.get_num_threads() == want
            assert set(used) == {1, 2} and len(used) <= 14  # a dozen steps, not a benchmark
            assert f"kept {want}" in trial.summary()
        assert ThreadTrial(1).done  # one core: nothing to measure
    finally:
        torch.set_num_threads(before)


def test_motions_name_the_labels_that_disagree_and_report_progress(monkeypatch, tmp_path):
    import numpy as np

    from interreal.motions import part, stage as motions
    from test_motions import _slide_case

    truth, states, known, pv = _slide_case(seed=4, wild=0)
    labelled = states.copy()
    bad = np.flatnonzero(known & (states == 0))[:2]  # two eyeballed labels that say open where it is closed
    labelled[bad] = 1.0
    motion, fig = motions.fit_motion(pv, labelled, known)
    check = {f: (lab, m) for f, lab, m in fig["label_check"]}
    assert len(check) >= known.sum() - fig["slide_rejected"] - 1
    for f in bad:
        assert check[f][0] == 1.0 and check[f][1] < 0.3  # the geometry says closed
    fids = [f"{i:05d}" for i in range(len(states))]
    text = motions.disagreement_text(fig["label_check"], fids)
    assert all(f"{fids[f]} (label 1.00" in text for f in bad) and "measured states" in text
    # progress: one call as each phase starts
    phases = []
    monkeypatch.setattr(part, "match_part", lambda *a, **k: tmp_path / "database.db")
    monkeypatch.setattr(part, "map_part", lambda *a, **k: 0)
    monkeypatch.setattr(part, "part_views", lambda rec, ds: pv)
    monkeypatch.setattr(part, "known_camera_motion",  # no tracks to pose: the slide's own poses stand
                        lambda *a, **k: (None, {"registered": 0, "at_known_state": 0, "known_reason": "no tracks"}))
    part.measure_part(None, None, [], tmp_path, states, known, part.MotionConfig(attempts=3, route="sfm"),
                      phases.append)
    assert phases == ["matching", "reconstruction 1/3"]


def test_masks_suggest_one_list_of_keyframes_that_the_warnings_name_too():
    import numpy as np

    from interreal.masks.confidence import next_keyframes, suggest_frames

    rng = np.random.default_rng(0)
    conf = rng.uniform(0.6, 0.95, (130, 1))
    conf[60:75] = 0.2  # least certain stretch: what suggest_frames picks first
    is_key = np.zeros(130, bool)
    is_key[[0, 129]] = True
    lost = [[(100, 110)]]  # the object vanished there (a confident but empty mask)
    picks = next_keyframes(conf, is_key, 5, lost, reach=[40])
    assert picks[:2] == [100, 40] and len(picks) == 5  # the lost stretch the warning names is suggested first
    assert set(picks[2:]) <= set(suggest_frames(conf, is_key, 5))
    assert next_keyframes(conf, is_key, 0, lost, [40]) == []
