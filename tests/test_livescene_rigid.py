"""livescene with rigid part motions (`articulation.json`): the toy door read in its rest frame renders states
its cameras never showed better than the k-axis alone, moves only its own pixels, and the run carries its motions."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_livescene_toy import ToyScene, toy_dataset  # noqa: E402

from interreal.dataset import Articulation, write_articulation  # noqa: E402
from livescene.config import load_preset  # noqa: E402
from livescene.errors import LiveSceneError  # noqa: E402
from livescene.trainer import load_run, train  # noqa: E402

# the toy door: 0.8 wide, hinged at (-0.9, 0.6) on a vertical axis, a quarter turn counter-clockwise at state 1
TOY_DOOR = Articulation("hinge", np.array([0.0, 0.0, 1.0]), np.array([-0.9, 0.6, 0.0]), np.pi / 2)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The same toy scene trained with and without the door's motion (one torch thread, ~20 s each)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("rigid")
    plain = toy_dataset(root / "ds", n_frames=24, size=(40, 30))
    rigid = toy_dataset(root / "ds_rigid", n_frames=24, size=(40, 30))
    write_articulation(rigid, {"door": TOY_DOOR}, {"source": "test"})
    out = {}
    for name, ds in (("none", plain), ("rigid", rigid)):
        cfg = load_preset("tiny")
        cfg.steps = 400
        summary = train(ds, root / f"run_{name}", cfg, device="cpu", show_progress=False)
        out[name] = (root / f"run_{name}", summary)
    torch.set_num_threads(before)
    return out


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(np.mean((a.astype(np.float64) - b) ** 2) + 1e-12))


def _novel_psnr(run_dir: Path) -> float:
    """Mean PSNR on held-out cameras with the door at the state opposite to their own (never seen from there)."""
    from livescene.render import render_view

    run = load_run(run_dir, device="cpu")
    states = np.load(run.dataset.root / "toy_states.npy")
    scores = []
    for i in run.views.held_out:
        s = 1.0 - float(states[i, 0])
        c2w, intr = run.views.c2w_gl[i], run.views.intrinsics[i]
        truth, _, _ = ToyScene(1).render(c2w, [s], intr)
        out = render_view(run, c2w, intr, {"door": s})
        scores.append(_psnr(out["rgb"], truth / 255.0))
    return float(np.mean(scores))


@pytest.mark.slow
def test_rigid_door_renders_unseen_states_better(runs):
    none, rigid = _novel_psnr(runs["none"][0]), _novel_psnr(runs["rigid"][0])
    assert rigid > none + 1.0, (rigid, none)
    assert runs["rigid"][1]["heldout_psnr"] > 22.0


@pytest.mark.slow
def test_rigid_run_carries_its_motion_and_moves_only_the_door(runs, tmp_path):
    from livescene.render import render_view

    run_dir = runs["rigid"][0]
    run = load_run(run_dir, device="cpu")
    pm = run.model.motions
    assert pm is not None and pm.rigid(1) == [0] and bool(pm.hull_set[0])
    assert torch.allclose(pm.axis[0], torch.tensor([0.0, 0.0, 1.0])) and abs(float(pm.range[0]) - np.pi / 2) < 1e-6
    (run.dataset.root / "articulation.json").unlink()  # a rendered run needs only its checkpoint
    run = load_run(run_dir, device="cpu")
    i = run.views.train[5]
    c2w, intr = run.views.c2w_gl[i], run.views.intrinsics[i]
    a = render_view(run, c2w, intr, {"door": 0.0})
    b = render_view(run, c2w, intr, {"door": 1.0})
    _, _, idx0 = ToyScene(1).render(c2w, [0.0], intr)
    _, _, idx1 = ToyScene(1).render(c2w, [1.0], intr)
    diff = np.abs(a["rgb"] - b["rgb"]).max(-1)
    static = (idx0 == 0) & (idx1 == 0)
    assert diff[(idx0 == 1) | (idx1 == 1)].mean() > 0.05
    assert np.percentile(diff[static], 90) < 0.03
    # the probability field follows the door: its pixels at each state are the door's
    for out, idx in ((a, idx0), (b, idx1)):
        door = out["probs"][..., 0] > 0.5
        assert (door & (idx == 1)).sum() / max(1, (door | (idx == 1)).sum()) > 0.6


def test_rigid_without_a_motion_file_is_a_clear_error(tmp_path):
    ds = toy_dataset(tmp_path / "ds", n_frames=8, size=(16, 12))
    cfg = load_preset("tiny")
    cfg.steps = 1
    cfg.model.motion = "rigid"
    with pytest.raises(LiveSceneError, match="interreal motions"):
        train(ds, tmp_path / "run", cfg, device="cpu", show_progress=False)
