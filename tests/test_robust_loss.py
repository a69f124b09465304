"""The trimmed colour loss (`--set loss.rgb=0 --set loss.rgb_trimmed=1`): what the scene cannot explain stops pulling
on it."""

from __future__ import annotations

import pytest
import torch

from livescene.config import LossConfig, TrainConfig, check_config
from livescene.errors import ConfigError
from livescene.losses import TERMS, total_loss, trimmed_mse


def test_trimmed_mse_leaves_out_the_worst_share_of_rays():
    torch.manual_seed(0)
    target = torch.rand(100, 3)
    pred = target + 0.01
    pred[:10] = 1.0 - target[:10]  # ten rays of a distractor the scene does not hold
    plain = trimmed_mse(pred, target, 0.0)
    trimmed = trimmed_mse(pred, target, 0.2)
    assert abs(plain.item() - ((pred - target) ** 2).mean().item()) < 1e-7
    assert abs(trimmed.item() - 1e-4) < 1e-6  # only the rays the scene explains remain
    pred.requires_grad_(True)
    trimmed_mse(pred, target, 0.2).backward()
    assert pred.grad[:10].abs().sum() == 0 and pred.grad[10:].abs().sum() > 0


def test_the_trimmed_term_is_off_by_default_and_swaps_in():
    w = LossConfig()
    assert w.rgb_trimmed == 0.0 and "rgb_trimmed" in TERMS
    w.rgb, w.rgb_trimmed = 0.0, 1.0
    terms = {"rgb": torch.tensor(2.0), "rgb_trimmed": torch.tensor(0.5)}
    assert total_loss(terms, w).item() == 0.5  # the plain one stays computed for the logs, weighted 0


def test_a_trim_out_of_range_is_refused():
    cfg = TrainConfig()
    cfg.loss.trim = 0.95
    with pytest.raises(ConfigError, match="loss.trim"):
        check_config(cfg)
