"""Per-frame appearance (`model.appearance`, `livescene.appearance`): off changes nothing, identity changes nothing,
known per-frame exposure gains are recovered and the neutral render is the unscaled scene, checkpoints round-trip
(old ones load), and `livescene eval` reports held-out PSNR neutral and with interpolated codes."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_livescene_toy import ToyScene, toy_dataset  # noqa: E402

from interreal.atomic import write_image  # noqa: E402
from interreal.dataset import load_dataset  # noqa: E402
from livescene.appearance import apply_codes, apply_to_image, interpolate_codes  # noqa: E402
from livescene.config import ModelConfig, apply_overrides, check_config, load_preset  # noqa: E402
from livescene.data import load_frame  # noqa: E402
from livescene.errors import ConfigError, LiveSceneError  # noqa: E402
from livescene.field import LiveSceneModel  # noqa: E402
from livescene.losses import psnr  # noqa: E402
from livescene.render import render_view  # noqa: E402
from livescene.run import Run, checkpoint_config, load_run  # noqa: E402
from livescene.trainer import Trainer, train  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")

BASE = 0.8  # the "unscaled" scene: the toy render x 0.8, so no gain below brings a pixel past 1 (no clipping)
SWING = 0.2  # log-gain amplitude: gains 0.82 .. 1.22, geometric mean 1 over the video


def true_gains(times: np.ndarray) -> np.ndarray:
    """A smooth auto-exposure swing through the video (geometric mean 1, as the identity penalty makes neutral)."""
    return np.exp(SWING * np.sin(2 * np.pi * np.asarray(times, np.float64)))


def exposed_dataset(root: Path, n_frames: int = 24, size: tuple[int, int] = (32, 24)) -> tuple[Path, np.ndarray]:
    """The toy room, each frame's colours x BASE x its own gain; (dataset, gains in dataset frame order)."""
    ds = toy_dataset(root, n_frames=n_frames, size=size)
    data = load_dataset(ds)
    idx = np.array([f.index for f in data.frames], np.float64)
    gains = true_gains(idx / idx.max())
    for f, g in zip(data.frames, gains):
        img = data.load_image(f).astype(np.float64) / 255.0
        write_image(ds / f.file_path, np.clip(np.round(img * BASE * g * 255), 0, 255).astype(np.uint8))
    return ds, gains


def tiny_cfg(appearance: str, steps: int):
    cfg = load_preset("tiny")
    cfg.steps, cfg.eval_every, cfg.ckpt_every, cfg.log_every = steps, 0, 0, 20
    cfg.final_eval_frames, cfg.final_eval_max_side = 1, 32
    cfg.model.appearance = appearance
    return cfg


# ----------------------------------------------------------------------------------------------------------------
# The transform and the interpolation, exactly
# ----------------------------------------------------------------------------------------------------------------
def test_identity_codes_change_nothing_and_modes_are_what_they_say():
    rgb = torch.rand(50, 3, generator=torch.Generator().manual_seed(0))
    for mode, size in (("gain", 3), ("affine", 12)):
        assert torch.equal(apply_codes(rgb, torch.zeros(50, size), mode), rgb)  # bit-identical, not close
    out = apply_codes(rgb, torch.tensor([np.log(2.0), 0.0, np.log(0.5)]), "gain")
    assert torch.allclose(out, rgb * torch.tensor([2.0, 1.0, 0.5]))
    mix = torch.zeros(12)
    mix[1], mix[9] = 0.5, 0.1  # red takes half of green, and a bias
    assert torch.allclose(apply_codes(rgb, mix, "affine")[:, 0], rgb[:, 0] + 0.5 * rgb[:, 1] + 0.1)
    img = np.full((2, 2, 3), 0.8, np.float32)
    assert apply_to_image(img, [np.log(2.0)] * 3, "gain").max() == 1.0  # clipped like renders


def test_held_out_codes_interpolate_in_time_from_the_training_frames():
    times = np.array([0.0, 0.1, 0.2, 0.3, 0.5, 1.0])
    codes = np.array([[1.0], [9.0], [3.0], [9.0], [5.0], [9.0]])  # 9 = never trained (must not be read)
    out = interpolate_codes(codes, times, trained=[0, 2, 4])
    # between the trained neighbours in time; the nearest one's past the end
    assert np.allclose(out[:, 0], [1.0, 2.0, 3.0, 3.0 + 2.0 / 3.0, 5.0, 5.0])
    assert np.allclose(interpolate_codes(codes, times, trained=[]), 0.0)


def test_settings_are_checked_and_sized_by_the_dataset(tmp_path):
    cfg = load_preset("tiny")
    cfg.model.appearance = "exposure"
    with pytest.raises(ConfigError, match="model.appearance"):
        check_config(cfg)
    cfg.model.appearance, cfg.model.appearance_lr = "gain", 0.0
    with pytest.raises(ConfigError, match="appearance_lr"):
        check_config(cfg)
    with pytest.raises(LiveSceneError, match="appearance_frames"):
        LiveSceneModel(ModelConfig(appearance="gain", resolution=8, k_resolution=4, prob_resolution=8,
                                   proposal_resolutions=[8, 8], var_resolution=4), 1)
    # a bare `off` is a YAML boolean: the setting still reads it as the word
    assert apply_overrides(load_preset("tiny"), ["model.appearance=off"]).model.appearance == "off"
    with pytest.raises(ConfigError, match="choose one of off, gain, affine"):
        check_config(apply_overrides(load_preset("tiny"), ["model.appearance=yes"]))
    ds = toy_dataset(tmp_path / "ds", n_frames=9, size=(16, 12))
    tr = Trainer(ds, tmp_path / "run", tiny_cfg("affine", 2), device="cpu", show_progress=False)
    assert tr.cfg.model.appearance_frames == 9 and tuple(tr.model.appearance.codes.shape) == (9, 12)


# ----------------------------------------------------------------------------------------------------------------
# (a) off is the model of before; at identity the codes change nothing
# ----------------------------------------------------------------------------------------------------------------
def test_off_adds_nothing_and_identity_codes_train_the_same_first_step(tmp_path):
    ds = toy_dataset(tmp_path / "ds", n_frames=9, size=(16, 12))
    off = Trainer(ds, tmp_path / "off", tiny_cfg("off", 3), device="cpu", show_progress=False)
    on = Trainer(ds, tmp_path / "on", tiny_cfg("gain", 3), device="cpu", show_progress=False)
    assert off.model.appearance is None and not any("appearance" in k for k in off.model.state_dict())
    assert [g["name"] for g in off.opt.param_groups] == ["field", "proposals", "prob", "variable"]
    shared = off.model.state_dict()
    for k, v in on.model.state_dict().items():  # the codes draw no random numbers: the same initial field
        if not k.startswith("appearance."):
            assert torch.equal(v, shared[k]), k
    a, b = off.train_step(), on.train_step()
    assert a["rgb"] == b["rgb"] and a["loss"] == b["loss"]  # identity codes: bit-identical loss ...
    shared = off.model.state_dict()
    for k, v in on.model.state_dict().items():  # ... and bit-identical weights after the step
        if not k.startswith("appearance."):
            assert torch.equal(v, shared[k]), k
    assert float(on.model.appearance.codes.detach().abs().max()) > 0  # the codes themselves did move
    # the rendered (neutral) image does not read the codes at all
    on.model.appearance.codes.data.normal_(0, 0.3)
    run_on = Run(on.run_dir, on.model, on.views, on.cfg, on.device, on.step)
    run_off = Run(off.run_dir, off.model, off.views, off.cfg, off.device, off.step)
    i = on.views.held_out[0]
    img_on = render_view(run_on, on.views.c2w_gl[i], on.views.intrinsics[i], fast=False)["rgb"]
    img_off = render_view(run_off, off.views.c2w_gl[i], off.views.intrinsics[i], fast=False)["rgb"]
    assert np.array_equal(img_on, img_off)


# ----------------------------------------------------------------------------------------------------------------
# (b) known per-frame gains: recovered, and the neutral render is the unscaled scene
# ----------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def exposed(one_thread, tmp_path_factory):
    """The exposed toy room trained with and without per-frame appearance (the same seed and steps)."""
    root = tmp_path_factory.mktemp("appearance")
    ds, gains = exposed_dataset(root / "ds")
    runs = {}
    for mode in ("off", "gain"):
        train(ds, root / mode, tiny_cfg(mode, 300), device="cpu", show_progress=False)
        runs[mode] = root / mode
    return ds, gains, runs


def neutral_psnr(run, frames: list[int]) -> float:
    """Mean PSNR of the neutral renders against the unscaled scene (the toy render x BASE) at these cameras."""
    scores = []
    states = np.load(run.views.dataset.root / "toy_states.npy")
    for i in frames:
        intr = run.views.intrinsics[i]
        truth = ToyScene(1).render(run.views.c2w_gl[i], states[i], intr)[0].astype(np.float32) / 255.0 * BASE
        out = render_view(run, run.views.c2w_gl[i], intr, None, time=float(run.views.times[i]), fast=False)
        scores.append(psnr(np.mean((out["rgb"] - truth) ** 2)))
    return float(np.mean(scores))


@pytest.mark.slow
def test_learned_codes_recover_the_per_frame_gains(exposed):
    ds, gains, runs = exposed
    run = load_run(runs["gain"], device="cpu")
    codes = run.model.appearance.centred().detach().numpy()
    train_idx = run.views.train
    assert run.model.appearance.trained.numpy().nonzero()[0].tolist() == train_idx
    learned = np.exp(codes[train_idx]).mean(1)
    truth = gains[train_idx]
    order = np.corrcoef(np.argsort(np.argsort(learned)), np.argsort(np.argsort(truth)))[0, 1]
    assert order > 0.9, (learned.round(3), truth.round(3))  # the ordering: Spearman's rank correlation
    # the values: the penalty towards identity (and the field's view-dependent colour, the toy's camera turning
    # with time) keep a share of the swing (measured: the codes take 0.8 of it at the default weight, within 0.05)
    slope = np.polyfit(np.log(truth), np.log(learned), 1)[0]
    assert 0.6 < slope < 1.1 and np.abs(learned - truth).max() < 0.08, (slope, learned.round(3), truth.round(3))
    assert np.all(run.model.appearance.codes.detach().numpy()[run.views.held_out] == 0)  # never trained


@pytest.mark.slow
def test_neutral_render_matches_the_unscaled_scene_better_than_without(exposed):
    ds, gains, runs = exposed
    with_code, without = load_run(runs["gain"], device="cpu"), load_run(runs["off"], device="cpu")
    frames = with_code.views.held_out + with_code.views.train[::4]
    a, b = neutral_psnr(with_code, frames), neutral_psnr(without, frames)
    assert a > b + 1.0, (a, b)


# ----------------------------------------------------------------------------------------------------------------
# (c) checkpoints: round trip, resume, runs from before
# ----------------------------------------------------------------------------------------------------------------
def test_checkpoint_round_trip_and_resume_are_exact(tmp_path):
    ds = toy_dataset(tmp_path / "ds", n_frames=10, size=(16, 12))
    full = Trainer(ds, tmp_path / "full", tiny_cfg("gain", 6), device="cpu", show_progress=False)
    full.fit()
    run = load_run(tmp_path / "full", device="cpu")
    assert run.config.model.appearance == "gain"
    assert torch.equal(run.model.appearance.codes, full.model.appearance.codes.detach())
    part = Trainer(ds, tmp_path / "part", tiny_cfg("gain", 6), device="cpu", show_progress=False)
    for _ in range(4):
        part.train_step()
    part.save_checkpoint()
    del part
    resumed = Trainer(ds, tmp_path / "part", load_preset("tiny"), device="cpu", resume=True, show_progress=False)
    assert resumed.step == 4 and resumed.cfg.model.appearance == "gain"
    resumed.cfg.steps = 6
    resumed.fit()
    a, b = full.model.state_dict(), resumed.model.state_dict()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_a_checkpoint_from_before_appearance_loads_without_it(tmp_path):
    ds = toy_dataset(tmp_path / "ds", n_frames=9, size=(16, 12))
    Trainer(ds, tmp_path / "run", tiny_cfg("off", 2), device="cpu", show_progress=False).fit()
    for name in ["latest.pt", *(f"checkpoints/{p.name}" for p in (tmp_path / "run" / "checkpoints").iterdir())]:
        ckpt = torch.load(tmp_path / "run" / name, weights_only=False)
        for key in ("appearance", "appearance_frames", "appearance_lr"):  # as written before the setting existed
            ckpt["config"]["model"].pop(key)
        ckpt["config"]["loss"].pop("appearance")
        torch.save(ckpt, tmp_path / "run" / name)
        assert checkpoint_config(ckpt).model.appearance == "off"
    run = load_run(tmp_path / "run", device="cpu")
    assert run.model.appearance is None
    i = run.views.held_out[0]
    assert render_view(run, run.views.c2w_gl[i], run.views.intrinsics[i])["rgb"].shape == (12, 16, 3)
    resumed = Trainer(ds, tmp_path / "run", load_preset("tiny"), device="cpu", resume=True, show_progress=False)
    resumed.cfg.steps = 3
    resumed.fit()  # the optimiser's groups are those of before
    assert resumed.step == 3


def test_migration_ignores_the_current_default(monkeypatch):
    from livescene import config

    monkeypatch.setattr(config.ModelConfig, "appearance", "gain")
    cfg = checkpoint_config({"config": {"model": {"features": 8}}})
    assert cfg.model.appearance == "off"


# ----------------------------------------------------------------------------------------------------------------
# (d) eval reports both PSNRs
# ----------------------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_eval_json_carries_neutral_and_interpolated_psnr(exposed, tmp_path):
    from livescene.cli import main

    ds, gains, runs = exposed
    out = {}
    for mode, run_dir in runs.items():  # off, gain
        assert main(["eval", str(run_dir), "--out", str(tmp_path / f"{mode}.json"), "--device", "cpu",
                     "--novel", "0"]) == 0
        out[mode] = json.loads((tmp_path / f"{mode}.json").read_text())
    on, off = out["gain"], out["off"]
    assert off["appearance"] == {"mode": "off"} and "psnr_interpolated" not in off
    assert on["appearance"]["mode"] == "gain"
    assert on["psnr"] > 0 and on["psnr_interpolated"] > 0 and 0 < on["ssim_interpolated"] <= 1
    for rec in on["frames"]:
        assert {"psnr", "ssim", "psnr_interpolated", "ssim_interpolated"} <= set(rec)
    # held-out frames recorded away from the mean exposure: the interpolated code brings their render closer
    assert on["psnr_interpolated"] > on["psnr"] + 1.0, (on["psnr"], on["psnr_interpolated"])
    # the neutral figure is the honest one for a new view: computed exactly as before, on the neutral render
    run = load_run(runs["gain"], device="cpu")
    i = run.views.held_out[0]
    img = render_view(run, run.views.c2w_gl[i], run.views.intrinsics[i], None, time=float(run.views.times[i]))
    rec = load_frame(run.views, i)[0].astype(np.float32) / 255.0
    assert on["frames"][0]["psnr"] == pytest.approx(psnr(np.mean((img["rgb"] - rec) ** 2)), abs=1e-4)


@pytest.mark.gpu
def test_appearance_trains_on_cuda(tmp_path):
    ds, _ = exposed_dataset(tmp_path / "ds", n_frames=9, size=(24, 18))
    train(ds, tmp_path / "run", tiny_cfg("affine", 20), device="cuda", show_progress=False)
    run = load_run(tmp_path / "run", device="cuda")
    assert run.model.appearance.codes.is_cuda and float(run.model.appearance.codes.abs().max()) > 0
