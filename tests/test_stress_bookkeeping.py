"""The stress runner's bookkeeping on two levels (no simulation: a fake runner stands in for the pipeline)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "recipes"))
spec = importlib.util.spec_from_file_location("bench_stress", REPO / "recipes" / "bench_stress.py")
bench_stress = importlib.util.module_from_spec(spec)
sys.modules["bench_stress"] = bench_stress  # dataclasses look their module up
spec.loader.exec_module(bench_stress)


def fake_runner(stress, field, level, train, work, frames, size, steps):
    LR = bench_stress.LevelResult
    if level == "photo":
        return LR(stress, level, {"registered_frac": 1.0, "rot_err_deg": 0.05, "mask_iou_min": 0.95}, {})
    if level == "low":  # poses fail, warned; masks bad and nobody said so
        return LR(stress, level, {"registered_frac": 0.5, "rot_err_deg": 3.0, "mask_iou_min": 0.5},
                  {"poses": ["frames 10-20 did not register: too little texture"]})
    # none: SfM refused with an error; later stages never ran
    return LR(stress, level, {}, {}, ("poses", "SfM registered 2 of 40 frames"))


def test_rows_usable_detected_and_silent():
    suite = {"texture": ("texture", ["photo", "low", "none"], [], False)}
    rows = bench_stress.run_suite(suite, quick=True, work=Path("/nonexistent"), runner=fake_runner)
    by = {(r["level"], r["metric"]): r for r in rows}
    assert by[("photo", "registered_frac")]["usable"] and by[("photo", "mask_iou_min")]["usable"]
    low_reg = by[("low", "registered_frac")]
    assert not low_reg["usable"] and low_reg["detected"] and "texture" in low_reg["message"]
    low_mask = by[("low", "mask_iou_min")]
    assert not low_mask["usable"] and not low_mask["detected"]
    none_reg = by[("none", "registered_frac")]
    assert none_reg["value"] is None and not none_reg["usable"] and none_reg["detected"]
    silent = bench_stress.silent_failures(rows)
    assert [(r["level"], r["metric"]) for r in silent] == [("low", "mask_iou_min")]


def test_level_filter_runs_only_the_named_levels():
    suite = {"texture": ("texture", ["photo", "low", "none"], [], False)}
    rows = bench_stress.run_suite(suite, quick=True, work=Path("/nonexistent"), runner=fake_runner, levels={"low"})
    assert {r["level"] for r in rows} == {"low"}


def test_thresholds_direction():
    assert bench_stress.is_usable("psnr", 30.0) and not bench_stress.is_usable("psnr", 10.0)
    assert bench_stress.is_usable("rot_err_deg", 0.1) and not bench_stress.is_usable("rot_err_deg", 5.0)
    assert not bench_stress.is_usable("state_mae", None)


def test_crash_is_a_silent_failure():
    def crashing(*a, **k):
        raise ValueError("boom")

    rows = bench_stress.run_suite({"noise": ("noise", [3.0], [], False)}, True, Path("/x"), runner=crashing)
    assert len(bench_stress.silent_failures(rows)) == 1 and "boom" in rows[0]["message"]


def test_only_degradation_causes_count_as_detection(tmp_path):
    import json

    rep = tmp_path / "masks.json"
    rep.write_text(json.dumps({"warnings": [{"message": "low confidence on 3 frames; add a keyframe", "cause": "propagation"}]}))
    assert bench_stress._warnings(rep, "masks") == []
    rep.write_text(json.dumps({"warnings": [{"message": "masks are unreliable", "cause": "masks-unreliable"}]}))
    assert bench_stress._warnings(rep, "masks") == ["masks are unreliable"]


def test_trainer_warns_about_too_few_labels():
    from types import SimpleNamespace

    import numpy as np

    from livescene.trainer import label_warnings

    given = np.zeros((40, 2), bool)
    given[::4, 0] = True  # 10 of 40 frames: fine
    given[0, 1] = True  # 1 frame: too few
    views = SimpleNamespace(train=list(range(40)), names=["door", "drawer"], given=given)
    warned = label_warnings(views)
    assert len(warned) == 1 and "'drawer'" in warned[0][0] and warned[0][1] == "few-labels"


def test_trainer_warns_when_learned_states_miss_held_out_labels():
    from types import SimpleNamespace

    import numpy as np

    from livescene.trainer import state_warnings

    labels = np.zeros((16, 1), np.float32)
    labels[8:] = 1.0
    given = np.zeros((16, 1), bool)
    given[[0, 8, 12, 15]] = True
    ds = SimpleNamespace(label_matrix=lambda: (labels, given))
    views = SimpleNamespace(dataset=ds, names=["door"], train=[i for i in range(16) if i % 8], held_out=[0, 8])
    good = labels.copy()
    assert state_warnings(good, views) == []
    bad = good.copy()
    bad[8] = 0.2  # the held-out labelled frame 8 is missed by 0.8 -> mean error 0.4 over frames 0 and 8
    warned = state_warnings(bad, views)
    assert len(warned) == 1 and "held-out" in warned[0][0] and warned[0][1] == "states-unreliable"


def test_a_resumed_run_keeps_earlier_rows_and_skips_their_levels(tmp_path):
    suite = {"texture": ("texture", ["photo", "low", "none"], [], False)}
    saved = []
    first = bench_stress.run_suite(suite, quick=True, work=tmp_path, runner=fake_runner, levels={"photo"},
                                   on_level=lambda rows: saved.append(len(rows)))
    assert saved == [3]  # written after the level, not only at the end
    calls = []

    def counting(stress, field, level, *a):
        calls.append(level)
        return fake_runner(stress, field, level, *a)

    rows = bench_stress.run_suite(suite, quick=True, work=tmp_path, runner=counting, done=first)
    assert calls == ["low", "none"] and [r["level"] for r in rows[:3]] == ["photo"] * 3
    import json

    (tmp_path / "stress.json").write_text(json.dumps({"quick": True, "runs": first}))
    assert bench_stress.earlier_rows(tmp_path / "stress.json", quick=True) == first
    assert bench_stress.earlier_rows(tmp_path / "stress.json", quick=False) == []  # another mode: start afresh
