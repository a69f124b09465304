"""Losses and regularisers of LiveScene (weights in `LossConfig`).

colour MSE, depth MSE (when depth exists), focal loss on rendered object masks, repulsion between rays of
different objects, Lvar (MSE on labelled (frame, object) pairs only), Laplacian smoothness along k, plane TV,
L1 of k-planes towards 1, proposal interlevel and distortion losses, smoothness of the per-frame variable
along time (not across its feature channels, as the official code does by mistake), and the per-frame appearance
codes pulled to identity (`livescene.appearance`).

`TERMS` is the table the trainer composes the loss from: each term's name is its weight in `LossConfig`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Callable

import torch
import torch.nn.functional as F

from .config import LossConfig
from .field import KPlanes, LiveSceneModel
from .sampler import RenderOut


def focal_loss(logits: torch.Tensor, target: torch.Tensor, alpha: float = 0.5, gamma: float = 1.5) -> torch.Tensor:
    """Focal cross-entropy of rendered logits (R, C) against class ids (R,); rays with target < 0 are ignored."""
    valid = target >= 0
    if not bool(valid.any()):
        return logits.sum() * 0.0
    ce = F.cross_entropy(logits[valid], target[valid], reduction="none")
    return (alpha * (1 - torch.exp(-ce)) ** gamma * ce).mean()


def repulsion_loss(logits: torch.Tensor, target: torch.Tensor, k: float, gen: torch.Generator | None) -> torch.Tensor:
    """Random disjoint ray pairs with different labels: push their rendered logits at least ~K apart (L1, over
    the channels where their one-hot labels differ): ELU(K - d) + 1."""
    valid = torch.nonzero(target >= 0)[:, 0]
    n = valid.numel() // 2
    if n == 0:
        return logits.sum() * 0.0
    perm = valid[torch.randperm(valid.numel(), generator=gen, device="cpu").to(valid.device)]
    a, b = perm[:n], perm[n: 2 * n]
    diff = target[a] != target[b]
    if not bool(diff.any()):
        return logits.sum() * 0.0
    a, b = a[diff], b[diff]
    # the one-hots differ in exactly the two channels of the two labels
    la, lb = logits[a], logits[b]
    d = 0.5 * ((la.gather(1, target[a, None]) - lb.gather(1, target[a, None])).abs()
               + (la.gather(1, target[b, None]) - lb.gather(1, target[b, None])).abs())[:, 0]
    return (F.elu(k - d) + 1.0).mean()


def var_loss(pred: torch.Tensor, labels: torch.Tensor, given: torch.Tensor) -> torch.Tensor:
    """Lvar: MSE between predicted and labelled values over the given (ray, object) pairs only."""
    if not bool(given.any()):
        return pred.sum() * 0.0
    return ((pred - labels) ** 2)[given].mean()


def time_smoothness(line: torch.Tensor) -> torch.Tensor:
    """Mean squared difference between neighbouring nodes of the per-frame variable line (N, C) along time."""
    if line.shape[0] < 2:
        return line.sum() * 0.0
    return ((line[1:] - line[:-1]) ** 2).mean()


def plane_tv(grid: KPlanes) -> torch.Tensor:
    """TV on spatial planes (both axes) and on k-planes along their spatial axis only."""
    total = 0.0
    for p in grid.spatial:
        total = total + ((p[..., 1:, :] - p[..., :-1, :]) ** 2).mean() + ((p[..., 1:] - p[..., :-1]) ** 2).mean()
    for p in grid.kplanes:
        total = total + ((p[..., 1:] - p[..., :-1]) ** 2).mean()
    return total * 2.0 / max(len(grid.spatial), 1)


def k_smoothness(grid: KPlanes) -> torch.Tensor:
    """Laplacian (second difference) along the interaction axis of the k-planes."""
    total = 0.0
    for plane in grid.kplanes:
        p = grid.state_rows(plane)  # the background node is no state: no smoothness across into it
        if p.shape[2] >= 3:
            total = total + ((p[:, :, 2:] - 2 * p[:, :, 1:-1] + p[:, :, :-2]) ** 2).mean()
    return total / max(len(grid.kplanes), 1) if len(grid.kplanes) else torch.zeros(())


def l1_kplanes(grid: KPlanes) -> torch.Tensor:
    if not len(grid.kplanes):
        return torch.zeros(())
    return sum((1 - p).abs().mean() for p in grid.kplanes) / len(grid.kplanes)


def _outer(t0: torch.Tensor, t1: torch.Tensor, w1: torch.Tensor) -> torch.Tensor:
    """Upper bound of the weight each interval of t0 can carry given the histogram (t1, w1) (mip-NeRF 360)."""
    cw = torch.cat([torch.zeros_like(w1[:, :1]), torch.cumsum(w1, -1)], -1)
    n1 = w1.shape[-1]
    lo = (torch.searchsorted(t1[:, :-1].contiguous(), t0[:, :-1].contiguous(), right=True) - 1).clamp(0, n1 - 1)
    hi = torch.searchsorted(t1[:, 1:].contiguous(), t0[:, 1:].contiguous(), right=True).clamp(0, n1 - 1)
    return cw[:, 1:].gather(1, hi) - cw[:, :-1].gather(1, lo)


def interlevel_loss(edges: torch.Tensor, weights: torch.Tensor,
                    proposals: list[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
    """Proposal weights must bound the final weights from above (final level detached)."""
    t, w = edges.detach(), weights.detach()
    total = 0.0
    for pe, pw in proposals:
        bound = _outer(t, pe.detach(), pw)
        total = total + ((w - bound).clamp(min=0) ** 2 / (w + 1e-7)).sum(-1).mean()
    return total


def distortion_loss(edges: torch.Tensor, weights: torch.Tensor, near: torch.Tensor, far: torch.Tensor) -> torch.Tensor:
    """mip-NeRF 360 distortion loss on ray distance normalised to [0, 1] between near and far."""
    s = (edges - near[:, None]) / (far - near).clamp(min=1e-6)[:, None]
    mid = 0.5 * (s[:, 1:] + s[:, :-1])
    width = s[:, 1:] - s[:, :-1]
    wm = weights * mid
    w_cum = torch.cumsum(weights, -1)
    wm_cum = torch.cumsum(wm, -1)
    inter = 2 * (wm[:, 1:] * w_cum[:, :-1] - weights[:, 1:] * wm_cum[:, :-1]).sum(-1)
    intra = (weights ** 2 * width).sum(-1) / 3.0
    return (inter + intra).mean()


def trimmed_mse(pred: torch.Tensor, target: torch.Tensor, trim: float) -> torch.Tensor:
    """Mean squared colour error of (R, 3) rays less the `trim` share with the largest error (RobustNeRF's trimmed
    L2, per batch): what the scene cannot explain at all (a hand, a passer-by no one painted) stops pulling on it.
    Early in training every error is large and the cut moves with them (a quantile, not a fixed threshold)."""
    err = ((pred - target) ** 2).mean(-1)
    if trim <= 0 or err.numel() < 2:
        return err.mean()
    keep = err.detach() <= torch.quantile(err.detach(), 1.0 - trim)
    return (err * keep).sum() / keep.sum().clamp_min(1)


def psnr(mse: torch.Tensor | float) -> float:
    m = float(mse)
    return 100.0 if m <= 1e-10 else -10.0 * math.log10(m)


# ----------------------------------------------------------------------------------------------------------------
# The table the loss is composed from
# ----------------------------------------------------------------------------------------------------------------
@dataclass
class LossInputs:
    """What the terms read for one training batch."""

    model: LiveSceneModel
    out: RenderOut  # the batch's rays rendered (`sampler.render_rays`)
    batch: dict[str, torch.Tensor]  # `RayData.sample`: rgb, mask, labels, given, t ...
    values: torch.Tensor  # (R, slots) object values of each ray's frame
    gen: torch.Generator  # CPU generator (the repulsion's random pairs)

    @functools.cached_property
    def target(self) -> torch.Tensor:
        """Class id per ray for the probability field: objects 0..M-1, background in the last slot."""
        target = self.batch["mask"].clone()
        target[target == self.model.n_objects] = self.model.cfg.max_objects
        return target


Term = Callable[[LossInputs, LossConfig], "torch.Tensor | None"]  # None: nothing to compare this batch


def _with_logits(x: LossInputs, loss: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]) -> torch.Tensor | None:
    return None if x.out.logits is None else loss(x.out.logits, x.target)


def _proposal_sum(x: LossInputs, loss: Callable[[KPlanes], torch.Tensor]):
    return sum(loss(p.grid) for p in x.model.proposals)


# name (= its weight in LossConfig) -> (term, is a regulariser: evaluated every `reg_every` steps, weighted up by it)
TERMS: dict[str, tuple[Term, bool]] = {
    "rgb": (lambda x, w: ((x.out.rgb - x.batch["rgb"]) ** 2).mean(), False),
    "rgb_trimmed": (lambda x, w: trimmed_mse(x.out.rgb, x.batch["rgb"], w.trim), False),
    "interlevel": (lambda x, w: interlevel_loss(x.out.edges, x.out.weights, x.out.proposals)
                   if x.out.proposals else None, False),
    "distortion": (lambda x, w: distortion_loss(x.out.edges, x.out.weights, x.out.near, x.out.far), False),
    "focal": (lambda x, w: _with_logits(x, lambda lg, t: focal_loss(lg, t, w.focal_alpha, w.focal_gamma)), False),
    "repulsion": (lambda x, w: _with_logits(x, lambda lg, t: repulsion_loss(lg, t, w.repulsion_k, x.gen)), False),
    "var": (lambda x, w: var_loss(x.values[:, : x.model.n_objects], x.batch["labels"], x.batch["given"])
            if x.model.n_objects else None, False),
    "var_smooth": (lambda x, w: time_smoothness(x.model.variable.line), False),
    "k_smooth": (lambda x, w: k_smoothness(x.model.field.grid), True),
    "k_smooth_proposal": (lambda x, w: _proposal_sum(x, k_smoothness), True),
    "l1_k": (lambda x, w: l1_kplanes(x.model.field.grid), True),
    "l1_k_proposal": (lambda x, w: _proposal_sum(x, l1_kplanes), True),
    "plane_tv": (lambda x, w: plane_tv(x.model.field.grid), True),
    "plane_tv_proposal": (lambda x, w: _proposal_sum(x, plane_tv), True),
    "plane_tv_prob": (lambda x, w: plane_tv(x.model.prob.grid), True),
    "appearance": (lambda x, w: x.model.appearance.penalty(x.batch["frame"])
                   if x.model.appearance is not None else None, False),
}
ALWAYS = {"rgb"}  # computed even at weight 0: its value is the PSNR the logs report


def loss_terms(x: LossInputs, weights: LossConfig, regularise: bool = True) -> dict[str, torch.Tensor]:
    """The terms with a non-zero weight (and the regularisers only when `regularise`), in `TERMS` order."""
    terms = {}
    for name, (term, is_reg) in TERMS.items():
        if (is_reg and not regularise) or (name not in ALWAYS and not getattr(weights, name)):
            continue
        value = term(x, weights)
        if value is not None:
            terms[name] = value
    return terms


def total_loss(terms: dict[str, torch.Tensor], weights: LossConfig, reg_every: int = 1) -> torch.Tensor:
    """The weighted sum; a regulariser evaluated every `reg_every` steps counts `reg_every` times."""
    w = vars(weights)
    return sum(w[k] * (reg_every if TERMS[k][1] else 1) * v for k, v in terms.items())
