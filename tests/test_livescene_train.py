"""livescene training on a toy articulated room: loss falls, PSNR passes a bar, resume is exact, the
learned states follow the labels, official layouts load, rendering at a new state changes only the object."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_livescene_toy import ToyScene, toy_dataset  # noqa: E402

from livescene.config import load_preset  # noqa: E402
from livescene.trainer import Trainer, load_run, train  # noqa: E402


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def trained(one_thread, tmp_path_factory):
    """One tiny run shared by the slow tests of this file (about 15 s on an idle core, minutes on a crowded one)."""
    root = tmp_path_factory.mktemp("ls_train")
    ds = toy_dataset(root / "ds", n_frames=24, size=(40, 30))
    cfg = load_preset("tiny")
    cfg.steps = 300
    summary = train(ds, root / "run", cfg, device="cpu", show_progress=False)
    return ds, root / "run", summary


@pytest.mark.slow
def test_loss_falls_and_psnr_passes(trained):
    ds, run_dir, summary = trained
    logs = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    train_logs = [r for r in logs if r["type"] == "train"]
    assert train_logs[-1]["rgb"] < 0.3 * train_logs[0]["rgb"]
    assert summary["train_psnr"] > 24.0
    assert summary["heldout_psnr"] > 22.0
    assert summary["heldout_eval_frames"] == 3  # all of the 24 frames' held-out ones (every 8th)
    for name in ("config.yaml", "latest.pt", "objects.yaml", "reports/train.json"):
        assert (run_dir / name).exists(), name
    assert json.loads((run_dir / "reports" / "train.json").read_text())["status"] == "ok"


@pytest.mark.slow
def test_learned_states_follow_labels(trained):
    ds, run_dir, _ = trained
    run = load_run(run_dir, device="cpu")
    labels, given = run.dataset.label_matrix()
    given &= np.isin(np.arange(len(given)), run.views.train)[:, None]
    with torch.no_grad():
        pred = run.model.frame_values(torch.as_tensor(run.views.times))[:, :1].numpy()
    assert np.abs(pred - labels)[given].mean() < 0.08


@pytest.mark.slow
def test_new_state_changes_only_the_object(trained):
    from livescene.render import render_view

    ds, run_dir, _ = trained
    run = load_run(run_dir, device="cpu")
    i = run.views.train[5]
    c2w, intr = run.views.c2w_gl[i], run.views.intrinsics[i]
    a = render_view(run, c2w, intr, {"door": 0.0})
    b = render_view(run, c2w, intr, {"door": 1.0})
    assert a["probs"].shape == (30, 40, 2) and np.allclose(a["probs"].sum(-1), 1, atol=1e-4)
    diff = np.abs(a["rgb"] - b["rgb"]).max(-1)
    # the truth: pixels that show the door in neither state must not change
    _, _, idx0 = ToyScene(1).render(c2w, [0.0], intr)
    _, _, idx1 = ToyScene(1).render(c2w, [1.0], intr)
    static = (idx0 == 0) & (idx1 == 0)
    model_static = (a["probs"][..., 0] < 0.5) & (b["probs"][..., 0] < 0.5)
    assert diff[(idx0 == 1) | (idx1 == 1)].mean() > 0.02  # the door does move
    assert np.percentile(diff[static & model_static], 95) < 0.02
    assert (static & model_static).mean() > 0.5


def _run(ds: Path, out: Path, steps: int) -> Trainer:
    cfg = load_preset("tiny")
    cfg.steps, cfg.ckpt_every, cfg.eval_every, cfg.log_every = steps, 0, 0, 5
    tr = Trainer(ds, out, cfg, device="cpu", show_progress=False)
    return tr


def test_resume_is_exact(tmp_path):
    ds = toy_dataset(tmp_path / "ds", n_frames=10, size=(16, 12))
    full = _run(ds, tmp_path / "full", 8)
    full.fit()
    part = _run(ds, tmp_path / "part", 8)
    for _ in range(5):  # "killed" after 5 steps: checkpoint then a fresh process resumes
        part.train_step()
    part.save_checkpoint()
    del part
    resumed = Trainer(ds, tmp_path / "part", load_preset("tiny"), device="cpu", resume=True, show_progress=False)
    assert resumed.step == 5
    resumed.cfg.steps = 8
    resumed.fit()
    a, b = full.model.state_dict(), resumed.model.state_dict()
    for k in a:
        assert torch.equal(a[k], b[k]), k


@pytest.mark.slow
def test_refuses_to_overwrite_a_run(tmp_path, trained):
    from livescene.errors import LiveSceneError

    ds, run_dir, _ = trained
    with pytest.raises(LiveSceneError, match="--resume"):
        Trainer(ds, run_dir, load_preset("tiny"), device="cpu")


def test_official_omnisim_layout_loads(tmp_path):
    from livescene.data import RayData, load_views

    ds = toy_dataset(tmp_path / "omni", n_frames=9, size=(24, 18), blender=True)
    meta = json.loads((ds / "transforms.json").read_text())
    assert "camera_angle_x" in meta and not meta["frames"][0]["file_path"].endswith(".png")
    cfg = load_preset("tiny")
    views = load_views(ds, cfg)
    assert views.dataset.layout == "blender" and len(views.train) == 8 and len(views.held_out) == 1
    assert abs(views.intrinsics[0].fl_x - 0.9 * 24) < 1e-6
    data = RayData(views, torch.device("cpu"))
    batch = data.sample(64, torch.Generator().manual_seed(0), 0.25)
    assert batch["rgb"].shape == (64, 3) and torch.allclose(batch["dirs"].norm(dim=-1), torch.ones(64), atol=1e-5)
    assert int((batch["mask"] >= 0).sum()) == 64


def test_rays_match_the_toy_cameras(tmp_path):
    """Distorted pixel centres, OpenGL poses -> OpenCV rays: rays of the loader hit what the toy renderer saw."""
    from livescene.data import RayData, load_views

    ds = toy_dataset(tmp_path / "ds", n_frames=9, size=(24, 18))
    views = load_views(ds, load_preset("tiny"))
    data = RayData(views, torch.device("cpu"))
    f = torch.tensor([2, 2]); ys = torch.tensor([0, 17]); xs = torch.tensor([0, 23])
    b = data.gather(f, ys, xs)
    from livescene.data import camera_rays

    o, d, _ = camera_rays(views.c2w_gl[2], views.intrinsics[2])
    assert np.allclose(b["dirs"][0].numpy(), d[0], atol=1e-5) and np.allclose(b["dirs"][1].numpy(), d[-1], atol=1e-5)
    assert np.allclose(b["origins"][0].numpy(), o[0], atol=1e-5)


@pytest.mark.slow
def test_render_cli_sweep_video_and_maps(trained, tmp_path):
    from livescene.cli import main

    ds, run_dir, _ = trained
    out = tmp_path / "r"
    assert main(["render", str(run_dir), "--sweep", "door=0:1:3", "--out", str(out), "--video",
                 str(tmp_path / "door.mp4"), "--depth", "--probs", "--device", "cpu"]) == 0
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert len([p for p in pngs if p.endswith("_probs.png")]) == 3 and len([p for p in pngs if "_depth" in p]) == 6
    import av

    with av.open(str(tmp_path / "door.mp4")) as c:
        assert c.streams.video[0].codec_context.name == "h264"
        assert sum(1 for _ in c.decode(video=0)) == 3
    cams = {"frames": [{"transform_matrix": np.eye(4).tolist(), "states": {"door": 0.5}}]}
    (tmp_path / "cams.json").write_text(json.dumps(cams))
    assert main(["render", str(run_dir), "--cameras", str(tmp_path / "cams.json"), "--out", str(out / "j"),
                 "--device", "cpu"]) == 0
    assert (out / "j" / "cam_0000.png").exists()
    assert main(["render", str(run_dir), "--state", "nosuch=1", "--device", "cpu"]) == 2



@pytest.mark.slow
def test_render_warns_of_states_never_seen_near_the_camera(trained, capsys):
    """A state that no training view near the camera showed is named (with what those views showed); one they
    showed is not; the CLI prints the warning and still renders."""
    from livescene.cli import main
    from livescene.data import nearest_views
    from livescene.render import learned_frame_states, unseen_states, warn_unseen

    ds, run_dir, _ = trained
    run = load_run(run_dir, device="cpu")
    learned = learned_frame_states(run)
    views = run.views
    i = views.held_out[0]
    seen = learned[nearest_views(views.c2w_gl[:, :3, 3], views.train, views.c2w_gl[i][:3, 3]), 0]
    grid = np.linspace(0, 1, 101)
    gap = np.abs(grid[:, None] - seen[None]).min(1)
    far, d = float(grid[gap.argmax()]), float(gap.max())
    # the toy's door moves while the camera moves: some states were only seen from elsewhere (0.21 away)
    assert d > 0.15
    hit = unseen_states(run, learned, views.c2w_gl[i], {"door": far}, tol=d / 2)
    assert hit["door"] == pytest.approx(seen[np.abs(seen - far).argmin()])
    assert unseen_states(run, learned, views.c2w_gl[i], {"door": far}, tol=d + 0.01) == {}
    assert unseen_states(run, learned, views.c2w_gl[i], {"door": float(seen[0])}, tol=0.01) == {}
    assert unseen_states(run, learned, views.c2w_gl[i], {"nosuch": 0.5}) == {}  # render_view names it
    jobs = [{"c2w": views.c2w_gl[i], "states": None}] * 2
    msgs = warn_unseen(run, jobs, {"door": far}, tol=d / 2)
    assert len(msgs) == 1 and "'door'" in msgs[0] and "2 of 2 renders" in msgs[0]
    capsys.readouterr()
    assert main(["render", str(run_dir), "--frames", str(i), "--state", f"door={far}", "--out",
                 str(run_dir / "warned"), "--device", "cpu"]) == 0
    err = capsys.readouterr().err
    assert "warning: 'door'" in err and "1 of 1 renders" in err and (run_dir / "warned").is_dir()

@pytest.mark.slow
def test_eval_with_truth(trained, tmp_path):
    from livescene.evaluate import evaluate

    ds, run_dir, _ = trained
    run = load_run(run_dir, device="cpu")
    states = np.load(ds / "toy_states.npy")
    scene = ToyScene(1)

    class Truth:
        def __init__(self):
            self.states = states

        metres_per_unit = 1.0

        def render(self, i, st, intr):  # frame i's true camera (here the dataset's own)
            return scene.render(run.views.c2w_gl[i], st, intr)[0]

        def depth(self, i, intr):
            return scene.render(run.views.c2w_gl[i], states[i], intr)[1]

        def instance(self, i, intr):
            return scene.render(run.views.c2w_gl[i], states[i], intr)[2]

    res = evaluate(run, Truth(), novel=2, progress=False)
    assert res["held_out_frames"] == 3
    assert res["psnr"] > 20 and 0 < res["ssim"] <= 1
    assert res["state_mae"] < 0.15 and res["mask_iou"] > 0.5
    assert res["novel_state_psnr"] > 18 and res["depth_l1"] < 1.0
    assert res["novel_state_mask_iou"] is None  # this truth cannot say who owns what at other states

    class StateTruth(Truth):
        def state_instance(self, i, st, intr):
            return scene.render(run.views.c2w_gl[i], st, intr)[2]

    res = evaluate(run, StateTruth(), novel=2, progress=False)
    assert res["novel_state_mask_iou"] > 0.4  # 0.55 with torch 2.13 here, 0.50 with 2.11 on a 16-core x86 machine
    for rec in res["novel_frames"]:
        assert len(rec["states"]) == 1 and rec["mask_iou"] > 0.3 and rec["true_state_mask_iou"] > 0.3

    # scored on the probabilities rendered at the novel states, not at the frame's own
    from livescene.evaluate import mask_iou
    from livescene.render import render_view

    def iou_at(i: int, values, st: np.ndarray) -> float:
        """The rendered probabilities at `values` against the truth at the novel state `st`."""
        intr = run.views.intrinsics[i]
        probs = render_view(run, run.views.c2w_gl[i], intr, values, time=float(run.views.times[i]))["probs"]
        return mask_iou(probs, scene.render(run.views.c2w_gl[i], st, intr)[2], 1)

    fids = [f.fid for f in run.views.dataset.frames]
    differs = []
    for rec in res["novel_frames"]:
        i, st = fids.index(rec["frame"]), np.asarray(rec["states"], np.float32)
        assert abs(rec["mask_iou"] - iou_at(i, st, st)) < 1e-6
        differs.append(iou_at(i, states[i], st) != rec["mask_iou"])
    assert any(differs)  # one near state can binarise alike (seen with torch 2.11), not every one


def test_nan_rolls_back_then_stops(tmp_path, monkeypatch):
    from livescene.errors import DivergenceError

    ds = toy_dataset(tmp_path / "ds", n_frames=9, size=(16, 12))
    tr = _run(ds, tmp_path / "run", 6)
    real = tr.losses
    calls = {"n": 0}

    def flaky(batch):
        terms, out = real(batch)
        calls["n"] += 1
        if calls["n"] == 3:  # one bad step: roll back to the last checkpoint with half the learning rate
            terms["rgb"] = terms["rgb"] * float("nan")
        return terms, out

    monkeypatch.setattr(tr, "losses", flaky)
    summary = tr.fit()
    assert summary["steps"] == 6 and summary["rollbacks"] == 1 and tr.lr_scale == 0.5
    logs = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert any(r["type"] == "rollback" for r in logs)

    tr2 = _run(ds, tmp_path / "run2", 6)
    real2 = tr2.losses

    def always_nan(batch):
        terms, out = real2(batch)
        terms["rgb"] = terms["rgb"] * float("nan")
        return terms, out

    monkeypatch.setattr(tr2, "losses", always_nan)
    with pytest.raises(DivergenceError, match="diverged"):
        tr2.fit()


def test_cli_help_has_examples(capsys):
    from livescene.cli import main

    for cmd in ("train", "render", "eval"):
        with pytest.raises(SystemExit):
            main([cmd, "--help"])
        assert "examples:" in capsys.readouterr().out


@pytest.mark.gpu
def test_tiny_training_on_cuda(tmp_path):
    ds = toy_dataset(tmp_path / "ds", n_frames=9, size=(24, 18))
    cfg = load_preset("tiny")
    cfg.steps, cfg.eval_every, cfg.ckpt_every = 30, 0, 0
    summary = train(ds, tmp_path / "run", cfg, device="cuda", show_progress=False)
    assert summary["steps"] == 30
    run = load_run(tmp_path / "run", device="cuda")
    assert run.device.type == "cuda" and next(run.model.parameters()).is_cuda


def test_lr_schedule_ends_with_the_time_budget():
    """A clock-limited run decays its learning rate by the clock: at the budget's end it is at the final ratio,
    whatever the nominal step count."""
    from livescene.config import TrainConfig
    from livescene.trainer import lr_factor

    cfg = TrainConfig()
    cfg.steps, cfg.warmup, cfg.lr_final_ratio = 100_000, 10, 0.05
    assert lr_factor(5, cfg) == pytest.approx(0.6)
    assert lr_factor(500, cfg) > 0.99  # step-based: barely started
    assert lr_factor(500, cfg, time_frac=0.5) == pytest.approx(0.525)
    assert lr_factor(500, cfg, time_frac=1.0) == pytest.approx(0.05)
    assert lr_factor(500, cfg, time_frac=3.0) == pytest.approx(0.05)


def test_auto_threads_look_at_other_processes_not_the_load_average(monkeypatch):
    """One thread only when other processes keep the cores busy; this process's own past work (SfM just before
    training) does not count, as it would in the load average."""
    import os

    from livescene import device

    cores = os.cpu_count() or 1
    now = device.other_processes_cores(0.1)
    # cores' worth of CPU time per second; over a 0.1 s window on an oversubscribed machine the sampling skew
    # between reading /proc and the clock can overshoot the core count
    assert now is not None and 0.0 <= now <= 2 * cores + 0.5
    before = torch.get_num_threads()
    try:
        monkeypatch.setattr(device, "other_processes_cores", lambda window=0.5: 0.0)
        monkeypatch.setattr(os, "getloadavg", lambda: (99.0, 99.0, 99.0))
        assert device.configure_threads(0) == cores
        monkeypatch.setattr(device, "other_processes_cores", lambda window=0.5: float(cores))
        assert device.configure_threads(0) == 1
        assert device.configure_threads(3) == 3
    finally:
        torch.set_num_threads(before)


def test_novel_and_composition_states_are_far_from_every_training_combination():
    """Novel states: far from every training combination. Composition states: also far, but built only from states
    each object shows near the camera (so they test composing parts, not rendering an unseen side of a part)."""
    from livescene.evaluate import composition_states, novel_states

    t = np.linspace(0, 1, 40)
    # object 0 opens during the first half while the camera is on the left, object 1 during the second half
    states = np.stack([np.clip(t * 2, 0, 1), np.clip(t * 2 - 1, 0, 1)], 1)
    centres = np.stack([t * 4 - 2, np.zeros_like(t), np.zeros_like(t)], 1)
    train = [i for i in range(40) if i % 8 != 4]
    st, d = novel_states(states[train], np.random.default_rng(0))
    assert d >= 0.25 and np.abs(states[train] - st).max(1).min() == d
    # in the middle both objects move near the camera: (object 0 half open, object 1 closed) never happens with
    # the camera there, yet each state is seen nearby
    pick = composition_states(states, centres, train, 20, near=12)
    assert pick is not None
    st, d = pick
    assert d >= 0.1 and np.abs(states[train] - st).max(1).min() == pytest.approx(d)
    near = np.argsort(np.abs(centres[train, 0] - centres[20, 0]))[:12]
    for o in range(2):
        assert np.abs(states[np.asarray(train)[near], o] - st[o]).min() <= 0.05 + 1e-9
    # at the start only object 0 moves: every nearby combination was seen, so there is nothing to compose
    assert composition_states(states, centres, train, 4, near=6) is None


def test_more_objects_than_slots_widens_the_slots(tmp_path, capsys):
    """A scene with more objects than the preset's slots trains (the slots widen, with a note) and reopens."""
    ds = toy_dataset(tmp_path / "ds", n_frames=8, size=(16, 12), n_objects=2)
    cfg = load_preset("tiny")
    cfg.model.max_objects = 1
    cfg.steps = 2
    train(ds, tmp_path / "run", cfg, device="cpu", show_progress=False)
    assert "2 objects > 1 object slots" in capsys.readouterr().err
    run = load_run(tmp_path / "run", device="cpu")
    assert run.model.n_objects == 2 and run.config.model.max_objects == 2


def test_low_fit_reads_several_held_out_frames(tmp_path, monkeypatch):
    """One good held-out frame among poor ones must not hide a poor fit (the stress suite's label-fraction 25 %
    run: 25.0 dB on the one frame the old check rendered, 23.9 dB over four, and no warning)."""
    ds = toy_dataset(tmp_path / "ds", n_frames=40, size=(16, 12))
    scores = {}

    def fake_psnr(self, i, max_side):
        held = self.views.held_out
        scores[i] = 30.0 if i == held[0] else 20.0
        return scores[i]

    monkeypatch.setattr(Trainer, "heldout_psnr", fake_psnr)
    cfg = load_preset("tiny")
    cfg.steps = 4
    summary = train(ds, tmp_path / "run", cfg, device="cpu", show_progress=False)
    assert summary["heldout_eval_frames"] == 4 and len(scores) == 4
    assert summary["heldout_psnr"] == pytest.approx(22.5)  # (30 + 3 x 20) / 4; the first frame alone reads 30
    report = json.loads((tmp_path / "run" / "reports" / "train.json").read_text())
    assert "low-fit" in {w["cause"] for w in report["warnings"]}


def test_max_minutes_bounds_the_whole_command(tmp_path, monkeypatch):
    """`--max-minutes` is the user's wall-clock limit: loading, periodic evaluations, checkpoints and the final
    evaluation come out of the training time (the demo's 10-minute training stage took 10.3 minutes before).

    On a fake clock where a step costs 50 ms, a checkpoint 20 ms and a render 0.2 ms a pixel, the whole command
    (loading to the final evaluation) must end within one step of the 6-second limit."""
    import livescene.trainer as tr
    from conftest import FakeClock

    clock = FakeClock(tick=1e-4)

    def costs(fn, seconds):
        def wrapped(*a, **k):
            clock.advance(seconds(*a, **k))
            return fn(*a, **k)
        return wrapped

    monkeypatch.setattr(Trainer, "train_step", costs(Trainer.train_step, lambda *a, **k: 0.05))
    monkeypatch.setattr(tr, "write_checkpoint", costs(tr.write_checkpoint, lambda *a, **k: 0.02))
    monkeypatch.setattr(tr, "render_view", costs(tr.render_view, lambda run, c2w, intr, *a, **k: 2e-4 * intr.w * intr.h))
    ds = toy_dataset(tmp_path / "ds", n_frames=24, size=(40, 30))
    cfg = load_preset("tiny")
    cfg.steps, cfg.eval_every, cfg.ckpt_every = 100_000, 0, 5  # no periodic evaluation to learn the render speed from
    t0 = clock()
    trainer = Trainer(ds, tmp_path / "run", cfg, device="cpu", max_minutes=0.1, show_progress=False, clock=clock)
    summary = trainer.fit()
    wall = clock() - t0
    assert summary["stop"] == "max-minutes"
    assert trainer.overhead > 0.3  # checkpoints every 5 steps, the loading, a first render to time the final evaluation
    assert trainer._eval_s_per_px > 0 and trainer.end_reserve() > 0.2
    assert summary["elapsed_s"] <= 6.0 - trainer.overhead + 0.06  # training got what the rest left
    assert 6.0 - 0.1 < wall <= 6.0 + 0.06, wall  # the limit used, and kept to within one step


def test_a_cold_first_read_is_not_planned_as_the_render_and_grid_speed(tmp_path, monkeypatch):
    """On CUDA the first field read of a process loads kernels for seconds: timed, it made the final evaluation and
    the occupancy grid look so dear that a 0.6-minute run trained 1 step (1.5 minutes: 0.8 of training, measured on
    an H200). Both are now timed warm: a first call that costs 1 s (on a fake clock) leaves the plan as cheap as it
    is."""
    import livescene.occupancy as occ
    import livescene.trainer as tr
    from conftest import FakeClock

    clock = FakeClock(tick=1e-3)

    def cold_once(fn):
        calls = []

        def wrapped(*a, **k):
            if not calls:
                calls.append(1)
                clock.advance(1.0)
            return fn(*a, **k)
        return wrapped

    monkeypatch.setattr(occ, "_lattice", cold_once(occ._lattice))  # inside build_grid's own timing
    monkeypatch.setattr(tr, "render_view", cold_once(tr.render_view))
    ds = toy_dataset(tmp_path / "ds", n_frames=12, size=(40, 30))
    cfg = load_preset("tiny")
    cfg.steps, cfg.eval_every, cfg.ckpt_every = 20, 0, 0
    trainer = Trainer(ds, tmp_path / "run", cfg, device="cpu", max_minutes=5, show_progress=False, clock=clock)
    trainer.fit()
    assert 0 < trainer._grid_s < 1.0  # the cold second, scaled by the cell ratio, was 8 s
    small = tr.within_side(trainer.views.intrinsics[trainer.quick_frame], cfg.eval_max_side)
    assert 0 < trainer._eval_s_per_px * small.w * small.h < 0.5  # one warm render, not the cold second


def test_jemalloc_is_opt_in_and_only_for_its_own_command(monkeypatch):
    """Measured slower here (3.7 vs 5.6 steps/s on the CPU preset), so never by default; and a CLI entry point
    called as a function must not re-execute its host (pytest)."""
    import os

    from livescene import device

    calls = []
    monkeypatch.setattr(os, "execve", lambda *a: calls.append(a))
    monkeypatch.setattr(device, "jemalloc_loaded", lambda: False)
    monkeypatch.setattr(os.path, "exists", lambda p: True)
    monkeypatch.delenv(device.JEMALLOC_ENV, raising=False)
    monkeypatch.setattr(sys, "argv", ["/venv/bin/livescene", "train", "ds"])
    device.reexec_with_jemalloc(("livescene", "train"))
    assert calls == []
    monkeypatch.setenv(device.JEMALLOC_ENV, "1")
    device.reexec_with_jemalloc(("interreal", "demo"))
    assert calls == []
    device.reexec_with_jemalloc(("livescene", "train"))
    assert len(calls) == 1 and device.JEMALLOC in calls[0][2]["LD_PRELOAD"]


def test_final_evaluation_shrinks_to_a_tenth_of_a_short_time_limit(tmp_path):
    """A 1.5-minute run on 1600x900 frames spent half its budget on the final evaluation at 640 px."""
    ds = toy_dataset(tmp_path / "ds", n_frames=24, size=(40, 30))
    cfg = load_preset("tiny")
    cfg.final_eval_max_side, cfg.eval_max_side = 40, 8
    tr = Trainer(ds, tmp_path / "run", cfg, device="cpu", max_minutes=1.0, show_progress=False)
    tr._eval_s_per_px = 0.001  # 3 frames x 1200 px -> 3.6 s, well under a tenth of a minute: kept
    assert tr.final_side() == 40
    tr._eval_s_per_px = 0.01  # 36 s at 40 px: shrunk to spend 6 s
    side = tr.final_side()
    assert 8 <= side < 40 and tr._final_eval_cost(side) <= 6.0 + 1e-6
    tr._eval_s_per_px = 10.0  # never below the periodic evaluation's size
    assert tr.final_side() == 8
    tr.max_minutes = 0.0  # no time limit: always the configured size
    assert tr.final_side() == 40


def test_near_plane_from_the_closest_sfm_point_any_camera_sees(tmp_path):
    """near = max(near, near_auto x the closest point depth): a floater in front of an untextured close-up has
    nowhere to sit, and nothing the cameras filmed is clipped. A stray point or two does not set it; without a
    point cloud (or with near_auto 0) the configured near stays."""
    import trimesh

    from livescene.data import closest_point_depth, load_views
    from livescene.trainer import build_model

    ds = toy_dataset(tmp_path / "ds", n_frames=8)
    cfg = load_preset("tiny")
    views = load_views(ds, cfg)
    assert closest_point_depth(views.dataset, views.c2w_gl, views.intrinsics) is None
    assert build_model(cfg, views)[0].sampler.near == cfg.sampler.near
    rng = np.random.default_rng(0)
    c2w = views.c2w_gl[3]
    eye, ahead = c2w[:3, 3], -c2w[:3, 2]  # OpenGL: the camera looks down -z
    near_pts = eye + 0.8 * ahead + rng.normal(scale=0.003, size=(300, 3))  # a wall 0.8 in front of camera 3
    far_pts = rng.uniform(-3, 3, size=(4000, 3))
    far_pts = far_pts[np.linalg.norm(far_pts[:, None] - views.c2w_gl[None, :, :3, 3], axis=-1).min(1) > 1.2]
    stray = eye + 0.05 * ahead  # one point nearly on the lens: SfM noise
    trimesh.PointCloud(np.vstack([near_pts, far_pts, stray[None]])).export(ds / "sparse_pc.ply")
    closest = closest_point_depth(views.dataset, views.c2w_gl, views.intrinsics)
    depths = []  # the wall's depth in every camera whose image it falls in (camera 3's 0.8 among them)
    for c, intr in zip(views.c2w_gl, views.intrinsics):
        local = (eye + 0.8 * ahead - c[:3, 3]) @ c[:3, :3]  # OpenGL camera axes
        x, y = intr.fl_x * local[0] / -local[2] + intr.cx, intr.fl_y * -local[1] / -local[2] + intr.cy
        if local[2] < 0 and 0 <= x < intr.w and 0 <= y < intr.h:
            depths.append(-local[2])
    assert 0.8 in np.round(depths, 6) and closest == pytest.approx(min(depths), abs=0.02)
    resolved = build_model(cfg, views)[0]
    assert resolved.sampler.near == pytest.approx(cfg.sampler.near_auto * closest, abs=1e-3)
    assert resolved.sampler.near > cfg.sampler.near
    assert build_model(resolved, views)[0].sampler.near == resolved.sampler.near  # resolving again changes nothing
    cfg.sampler.near_auto = 0.0
    assert build_model(cfg, views)[0].sampler.near == cfg.sampler.near
