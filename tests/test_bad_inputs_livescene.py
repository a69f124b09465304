"""Bad inputs to `livescene train / render / eval / ground`: each is refused with one clear line that names the
problem (exit code, no traceback), or gives a correct result with a warning - never a plausible-looking output.
Plus a kill test: `livescene train` SIGKILLed twice, `--resume` finishes, the final checkpoint loads.

Everything runs the real CLI in-process (`livescene.cli.main`) on a 10-frame toy dataset and one tiny run trained
once per module (a few seconds)."""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_livescene_toy import toy_cameras, toy_dataset  # noqa: E402

from interreal.conventions import LABELS_FILE  # noqa: E402
from livescene.cli import main  # noqa: E402

TRAIN_FLAGS = ["--preset", "tiny", "--steps", "2", "--device", "cpu", "--threads", "1", "--no-progress"]


@pytest.fixture(scope="module")
def base(tmp_path_factory, one_thread):
    """(root, dataset, run): a 10-frame toy dataset and a tiny run of 10 steps with checkpoints at 5 and 10."""
    from livescene.config import load_preset
    from livescene.trainer import train

    root = tmp_path_factory.mktemp("bad_inputs")
    ds = toy_dataset(root / "ds", n_frames=10, size=(16, 12))
    cfg = load_preset("tiny")
    cfg.steps, cfg.eval_every, cfg.ckpt_every, cfg.log_every, cfg.final_eval_frames = 10, 0, 5, 5, 1
    train(ds, root / "run", cfg, device="cpu", show_progress=False)
    return root, ds, root / "run"


def run_cli(capsys, args: list[str]) -> tuple[int, str, str]:
    capsys.readouterr()
    rc = main([str(a) for a in args])
    out, err = capsys.readouterr()
    assert "Traceback" not in err + out
    return rc, out, err


def refused(capsys, args: list[str], *needles: str, rc: int = 2) -> str:
    """The command exits with `rc`, without a traceback, and its error line names every needle."""
    code, out, err = run_cli(capsys, args)
    assert code == rc, (code, out, err)
    assert "error:" in err, err
    for needle in needles:
        assert needle.lower() in err.lower(), (needle, err)
    return err


# ---------------------------------------------------------------------------------------------------------------
# Broken datasets: train, render, eval and ground all refuse them with `interreal validate`'s problems
# ---------------------------------------------------------------------------------------------------------------
def _yaml(path: Path, value) -> None:
    path.write_text(yaml.safe_dump(value))


def _edit_transforms(ds: Path, fn) -> None:
    meta = json.loads((ds / "transforms.json").read_text())
    fn(meta)
    (ds / "transforms.json").write_text(json.dumps(meta))


def _first_label_key(ds: Path) -> str:
    return next(iter(yaml.safe_load((ds / LABELS_FILE).read_text())))


def _set_label(ds: Path, value) -> None:
    labels = yaml.safe_load((ds / LABELS_FILE).read_text())
    labels[_first_label_key(ds)]["door"] = value
    _yaml(ds / LABELS_FILE, labels)


def _mask_paths(ds: Path) -> list[Path]:
    return sorted((ds / "masks").glob("*.npy"))


def _nan_pose(ds: Path) -> None:
    def fn(meta):
        meta["frames"][3]["transform_matrix"][0][3] = float("nan")
    _edit_transforms(ds, fn)


def _float_mask(ds: Path) -> None:
    m = np.load(_mask_paths(ds)[0])
    np.save(_mask_paths(ds)[0], np.full(m.shape, 0.5, np.float32))


def _mask_channels(ds: Path) -> None:
    m = np.load(_mask_paths(ds)[0])
    np.save(_mask_paths(ds)[0], np.concatenate([m, np.zeros_like(m[..., :1])], -1))


def _two_d_mask(ds: Path) -> None:
    m = np.load(_mask_paths(ds)[0])
    np.save(_mask_paths(ds)[0], m[..., 0])


def _stage_running(ds: Path) -> None:
    (ds / "reports").mkdir(exist_ok=True)
    (ds / "reports" / "masks.json").write_text(json.dumps({"stage": "masks", "status": "running"}))


def _truncate_image(ds: Path) -> None:
    img = sorted((ds / "images").glob("*.png"))[2]
    img.write_bytes(img.read_bytes()[:40])


def _nan_box(ds: Path) -> None:
    def fn(meta):
        meta["aabb"] = [[float("nan"), 0, 0], [1, 1, 1]]
    _edit_transforms(ds, fn)


def _two_by_two(ds: Path) -> None:
    def fn(meta):
        meta["frames"][1]["transform_matrix"] = [[1, 0], [0, 1]]
    _edit_transforms(ds, fn)


BROKEN_DATASETS = {
    "label-5.0": (lambda ds: _set_label(ds, 5.0), ["label-bad-value", "5.0"]),
    "label-not-a-number": (lambda ds: _set_label(ds, "half"), ["label-bad-value", "half"]),
    "label-nan": (lambda ds: _set_label(ds, float("nan")), ["label-bad-value"]),
    "pose-nan": (_nan_pose, ["bad-pose", "non-finite"]),
    "pose-2x2": (_two_by_two, ["bad-pose"]),
    "mask-float-0.5": (_float_mask, ["bad-mask"]),
    "mask-extra-channel": (_mask_channels, ["mask-channels"]),
    "mask-2d": (_two_d_mask, ["bad-mask"]),
    "one-mask-missing": (lambda ds: _mask_paths(ds)[4].unlink(), ["missing-mask"]),
    "duplicate-names": (lambda ds: _yaml(ds / "mapping.yaml", {0: "door", 1: "door"}), ["names used twice"]),
    "ids-0-5": (lambda ds: _yaml(ds / "mapping.yaml", {0: "door", 5: "drawer"}), ["not contiguous"]),
    "stage-running": (_stage_running, ["stage-incomplete", "running"]),
    "image-missing": (lambda ds: sorted((ds / "images").glob("*.png"))[1].unlink(), ["missing-image"]),
    "image-truncated": (_truncate_image, ["bad-image"]),
    "transforms-garbage": (lambda ds: (ds / "transforms.json").write_text("{not json"), ["bad-json"]),
    "mapping-broken-yaml": (lambda ds: (ds / "mapping.yaml").write_text("0: [door\n"), ["bad-yaml"]),
    "labels-missing": (lambda ds: (ds / LABELS_FILE).unlink(), ["no-labels"]),
    "scene-box-nan": (_nan_box, ["box", "not a finite box"]),
}


@pytest.fixture
def broken(base, tmp_path, request):
    root, ds, run = base
    copy = tmp_path / "ds"
    shutil.copytree(ds, copy)
    mutate, needles = BROKEN_DATASETS[request.param]
    mutate(copy)
    return copy, needles


@pytest.mark.parametrize("broken", sorted(BROKEN_DATASETS), indirect=True)
def test_train_refuses_a_broken_dataset(broken, tmp_path, capsys):
    ds, needles = broken
    refused(capsys, ["train", ds, "--out", tmp_path / "run", *TRAIN_FLAGS], *needles)
    assert not (tmp_path / "run").exists()  # refused before anything was written


@pytest.mark.parametrize("broken", ["label-5.0", "pose-nan", "mask-float-0.5", "stage-running"], indirect=True)
def test_render_and_eval_refuse_a_broken_dataset(broken, base, tmp_path, capsys):
    ds, needles = broken
    run = base[2]
    refused(capsys, ["render", run, "--dataset", ds, "--frames", "0", "--out", tmp_path / "r", "--device", "cpu"],
            *needles)
    assert not (tmp_path / "r").exists()
    refused(capsys, ["eval", run, "--dataset", ds, "--out", tmp_path / "e.json", "--device", "cpu"], *needles)
    assert not (tmp_path / "e.json").exists()


def test_ground_refuses_a_run_whose_dataset_is_broken(base, tmp_path, capsys):
    pytest.importorskip("sentence_transformers")
    root, ds, run = base
    copy_ds, copy_run = tmp_path / "ds", tmp_path / "run"
    shutil.copytree(ds, copy_ds)
    shutil.copytree(run, copy_run)
    _set_label(copy_ds, 5.0)
    cfg = yaml.safe_load((copy_run / "config.yaml").read_text())
    _yaml(copy_run / "config.yaml", {**cfg, "dataset": str(copy_ds)})
    refused(capsys, ["ground", copy_run, "the door"], "label-bad-value")


def test_train_refuses_a_missing_dataset(tmp_path, capsys):
    refused(capsys, ["train", tmp_path / "nope", "--out", tmp_path / "run", *TRAIN_FLAGS], "not a folder")


# ---------------------------------------------------------------------------------------------------------------
# Settings: named before training, never "training diverged"
# ---------------------------------------------------------------------------------------------------------------
BAD_SETTINGS = {
    "features-0.5": (["--set", "model.features=0.5"], ["model.features", "whole number"]),
    "features-0": (["--set", "model.features=0"], ["model.features", ">= 1"]),
    "steps-negative": (["--set", "steps=-5"], ["steps", ">= 1"]),
    "steps-flag-negative": (["--steps", "-5"], ["--steps -5"]),
    "batch-zero": (["--set", "batch_rays=0"], ["batch_rays"]),
    "lr-nan": (["--set", "lr=nan"], ["lr", "finite"]),
    "lr-text": (["--set", "lr=fast"], ["lr", "fast"]),
    "lr-negative": (["--set", "lr=-0.1"], ["lr", "> 0"]),
    "background-choice": (["--set", "model.background=blue"], ["model.background", "white"]),
    "bool-garbage": (["--set", "model.proposal_k=maybe"], ["model.proposal_k", "true or false"]),
    "unknown-key": (["--set", "modle.features=3"], ["unknown setting", "did you mean 'model'"]),
    "group-as-value": (["--set", "model=5"], ["model", "group of settings"]),
    "no-equals": (["--set", "model.features"], ["KEY=VALUE"]),
    "empty-key": (["--set", "=3"], ["not a setting name"]),
    "scene-box-3": (["--set", "scene_box=1,2,3"], ["scene_box", "6 numbers"]),
    "scene-box-inverted": (["--set", "scene_box=1,1,1,0,0,0"], ["scene_box", "below"]),
    "proposal-levels": (["--set", "sampler.proposal_samples=[8]"], ["proposal_samples"]),
    "sh-degree": (["--set", "model.sh_degree=9"], ["model.sh_degree", "[1, 4]"]),
    "auto-size-1": (["--set", "model.k_resolution=1"], ["model.k_resolution", "at least 2"]),
    "loss-negative": (["--set", "loss.rgb=-1"], ["loss.rgb"]),
    "log-every-0": (["--set", "log_every=0"], ["log_every"]),
    "seed-negative": (["--seed", "-3"], ["seed"]),
    "preset-missing": (["--preset", "nosuch"], ["preset 'nosuch' not found"]),
    "max-minutes-negative": (["--max-minutes", "-1"], ["--max-minutes"]),
    "device-unknown": (["--device", "tpu"], ["unknown device"]),
}


@pytest.mark.parametrize("case", sorted(BAD_SETTINGS))
def test_train_names_a_bad_setting(case, base, tmp_path, capsys):
    extra, needles = BAD_SETTINGS[case]
    flags = TRAIN_FLAGS if "steps=-5" not in extra else [f for f in TRAIN_FLAGS if f not in ("--steps", "2")]
    refused(capsys, ["train", base[1], "--out", tmp_path / "run", *flags, *extra], *needles)
    assert not (tmp_path / "run").exists()


PRESET_FILES = {
    "broken-yaml": ("model: [features\n", ["not readable YAML"]),
    "not-a-mapping": ("- 1\n- 2\n", ["expected settings"]),
    "unknown-key": ("stepz: 3\n", ["unknown setting 'stepz'", "did you mean 'steps'"]),
    "features-0.5": ("model:\n  features: 0.5\n", ["model.features", "whole number"]),
    "group-not-a-mapping": ("sampler: 3\n", ["sampler", "group of settings"]),
}


@pytest.mark.parametrize("case", sorted(PRESET_FILES))
def test_train_names_a_bad_preset_file(case, base, tmp_path, capsys):
    text, needles = PRESET_FILES[case]
    preset = tmp_path / "mine.yaml"
    preset.write_text(text)
    args = ["train", base[1], "--out", tmp_path / "run", *TRAIN_FLAGS]
    args[args.index("tiny")] = str(preset)
    refused(capsys, args, *needles)


def test_bad_settings_never_blame_the_optimiser(base, tmp_path, capsys):
    """The issue's case: model.features=0.5 used to become 0 features and a 'training diverged' error."""
    err = refused(capsys, ["train", base[1], "--out", tmp_path / "run", *TRAIN_FLAGS, "--set", "model.features=0.5"])
    assert "diverged" not in err and "learning rate" not in err


# ---------------------------------------------------------------------------------------------------------------
# Runs and checkpoints
# ---------------------------------------------------------------------------------------------------------------
@pytest.fixture
def run_copy(base, tmp_path):
    copy = tmp_path / "run"
    shutil.copytree(base[2], copy)
    return copy


def _garbage_all_checkpoints(run: Path) -> None:
    for p in [run / "latest.pt", *(run / "checkpoints").glob("*.pt")]:
        p.write_bytes(b"not a checkpoint at all")


def _nan_weights_everywhere(run: Path) -> None:
    for p in [run / "latest.pt", *(run / "checkpoints").glob("*.pt")]:
        ckpt = torch.load(p, map_location="cpu", weights_only=False)
        key = next(k for k, t in ckpt["model"].items() if t.is_floating_point())
        ckpt["model"][key] = ckpt["model"][key] * float("nan")
        torch.save(ckpt, p)


def _not_a_checkpoint_dict(run: Path) -> None:
    for p in [run / "latest.pt", *(run / "checkpoints").glob("*.pt")]:
        torch.save({"hello": 1}, p)


BROKEN_RUNS = {
    "all-checkpoints-garbage": (_garbage_all_checkpoints, ["no intact checkpoint", "unreadable"]),
    "nan-weights": (_nan_weights_everywhere, ["non-finite weights"]),
    "not-a-checkpoint": (_not_a_checkpoint_dict, ["not a livescene checkpoint"]),
    "no-checkpoints": (lambda run: [p.unlink() for p in [run / "latest.pt", *(run / "checkpoints").glob("*.pt")]],
                       ["holds no checkpoint"]),
    "dataset-gone": (lambda run: _point_at(run, run.parent / "moved"), ["is gone", "--dataset"]),
}


def _point_at(run: Path, dataset: Path) -> None:
    for p in [run / "latest.pt", *(run / "checkpoints").glob("*.pt")]:
        ckpt = torch.load(p, map_location="cpu", weights_only=False)
        ckpt["meta"]["dataset"] = str(dataset)
        torch.save(ckpt, p)


@pytest.mark.parametrize("case", sorted(BROKEN_RUNS))
def test_render_eval_resume_refuse_a_broken_run(case, base, run_copy, tmp_path, capsys):
    mutate, needles = BROKEN_RUNS[case]
    mutate(run_copy)
    refused(capsys, ["render", run_copy, "--frames", "0", "--out", tmp_path / "r", "--device", "cpu"], *needles)
    refused(capsys, ["eval", run_copy, "--out", tmp_path / "e.json", "--device", "cpu"], *needles)
    if case != "dataset-gone":
        refused(capsys, ["train", base[1], "--out", run_copy, "--resume", "--device", "cpu", "--no-progress"],
                needles[0])


def test_render_of_a_folder_that_is_not_a_run(tmp_path, capsys):
    refused(capsys, ["render", tmp_path / "nope", "--device", "cpu"], "not a run folder")


def test_render_with_a_moved_dataset_works_through_dataset_flag(base, run_copy, tmp_path, capsys):
    moved = tmp_path / "moved"
    shutil.copytree(base[1], moved)
    _point_at(run_copy, tmp_path / "gone")
    code, _, err = run_cli(capsys, ["render", run_copy, "--dataset", moved, "--frames", "0", "--out", tmp_path / "r",
                                    "--device", "cpu"])
    assert code == 0 and len(list((tmp_path / "r").glob("*.png"))) == 1


def test_render_refuses_another_dataset_for_the_run(base, tmp_path, capsys):
    other = toy_dataset(tmp_path / "other", n_frames=10, size=(16, 12), n_objects=2)
    refused(capsys, ["render", base[2], "--dataset", other, "--frames", "0", "--device", "cpu"],
            "not the run's dataset")


def test_truncated_latest_falls_back_to_the_newest_intact_checkpoint(base, run_copy, tmp_path, capsys):
    latest = run_copy / "latest.pt"
    latest.write_bytes(latest.read_bytes()[: latest.stat().st_size // 3])
    code, _, err = run_cli(capsys, ["render", run_copy, "--frames", "0", "--out", tmp_path / "r", "--device", "cpu"])
    assert code == 0 and "warning" in err and "step_0000010.pt" in err and "newest intact" in err
    # resume from it (more steps): the run continues from step 10 and writes a new intact latest.pt
    code, out, err = run_cli(capsys, ["train", base[1], "--out", run_copy, "--resume", "--steps", "12",
                                      "--device", "cpu", "--threads", "1", "--no-progress"])
    assert code == 0 and "step_0000010.pt" in err and "12 steps" in out
    from livescene.trainer import load_run

    assert load_run(run_copy, device="cpu").step == 12


def test_train_into_an_existing_run_or_resume_nothing(base, tmp_path, capsys):
    refused(capsys, ["train", base[1], "--out", base[2], *TRAIN_FLAGS], "already holds a run", "--resume")
    (tmp_path / "empty").mkdir()
    refused(capsys, ["train", base[1], "--out", tmp_path / "empty", "--resume", "--device", "cpu", "--no-progress"],
            "nothing to resume")


def test_resume_of_a_finished_run_changes_nothing(base, run_copy, capsys):
    (run_copy / ".latest.pt.x1y2.tmp").write_bytes(b"half a checkpoint")  # left by a kill
    before = {p: p.read_bytes() for p in run_copy.rglob("*") if p.is_file() and not p.name.endswith(".tmp")}
    code, out, _ = run_cli(capsys, ["train", base[1], "--out", run_copy, "--resume", "--device", "cpu",
                                    "--no-progress"])
    assert code == 0 and "already finished" in out
    after = {p: p.read_bytes() for p in run_copy.rglob("*") if p.is_file()}
    after.pop(run_copy / ".lock", None)
    assert after == {k: v for k, v in before.items() if k.name != ".lock"}  # the .tmp is gone, the rest untouched
    report = json.loads((run_copy / "reports" / "train.json").read_text())
    assert report["status"] == "ok" and report["figures"]["train_psnr"] is not None


def test_no_held_out_frame_is_said_plainly(tmp_path, capsys):
    ds = toy_dataset(tmp_path / "ds", n_frames=4, size=(16, 12), label_every=1)
    code, out, _ = run_cli(capsys, ["train", ds, "--out", tmp_path / "run", *TRAIN_FLAGS])
    assert code == 0
    assert "held-out PSNR" not in out and "no frame is held out" in out and "4 frames it trained on" in out
    figures = json.loads((tmp_path / "run" / "reports" / "train.json").read_text())["figures"]
    assert figures["heldout_psnr"] is None and figures["eval_on"] == "training"


# ---------------------------------------------------------------------------------------------------------------
# Render: states and cameras that would make plausible garbage
# ---------------------------------------------------------------------------------------------------------------
BAD_RENDER = {
    "state-nan": (["--state", "door=nan"], ["outside [0, 1]", "door"]),
    "state-1.5": (["--state", "door=1.5"], ["outside [0, 1]", "1.5"]),
    "state-negative": (["--state", "door=-0.2"], ["outside [0, 1]"]),
    "state-text": (["--state", "door=open"], ["not a number"]),
    "state-no-equals": (["--state", "door"], ["name=value"]),
    "state-unknown-object": (["--state", "fridge=0.5"], ["unknown object 'fridge'"]),
    "sweep-out-of-range": (["--sweep", "door=0:1.5:3"], ["outside [0, 1]"]),
    "sweep-malformed": (["--sweep", "door=0:1"], ["--sweep expects"]),
    "sweep-count-0": (["--sweep", "door=0:1:0"], ["count 0"]),
    "frames-out-of-range": (["--frames", "99"], ["position 99", "not a frame"]),
    "frames-garbage": (["--frames", "a,b"], ["frame positions"]),
    "scale-zero": (["--scale", "0"], ["--scale"]),
    "time-nan": (["--time", "nan"], ["--time"]),
    "cameras-unknown": (["--cameras", "nowhere"], ["--cameras 'nowhere'"]),
    "count-zero": (["--cameras", "path", "--count", "0"], ["--count"]),
}


@pytest.mark.parametrize("case", sorted(BAD_RENDER))
def test_render_refuses_bad_options(case, base, tmp_path, capsys):
    extra, needles = BAD_RENDER[case]
    refused(capsys, ["render", base[2], "--out", tmp_path / "r", "--device", "cpu", *extra], *needles)
    assert not list((tmp_path / "r").glob("*.png")) if (tmp_path / "r").exists() else True


def _cams(frames) -> dict:
    return {"frames": frames}


EYE = np.eye(4).tolist()
NAN_CAM = np.eye(4)
NAN_CAM[0, 3] = np.nan
BAD_CAMERA_FILES = {
    "matrix-2x2": (_cams([{"transform_matrix": [[1, 0], [0, 1]]}]), ["shape 2x2"]),
    "matrix-nan": (_cams([{"transform_matrix": NAN_CAM.tolist()}]), ["non-finite"]),
    "matrix-not-rotation": (_cams([{"transform_matrix": (2 * np.eye(4)).tolist()}]), ["not a rotation"]),
    "matrix-strings": (_cams([{"transform_matrix": "identity"}]), ["camera matrix"]),
    "no-matrix": (_cams([{"states": {"door": 0.5}}]), ["malformed", "transform_matrix"]),
    "state-1.5": (_cams([{"transform_matrix": EYE, "states": {"door": 1.5}}]), ["outside [0, 1]"]),
    "state-nan": (_cams([{"transform_matrix": EYE, "states": {"door": float("nan")}}]), ["outside [0, 1]"]),
    "states-not-a-mapping": (_cams([{"transform_matrix": EYE, "states": [0.5]}]), ["'states' must be"]),
    "no-cameras": (_cams([]), ["no cameras"]),
    "intrinsics-nan": ({"intrinsics": {"w": 16, "h": 12, "fl_x": float("nan"), "fl_y": 10, "cx": 8, "cy": 6},
                        "frames": [{"transform_matrix": EYE}]}, ["intrinsics"]),
    "fov-zero": ({"camera_path": [{"camera_to_world": np.eye(4).ravel().tolist(), "fov": 0}]}, ["fov"]),
    "not-json": (None, ["not a readable JSON"]),
    "top-level-list": ([1, 2], ["JSON object"]),
}


@pytest.mark.parametrize("case", sorted(BAD_CAMERA_FILES))
def test_render_refuses_bad_camera_files(case, base, tmp_path, capsys):
    content, needles = BAD_CAMERA_FILES[case]
    cams = tmp_path / "cams.json"
    cams.write_text("{frames: oops" if content is None else json.dumps(content))
    refused(capsys, ["render", base[2], "--cameras", cams, "--out", tmp_path / "r", "--device", "cpu"], *needles)
    assert not (tmp_path / "r").exists()


# ---------------------------------------------------------------------------------------------------------------
# Eval: the truth must be this dataset's capture
# ---------------------------------------------------------------------------------------------------------------
def fake_capture(folder: Path, poses: np.ndarray, size=(16, 12), n_frames: int | None = None) -> Path:
    """The gt/ files `interreal.synth.Capture.open` reads, for the toy scene's cameras (no video needed)."""
    from interreal.synth import SynthConfig

    n = len(poses) if n_frames is None else n_frames
    gt = folder / "gt"
    gt.mkdir(parents=True)
    w, h = size
    intr = {"w": w, "h": h, "fl_x": 0.9 * w, "fl_y": 0.9 * w, "cx": w / 2, "cy": h / 2, "camera_model": "PINHOLE"}
    (gt / "meta.json").write_text(json.dumps({"config": SynthConfig().to_dict()}))
    (gt / "cameras.json").write_text(json.dumps({"intrinsics": intr, "frames": [
        {"transform_matrix": poses[i % len(poses)].tolist()} for i in range(n)]}))
    (gt / "states.json").write_text(json.dumps({"objects": ["door"], "values": [[0.5]] * n}))
    return folder


def _toy_poses(n: int = 30) -> np.ndarray:
    return toy_cameras(10).repeat(3, axis=0)[:n]  # dataset frame i has source index 3 i


def _other_trajectory() -> np.ndarray:
    from test_livescene_toy import look_at_gl

    return np.stack([look_at_gl((2 * np.cos(a), 2 * np.sin(a), 0.3 + a), (0, 0, 1)) for a in np.linspace(0, 6, 30)])


BAD_TRUTH = {
    "too-few-frames": (lambda d: fake_capture(d, _toy_poses(), n_frames=5), ["has 5 frames"]),
    "other-aspect": (lambda d: fake_capture(d, _toy_poses(), size=(16, 16)), ["aspect ratio"]),
    "other-cameras": (lambda d: fake_capture(d, _other_trajectory()), ["cameras do not match"]),
    "not-a-capture": (lambda d: d.mkdir(), ["states.json not found"]),
    "missing-folder": (lambda d: None, ["not a folder"]),
}


@pytest.mark.parametrize("case", sorted(BAD_TRUTH))
def test_eval_refuses_the_truth_of_another_capture(case, base, tmp_path, capsys):
    make, needles = BAD_TRUTH[case]
    gt = tmp_path / "cap"
    make(gt)
    refused(capsys, ["eval", base[2], "--gt", gt, "--out", tmp_path / "e.json", "--device", "cpu"], *needles)
    assert not (tmp_path / "e.json").exists()


def test_eval_accepts_its_own_capture(base):
    """The camera check passes the capture the dataset was made from (so the refusals above are not luck)."""
    from interreal.synth.evaltruth import check_same_capture
    from livescene.trainer import load_run
    from interreal.synth.capture import Capture

    cap = Capture.open(fake_capture(base[0] / "own_cap", _toy_poses()))
    check_same_capture(cap, load_run(base[2], device="cpu").views, base[0] / "own_cap")


# ---------------------------------------------------------------------------------------------------------------
# Disk full, read-only: one line, partial outputs removed
# ---------------------------------------------------------------------------------------------------------------
def _failing_writes(monkeypatch, code: int, after: int = 0, suffix: str = ""):
    """interreal.atomic.write_bytes raising OSError(code) for paths ending in `suffix`, after `after` such writes."""
    import interreal.atomic as atomic

    real = atomic.write_bytes
    calls = {"n": 0}

    def fake(path, data):
        if str(path).endswith(suffix):
            calls["n"] += 1
            if calls["n"] > after:
                raise OSError(code, os.strerror(code), str(path))
        return real(path, data)

    monkeypatch.setattr(atomic, "write_bytes", fake)


@pytest.mark.parametrize("code,needle", [(errno.ENOSPC, "No space left"), (errno.EACCES, "Permission denied"),
                                         (errno.EROFS, "Read-only")])
def test_train_write_errors_are_one_line_and_leave_no_half_run(base, tmp_path, capsys, monkeypatch, code, needle):
    _failing_writes(monkeypatch, code, suffix=".pt")
    refused(capsys, ["train", base[1], "--out", tmp_path / "run", *TRAIN_FLAGS], "cannot write", needle, ".pt")
    assert not (tmp_path / "run").exists()


def test_render_disk_full_removes_its_partial_images(base, tmp_path, capsys, monkeypatch):
    _failing_writes(monkeypatch, errno.ENOSPC, after=2, suffix=".png")
    refused(capsys, ["render", base[2], "--frames", "0,1,2", "--out", tmp_path / "r", "--device", "cpu"],
            "cannot write", "No space left")
    assert not list((tmp_path / "r").glob("*.png"))


def test_eval_output_into_a_folder(base, tmp_path, capsys):
    (tmp_path / "e.json").mkdir()
    refused(capsys, ["eval", base[2], "--out", tmp_path / "e.json", "--device", "cpu", "--max-frames", "1"],
            "cannot write")


# ---------------------------------------------------------------------------------------------------------------
# Kill test: SIGKILL twice mid-training, resume finishes, the final checkpoint loads, metrics have no duplicates
# ---------------------------------------------------------------------------------------------------------------
def _last_step(metrics: Path) -> int:
    try:
        lines = metrics.read_text().splitlines()
    except FileNotFoundError:
        return -1
    steps = [json.loads(x)["step"] for x in lines if x.strip().endswith("}")]
    return max(steps, default=-1)


def test_kill_and_resume(tmp_path):
    from livescene.trainer import load_run

    ds = toy_dataset(tmp_path / "ds", n_frames=10, size=(16, 12))
    run = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "livescene", "train", str(ds), "--out", str(run), "--preset", "tiny", "--steps", "40",
           "--seed", "3", "--device", "cpu", "--threads", "1", "--no-progress", "--set", "ckpt_every=10",
           "--set", "log_every=2", "--set", "eval_every=0", "--set", "final_eval_frames=1"]
    for kill_after in (13, 27):  # between checkpoints: the resume trains those steps again
        proc = subprocess.Popen(cmd + (["--resume"] if run.exists() and (run / "latest.pt").exists() else []),
                                env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        deadline = time.time() + 60
        while _last_step(run / "metrics.jsonl") < kill_after and proc.poll() is None and time.time() < deadline:
            time.sleep(0.02)
        assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    done = subprocess.run(cmd + ["--resume"], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "Traceback" not in done.stderr
    loaded = load_run(run, device="cpu")
    assert loaded.step == 40
    records = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    train_steps = [r["step"] for r in records if r["type"] == "train"]
    assert train_steps == sorted(set(train_steps)) and train_steps[-1] == 40  # no duplicates after the resumes
    assert sum(1 for r in records if r.get("final")) == 1
    report = json.loads((run / "reports" / "train.json").read_text())
    assert report["status"] == "ok" and report["figures"]["train_psnr"] is not None
    assert not list(run.rglob("*.tmp"))


@pytest.mark.parametrize("sig,code,word", [(signal.SIGTERM, 143, "terminated (SIGTERM)"),
                                           (signal.SIGINT, 130, "interrupted (Ctrl-C)")])
def test_sigterm_and_ctrl_c_save_the_steps_and_say_where_the_run_stands(tmp_path, sig, code, word):
    """SIGTERM (a scheduler, `timeout`, `docker stop`) killed training at once: no message, the report left
    "running", up to `ckpt_every` steps lost. Now both it and Ctrl-C stop after the current step with a checkpoint
    there, the report says "interrupted" and how to continue, `--resume` says where it resumes, and `render` of the
    interrupted run says it is one."""
    ds = toy_dataset(tmp_path / "ds", n_frames=10, size=(16, 12))
    run = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "livescene", "train", str(ds), "--out", str(run), "--preset", "tiny", "--steps",
           "60", "--seed", "3", "--device", "cpu", "--threads", "1", "--no-progress", "--set", "ckpt_every=1000",
           "--set", "log_every=2", "--set", "eval_every=0", "--set", "final_eval_frames=1"]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while _last_step(run / "metrics.jsonl") < 7 and proc.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, proc.stderr.read()[-2000:]
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == code, err[-2000:]
    assert "Traceback" not in err and word in err and "--resume" in err, err[-2000:]
    report = json.loads((run / "reports" / "train.json").read_text())
    assert report["status"] == "interrupted" and word in report["error"], report
    saved = max(int(p.stem.split("_")[1]) for p in (run / "checkpoints").glob("step_*.pt"))
    assert 7 <= saved < 60 and f"at step {saved} of 60: checkpoint at step {saved} saved" in report["error"]
    more = subprocess.run(cmd + ["--resume"], env=env, capture_output=True, text=True, timeout=300)
    assert more.returncode == 0 and f"resuming from step {saved} of 60 (the run was interrupted)" in more.stdout
    report["status"] = "interrupted"  # as if this run, too, had been stopped: `render` says so
    (run / "reports" / "train.json").write_text(json.dumps(report))
    shown = subprocess.run([sys.executable, "-m", "livescene", "render", str(run), "--device", "cpu", "--frames",
                            "0", "--out", str(tmp_path / "r")], env=env, capture_output=True, text=True, timeout=120)
    assert "training was interrupted (its last checkpoint, step" in shown.stderr, shown.stderr[-2000:]
