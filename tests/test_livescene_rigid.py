"""livescene with rigid part motions (`articulation.json`): a part's samples are read in its rest frame and owned
only inside its hull, a trained toy door moves only its own pixels, and the run carries its motions."""

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


def train_toy_door(root, n_frames: int, size: tuple[int, int], steps: int) -> tuple:
    """(run folder, summary): the toy scene trained with the door's motion (tiny preset, on the CPU)."""
    ds = toy_dataset(root / "ds", n_frames=n_frames, size=size)
    write_articulation(ds, {"door": TOY_DOOR}, {"source": "test"})
    cfg = load_preset("tiny")
    cfg.steps = steps
    return root / "run", train(ds, root / "run", cfg, device="cpu", show_progress=False)


@pytest.fixture(scope="module")
def rigid_run(tmp_path_factory, one_thread):
    """The toy scene trained with the door's motion (one torch thread, ~20 s)."""
    return train_toy_door(tmp_path_factory.mktemp("rigid"), 24, (40, 30), 400)


def test_place_reads_a_rigid_part_in_its_rest_frame():
    """A point on the door at state 1 is the door's, read where the door is at rest; the door's rest place at
    state 1 (it has swung away) is the background's, read in the world."""
    from livescene.articulation import HULL_RES
    from livescene.config import ModelConfig
    from livescene.field import LiveSceneModel, normalise

    model = LiveSceneModel(ModelConfig(motion="rigid", max_objects=2, resolution=8, scales=[1], k_resolution=4,
                                       proposal_resolutions=[8], prob_resolution=8, var_resolution=4), 1)
    model.motions.load([TOY_DOOR])
    lo, hi = np.array([-1.0, 0.5, -0.1]), np.array([0.0, 0.7, 1.4])  # around the rest door (x -0.9..-0.1, y 0.6)
    model.motions.set_hull(0, (lo, hi, np.ones((HULL_RES,) * 3, bool)))

    def door_wins(xyz, values):
        out = torch.zeros(xyz.shape[0], 3)
        out[:, 0] = 5.0
        return out

    model.prob.forward = door_wins  # inside its hull the door owns everything: only the gate and the warp decide
    box = (torch.tensor([-2.0, -2.0, -0.5]), torch.tensor([2.0, 2.0, 3.0]))
    on_rest = torch.tensor([[-0.5, 0.6, 0.6]])  # the middle of the closed door
    r, t = TOY_DOOR.pose(1.0)
    on_open = torch.as_tensor(r @ on_rest[0].numpy() + t, dtype=torch.float32)[None]  # the same point, door open
    pts = torch.cat([on_open, on_rest])
    values = torch.tensor([[1.0, 0.0], [1.0, 0.0]])
    place = model.place(pts, torch.tensor([[1.0, 0, 0]] * 2), values, box)
    probs = torch.softmax(place.logits, -1)
    assert probs[0, 0] > 0.99 and probs[1, -1] > 0.99  # the door there, the background where it was
    assert torch.allclose(place.xyz[0], normalise(on_rest, box)[0], atol=1e-5)  # read at rest
    assert torch.allclose(place.xyz[1], normalise(on_rest, box)[0], atol=1e-5)  # the world point itself
    assert place.k[0] == 0.0 and place.k[1] < 0  # part_k "rest"; the background's own k slice


@pytest.mark.slow
def test_rigid_run_carries_its_motion_and_moves_only_the_door(rigid_run, tmp_path):
    from livescene.render import render_view

    run_dir, summary = rigid_run
    assert summary["heldout_psnr"] > 22.0
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
    assert diff[(idx0 == 1) | (idx1 == 1)].mean() > 0.02  # the door does move
    assert np.percentile(diff[static], 90) < 0.03



def test_rigid_without_a_motion_file_is_a_clear_error(tmp_path):
    ds = toy_dataset(tmp_path / "ds", n_frames=8, size=(16, 12))
    cfg = load_preset("tiny")
    cfg.steps = 1
    cfg.model.motion = "rigid"
    with pytest.raises(LiveSceneError, match="interreal motions"):
        train(ds, tmp_path / "run", cfg, device="cpu", show_progress=False)


def test_mask_losses_move_light_along_the_ray_not_its_amount():
    """With `mask_shapes`, a pixel's mask loss reaches the sample weights, but scaling them all (a more transparent
    ray) must not change it: else "transparent" is the cheapest way to be background."""
    from livescene.sampler import render_logits

    gen = torch.Generator().manual_seed(0)
    logits = torch.randn(4, 6, 3, generator=gen)
    weights = (torch.rand(4, 6, generator=gen) * 0.2).requires_grad_()
    slots = torch.ones(3, dtype=torch.bool)
    loss = -torch.log_softmax(render_logits(logits, weights, slots, "probs"), -1)[:, -1].sum()
    loss.backward()
    assert weights.grad.abs().max() > 1e-3  # the loss does reach the weights ...
    assert (weights.grad * weights).sum(1).abs().max() < 1e-5  # ... but not their sum along each ray
    detached = render_logits(logits, weights.detach(), slots, "probs")
    assert torch.allclose(detached, render_logits(logits, weights, slots, "probs"), atol=1e-6)
