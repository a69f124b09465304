"""The per-frame variable: Lvar reaches it only through labelled (frame, object) pairs."""

from __future__ import annotations

import torch

from livescene.config import ModelConfig
from livescene.field import FrameVariable, LiveSceneModel
from livescene.losses import time_smoothness, var_loss


def test_lvar_gradient_only_through_labelled_pairs():
    torch.manual_seed(0)
    cfg = ModelConfig(resolution=8, k_resolution=4, features=4, prob_resolution=8, proposal_resolutions=[8, 8],
                      var_resolution=50, max_objects=4)
    model = LiveSceneModel(cfg, n_objects=2)
    n_frames = 100
    times = torch.arange(n_frames, dtype=torch.float32) / (n_frames - 1)
    labels = torch.rand(n_frames, 2)
    given = torch.zeros(n_frames, 2, dtype=torch.bool)
    labelled = [0, 37, 80]
    given[labelled, 0] = True
    given[37, 1] = True
    pred = model.frame_values(times)[:, :2]
    var_loss(pred, labels, given).backward()
    grad = model.variable.line.grad
    touched = set(torch.nonzero(grad.abs().sum(-1) > 0)[:, 0].tolist())
    # the nodes around each labelled frame's time, and no others
    allowed = set()
    for f in labelled:
        pos = times[f].item() * (cfg.var_resolution - 1)
        allowed |= {int(pos), min(int(pos) + 1, cfg.var_resolution - 1)}
    assert touched and touched <= allowed
    # unlabelled pairs contribute nothing: changing their labels does not change the gradient
    model.zero_grad()
    labels2 = labels.clone()
    labels2[~given] = 1 - labels2[~given]
    var_loss(model.frame_values(times)[:, :2], labels2, given).backward()
    assert torch.equal(model.variable.line.grad, grad)
    # the other fields get no gradient from Lvar
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in model.field.parameters())


def test_time_smoothness_acts_along_time():
    line = torch.zeros(10, 4)
    line[:, 0] = 1.0  # constant in time, different across channels: no penalty
    assert time_smoothness(line) == 0
    line2 = torch.zeros(10, 4)
    line2[5] = 1.0
    assert time_smoothness(line2) > 0


def test_parameter_count_independent_of_objects():
    cfg = ModelConfig(resolution=8, k_resolution=4, features=4, prob_resolution=8, proposal_resolutions=[8, 8],
                      var_resolution=10, max_objects=6)
    counts = {LiveSceneModel(cfg, n).param_count() for n in range(1, 7)}
    assert len(counts) == 1


def test_frame_variable_outputs_in_unit_range():
    v = FrameVariable(ModelConfig(var_resolution=5, max_objects=3))
    out = v(torch.linspace(0, 1, 7))
    assert out.shape == (7, 3) and bool(((out > 0) & (out < 1)).all())
