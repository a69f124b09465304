"""What a training run warns about: too few state labels before it starts, a poor fit or learned states that miss
the labels after it ends (each warning goes to the console and to RUN/reports/train.json with its cause)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from interreal.dataset import label_shortage


# below this, the renders are not to be trusted (held-out PSNR of runs that are still far from converged); the
# label figures are interreal.dataset.MIN_LABELS / MIN_LABEL_FRACTION
LOW_FIT_PSNR = 24.0  # renders below this are visibly blurry (the stress suite's usable threshold)


MAX_STATE_ERROR = 0.1


def learned_states(trainer) -> tuple[np.ndarray, Any]:
    """(N, M) states the per-frame variable gives every frame after training, and the views."""
    views = trainer.views
    with torch.no_grad():
        values = trainer.model.frame_values(torch.as_tensor(views.times, device=trainer.device))
    return values[:, : len(views.names)].cpu().numpy(), views


def state_warnings(values: np.ndarray, views) -> list[tuple[str, str]]:
    """Warn when the learned states miss the labels: on training frames (not fitted) or on held-out labelled frames
    (never trained on, so their error estimates the error on every unlabelled frame)."""
    labels, given_all = views.dataset.label_matrix()
    out = []
    for k, name in enumerate(views.names):
        for which, frames in (("labelled training", views.train), ("held-out labelled", views.held_out)):
            idx = [i for i in frames if given_all[i, k]]
            if not idx:
                continue
            err = float(np.abs(values[idx, k] - labels[idx, k]).mean())
            if err > MAX_STATE_ERROR:
                out.append((f"'{name}': learned states miss the {which} frames by {err:.2f} on average: its states "
                            f"are unreliable (train longer, or add labels)", "states-unreliable"))
    return out


def label_warnings(views) -> list[tuple[str, str]]:
    """(message, cause) for each object whose state labels on the training frames are too sparse for Lvar to pin
    its states down (interreal.dataset.label_shortage: the figures `interreal validate` warns with)."""
    counts = {name: int(views.given[views.train, k].sum()) for k, name in enumerate(views.names)}
    return [(m.replace(" frames (", " training frames (", 1), "few-labels")
            for _, m in label_shortage(counts, len(views.train))]
