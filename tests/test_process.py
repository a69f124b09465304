"""`interreal process`: stage order, annotated frames forced into the selection, end to end."""

from __future__ import annotations

import json

import pytest
import yaml

from interreal import cli
from interreal import process as proc
from interreal.errors import InputError

from test_sfm import errors, gt


def test_annotation_files_name_the_frames_to_keep(tmp_path):
    kf = tmp_path / "keyframes"
    kf.mkdir()
    for name in ("00000.png", "00042.json", "frame_00007.png", "mapping.yaml", "notes.txt"):
        (kf / name).write_text("x")
    assert proc.keyframe_indices(kf) == [0, 7, 42]
    labels = tmp_path / "states.yaml"
    labels.write_text(yaml.safe_dump({"frame_00003": {"door": 0.0}, "frame_00011": {"door": 1.0}}))
    assert proc.label_indices(labels) == [3, 11]
    csv = tmp_path / "states.csv"
    csv.write_text("frame,object,value\nframe_00005,door,0.5\n9,door,1\n")
    assert proc.label_indices(csv) == [5, 9]
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no keyframe files"):
        proc.keyframe_indices(empty)


def test_stages_run_in_order_with_annotated_frames_kept(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(proc, "extract_frames", lambda src, ds, **kw: calls.append(("frames", kw)) or [1, 2, 3])
    monkeypatch.setattr(proc, "estimate_poses", lambda ds, **kw: calls.append(("poses", kw)) or
                        {"registered": 3, "total": 3})
    monkeypatch.setattr(proc, "propagate", lambda ds, kdir, **kw: calls.append(("masks", kdir.name)))
    monkeypatch.setattr(proc, "import_labels", lambda ds, f, **kw: calls.append(("labels", f.name)))
    monkeypatch.setattr(proc, "estimate_motions", lambda ds, **kw: calls.append(("motions", kw)) or {"measured": 1})
    kf = tmp_path / "kf"
    kf.mkdir()
    (kf / "00012.png").write_text("x")
    states = tmp_path / "states.yaml"
    states.write_text(yaml.safe_dump({"frame_00030": {"door": 1.0}}))
    proc.process("in.mp4", tmp_path / "ds", keyframes=kf, labels=states, target=50, matcher="sequential")
    assert [c[0] for c in calls] == ["frames", "masks", "poses", "labels", "motions"]
    assert calls[0][1]["keep"] == [12, 30] and calls[0][1]["target"] == 50
    assert calls[2][1]["matcher"] == "sequential"
    rep = json.loads((tmp_path / "ds" / "reports" / "process.json").read_text())
    assert rep["status"] == "ok" and list(rep["steps"]) == ["frames", "masks", "poses", "labels", "motions"]
    calls.clear()
    proc.process("in.mp4", tmp_path / "ds", keyframes=kf, labels=states, motions=False)
    assert [c[0] for c in calls] == ["frames", "masks", "poses", "labels"]



def test_bad_input_exits_non_zero(tmp_path):
    (tmp_path / "empty.mp4").write_bytes(b"")
    assert cli.main(["process", str(tmp_path / "empty.mp4"), str(tmp_path / "ds")]) == 2


@pytest.mark.slow
def test_process_video_end_to_end(tmp_path, capsys):
    """A simulated capture whose parts barely move (so no masks are needed), with its annotated states."""
    from interreal.synth import SynthConfig, write_capture

    cap = write_capture(SynthConfig(frames=24, width=320, height=240, articulation=0.02), tmp_path / "cap",
                        progress=False)
    labels = cap / "annotations" / "states.yaml"
    ds = tmp_path / "ds"
    assert cli.main(["process", str(cap / "video.mp4"), str(ds), "--target", "12", "--labels", str(labels)]) == 0
    out = capsys.readouterr().out
    assert "frames registered" in out and "process: done" in out
    kept = {int(p.stem[-5:]) for p in (ds / "images").glob("*.png")}
    wanted = set(proc.label_indices(labels))
    assert wanted <= kept and 12 <= len(kept) <= 12 + len(wanted)  # every labelled frame survives selection
    err = errors(ds, gt(cap))
    assert err["rot_err_deg_median"] < 0.5 and err["center_err_pct_median"] < 0.5, err
    for stage in ("frames", "poses", "process"):
        assert json.loads((ds / "reports" / f"{stage}.json").read_text())["status"] == "ok"
    assert (ds / "key_frame_value.yaml").exists()
    # an unchanged re-run reuses every finished step: the images are not rewritten, SfM reuses its features
    stamps = {p.name: p.stat().st_mtime_ns for p in (ds / "images").glob("*.png")}
    assert cli.main(["process", str(cap / "video.mp4"), str(ds), "--target", "12", "--labels", str(labels)]) == 0
    assert "up to date" in capsys.readouterr().out
    assert {p.name: p.stat().st_mtime_ns for p in (ds / "images").glob("*.png")} == stamps
    steps = json.loads((ds / "reports" / "poses.json").read_text())["steps"]
    assert steps.get("reuse", {}).get("reused") or steps["features"]["reused"], steps


def test_process_flags_come_from_the_stage_configs(tmp_path, monkeypatch):
    """`interreal process` takes the frames, masks and poses flags from `FramesConfig`, `MasksConfig` and
    `SfMConfig`, and hands each stage its own options."""
    import argparse

    from interreal.frames import FramesConfig
    from interreal.masks.config import MasksConfig
    from interreal.options import flag_fields, flag_name
    from interreal.sfm import SfMConfig

    p = argparse.ArgumentParser()
    proc.add_arguments(p)
    flags = {s for a in p._actions for s in a.option_strings}
    for cls in (FramesConfig, MasksConfig, SfMConfig):
        assert {flag_name(f) for f in flag_fields(cls)} <= flags, cls
    calls = {}
    monkeypatch.setattr(proc, "process", lambda src, ds, **kw: calls.update(kw) or {"stale": []})
    monkeypatch.setattr(proc, "read_report", lambda ds, stage: None)
    proc.main(p.parse_args(["in.mp4", str(tmp_path), "--every", "2", "--work-size", "0", "--no-fusion",
                            "--matcher", "exhaustive"]))
    assert calls["every"] == 2 and calls["long_side"] == 1600 and calls["target"] is None
    assert calls["work_long_side"] == 0 and calls["fusion"] is False and calls["preview"] == "both"
    assert calls["matcher"] == "exhaustive" and calls["sfm_long_side"] == 1000


def test_a_captures_prompts_travel_into_the_dataset(tmp_path, monkeypatch):
    """The `prompts.yaml` beside a capture's keyframes is imported with them (objects without a description only);
    `--prompts FILE` replaces; a name that is not an object is skipped with the closest one; a malformed file
    fails before any stage runs."""
    from interreal.dataset import read_prompts, write_mapping
    from interreal.errors import InputError

    calls = []
    monkeypatch.setattr(proc, "extract_frames", lambda src, ds, **kw: calls.append("frames") or [1])
    monkeypatch.setattr(proc, "estimate_poses", lambda ds, **kw: {"registered": 1, "total": 1})
    monkeypatch.setattr(proc, "propagate", lambda ds, kdir, **kw: write_mapping(ds, {0: "door", 1: "drawer"}))
    monkeypatch.setattr(proc, "import_labels", lambda ds, f, **kw: None)
    monkeypatch.setattr(proc, "estimate_motions", lambda ds, **kw: {"measured": 0})
    ann = tmp_path / "cap" / "annotations"
    (ann / "keyframes").mkdir(parents=True)
    (ann / "keyframes" / "00000.png").write_text("x")
    (ann / "states.yaml").write_text(yaml.safe_dump({"frame_00000": {"door": 0.0}}))
    (ann / "prompts.yaml").write_text(yaml.safe_dump({"door": "the thing you walk through", "drawr": "a drawer"}))
    ds = tmp_path / "ds"
    ds.mkdir()
    (ds / "prompts.yaml").write_text(yaml.safe_dump({"door": "typed in the app"}))
    proc.process("in.mp4", ds, keyframes=ann / "keyframes", labels=ann / "states.yaml")
    assert read_prompts(ds) == {"door": "typed in the app"}  # found beside the keyframes: fills only what is missing
    rep = json.loads((ds / "reports" / "process.json").read_text())
    step = rep["steps"]["prompts"]
    assert step["without"] == ["drawer"] and step["skipped"] == {"drawr": "drawer"}
    assert any(w["cause"] == "prompt-unknown-object" and "did you mean 'drawer'" in w["message"] for w in rep["warnings"])
    mine = tmp_path / "mine.yaml"
    mine.write_text(yaml.safe_dump({"door": "the front door", "drawer": "where the forks are"}))
    proc.process("in.mp4", ds, keyframes=ann / "keyframes", labels=ann / "states.yaml", prompts=mine)
    assert read_prompts(ds) == {"door": "the front door", "drawer": "where the forks are"}
    assert "prompts: 2 description(s)" in proc.prompts_line(
        json.loads((ds / "reports" / "process.json").read_text())["steps"]["prompts"])
    calls.clear()
    mine.write_text("door: [not, text]\n")
    with pytest.raises(InputError, match="description of 'door'"):
        proc.process("in.mp4", ds, keyframes=ann / "keyframes", prompts=mine)
    assert calls == []


def test_validate_names_the_objects_text_finds_by_name_alone(tmp_path):
    from conftest import make_tiny_dataset

    from interreal.dataset import validate, write_prompts

    ds = make_tiny_dataset(tmp_path / "ds", n_objects=2)
    names = validate(ds).summary["objects"]
    write_prompts(ds, {names[0]: "what keeps food cold"})
    res = validate(ds)
    assert res.ok and res.summary["described"] == 1
    assert any(f"no description of {names[1]!r}" in w and "by name alone" in w for w in res.warnings), res.warnings
