"""The background slice (rejected samples read a k node of their own, never an object's state 0) and masks
rendered from per-sample probabilities (the samples that pick k are the ones the mask losses judge)."""

from __future__ import annotations

import pytest
import torch

from livescene.config import ModelConfig
from livescene.field import BACKGROUND_K, KPlanes, LiveSceneModel
from livescene.losses import k_smoothness
from livescene.trainer import checkpoint_config


def _grad_rows(grid: KPlanes, k: torch.Tensor) -> set[int]:
    grid.zero_grad()
    xyz = torch.rand(len(k), 3) * 2 - 1
    grid(xyz, k).sum().backward()
    g = grid.kplanes[0].grad  # (3, C, rows, R)
    return set(torch.nonzero(g.abs().sum((0, 1, 3)) > 0)[:, 0].tolist())


def test_background_and_states_read_disjoint_k_nodes():
    torch.manual_seed(0)
    grid = KPlanes([8], 16, 4, background_slice=True)
    assert grid.kplanes[0].shape[2] == 17
    assert _grad_rows(grid, torch.full((64,), BACKGROUND_K)) == {16}
    states = _grad_rows(grid, torch.rand(256))
    assert 16 not in states and {0, 15} <= states | _grad_rows(grid, torch.tensor([0.0, 1.0]))
    # state 0 and state 1 land exactly on the first and last state node
    assert _grad_rows(grid, torch.zeros(8)) == {0}
    assert _grad_rows(grid, torch.ones(8)) == {15}


def test_official_zero_background_reads_state_zero():
    grid = KPlanes([8], 16, 4, background_slice=False)
    assert grid.kplanes[0].shape[2] == 16
    assert _grad_rows(grid, torch.zeros(8)) == {0}


@pytest.mark.parametrize("mode,expected", [("slice", BACKGROUND_K), ("zero", 0.0)])
def test_rejected_samples_take_the_background_k(mode, expected):
    cfg = ModelConfig(resolution=8, k_resolution=4, features=4, prob_resolution=8, proposal_resolutions=[8, 8],
                      var_resolution=10, max_objects=4, reject_threshold=0.5, background_k=mode)
    model = LiveSceneModel(cfg, n_objects=2)
    values = torch.tensor([[0.3, 0.7, 0.0, 0.0]]).expand(3, -1)
    logits = torch.tensor([[9.0, 0, 0, 0, 0], [0, 9.0, 0, 0, 0], [0, 0, 0, 0, 9.0]])  # door, drawer, background
    k = model.select_k(logits, values)
    assert k[:2].tolist() == pytest.approx([0.3, 0.7]) and k[2].item() == expected


def test_k_smoothness_ignores_the_background_node():
    grid = KPlanes([8], 8, 4, background_slice=True)
    base = float(k_smoothness(grid).detach())
    with torch.no_grad():
        grid.kplanes[0][:, :, -1] = 5.0  # a background node unlike every state node
    assert float(k_smoothness(grid).detach()) == base
    with torch.no_grad():
        grid.kplanes[0][:, :, 3] = 5.0
    assert float(k_smoothness(grid).detach()) > base


def test_bad_background_mode_and_old_checkpoints():
    with pytest.raises(Exception, match="background_k"):
        LiveSceneModel(ModelConfig(resolution=8, k_resolution=4, prob_resolution=8, proposal_resolutions=[8, 8],
                                   var_resolution=10, background_k="none"), n_objects=1)
    assert checkpoint_config({"config": {"model": {"background_k": "slice"}}}).model.background_k == "slice"
    old = {"config": {"model": {"features": 16}}}  # saved before the slice existed
    assert checkpoint_config(old).model.background_k == "zero"


def test_masks_rendered_from_probabilities_judge_the_surface_samples():
    from livescene.sampler import render_logits

    slots = torch.tensor([True, True, False, True])  # door, drawer, an empty slot, background
    # one ray: a faint sample in front with a huge door logit, the surface sample (weight 0.9) undecided -> bg
    logits = torch.tensor([[[40.0, 0.0, -1e4, 0.0], [0.0, 0.0, -1e4, 0.5]]])
    w = torch.tensor([[0.05, 0.9]])
    by_logits = render_logits(logits, w, slots, "logits")
    by_probs = render_logits(logits, w, slots, "probs")
    assert by_logits.argmax(-1).item() == 0  # the front sample outvotes the surface
    assert by_probs.argmax(-1).item() == 3  # the surface decides
    assert by_probs[0, 2].item() == -1e4  # empty slots stay out
    # light that leaves the box is background, and the rendered probabilities sum to one
    empty = render_logits(torch.zeros(1, 2, 4), torch.zeros(1, 2), slots, "probs")
    assert empty.argmax(-1).item() == 3
    assert torch.exp(by_probs[0, slots]).sum().item() == pytest.approx(1.0, abs=1e-4)
    # the gradient of a mask loss reaches each sample in proportion to its weight
    lg = logits.clone().requires_grad_(True)
    torch.nn.functional.cross_entropy(render_logits(lg, w, slots, "probs"), torch.tensor([0])).backward()
    g = lg.grad[0, :, 0].abs()
    assert g[1] > 5 * g[0]
