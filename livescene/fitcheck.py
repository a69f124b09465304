"""What a training run warns about: too few state labels before it starts, a poor fit or learned states that miss
the labels after it ends (each warning goes to the console and to RUN/reports/train.json with its cause)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from interreal.dataset import label_shortage

from .data import measured_counts, measured_targets


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
    """Warn when the learned states miss what Lvar fits them to (the labels, or where `interreal motions` measured
    a frame's state, that state: `data.measured_targets`): on training frames (not fitted) or on held-out frames
    (never trained on, so their error estimates the error on every other frame). Labels that disagree with the
    measured states are `interreal motions`' warning (flagged labels), not a failed fit."""
    labels, given_all = views.dataset.label_matrix()
    measured = getattr(views, "measured_states", False) and bool(measured_counts(views))
    if measured:
        labels, given_all = measured_targets(views.dataset, labels, given_all)
    what = "labelled or measured" if measured else "labelled"
    out = []
    for k, name in enumerate(views.names):
        for which, frames in (("training", views.train), ("held-out", views.held_out)):
            idx = [i for i in frames if given_all[i, k]]
            if not idx:
                continue
            err = float(np.abs(values[idx, k] - labels[idx, k]).mean())
            if err > MAX_STATE_ERROR:
                out.append((f"'{name}': learned states miss the {what} {which} frames by {err:.2f} on average: its "
                            f"states are unreliable (train longer, or add labels)", "states-unreliable"))
    return out


def label_warnings(views) -> list[tuple[str, str]]:
    """(message, cause) for each object whose state labels on the training frames are too sparse for Lvar to pin
    its states down (interreal.dataset.label_shortage: the figures `interreal validate` warns with)."""
    counts = {name: int(views.given[views.train, k].sum()) for k, name in enumerate(views.names)}
    return [(m.replace(" frames (", " training frames (", 1), "few-labels")
            for _, m in label_shortage(counts, len(views.train))]
