"""Ray marching with two proposal levels (K-planes / mip-NeRF 360 style) and volume rendering.

Every level asks the model where each sample is read (`LiveSceneModel.place`: its owner, from the interaction
probability field; the owner's frame when it is a rigid part; the owner's interaction value k); proposal densities
and the final field are read there, at (x, y, z, k).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from .config import SamplerConfig
from .field import LiveSceneModel


@dataclass
class RenderOut:
    rgb: torch.Tensor  # (R, 3)
    depth: torch.Tensor  # (R,) expected distance along the (unit) ray
    acc: torch.Tensor  # (R,)
    logits: torch.Tensor | None  # (R, max_objects + 1) rendered with detached weights
    weights: torch.Tensor  # (R, S) final level
    edges: torch.Tensor  # (R, S + 1) final level, in ray distance
    proposals: list[tuple[torch.Tensor, torch.Tensor]] = field(default_factory=list)  # (edges, weights) per level
    near: torch.Tensor | None = None
    far: torch.Tensor | None = None


def ray_box(origins: torch.Tensor, dirs: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
            near_min: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry / exit distances of rays in an axis-aligned box; rays that miss get a zero-length span."""
    inv = 1.0 / torch.where(dirs.abs() < 1e-9, torch.full_like(dirs, 1e-9), dirs)
    t0 = (lo - origins) * inv
    t1 = (hi - origins) * inv
    near = torch.minimum(t0, t1).amax(-1).clamp(min=near_min)
    far = torch.maximum(t0, t1).amin(-1)
    far = torch.maximum(far, near + 1e-4)
    return near, far


def uniform_edges(near: torch.Tensor, far: torch.Tensor, n: int, gen: torch.Generator | None) -> torch.Tensor:
    u = torch.linspace(0, 1, n + 1, device=near.device).expand(near.shape[0], n + 1)
    if gen is not None:  # stratified jitter, endpoints kept
        mid = (u[:, 1:] + u[:, :-1]) * 0.5
        jit = (torch.rand(near.shape[0], n - 1, device=near.device, generator=gen) - 0.5) / n
        u = torch.cat([u[:, :1], mid[:, :-1] + 0.5 / n + jit, u[:, -1:]], -1) if n > 1 else u
    return near[:, None] + (far - near)[:, None] * u


def pdf_edges(edges: torch.Tensor, weights: torch.Tensor, n: int, gen: torch.Generator | None) -> torch.Tensor:
    """Inverse-CDF resampling of n bins from a piecewise-constant density over `edges`."""
    w = weights + 1e-5
    pdf = w / w.sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, -1)], -1).clamp(max=1.0)
    r = edges.shape[0]
    if gen is not None:
        u = (torch.arange(n + 1, device=edges.device) + torch.rand(r, n + 1, device=edges.device, generator=gen))
        u = (u / (n + 1)).clamp(0, 1)
        u = torch.sort(u, -1).values
        u = torch.cat([torch.zeros_like(u[:, :1]), u[:, 1:-1], torch.ones_like(u[:, :1])], -1)
    else:
        u = torch.linspace(0, 1, n + 1, device=edges.device).expand(r, n + 1).contiguous()
    idx = torch.searchsorted(cdf.contiguous(), u, right=True)
    below = (idx - 1).clamp(0, edges.shape[1] - 1)
    above = idx.clamp(0, edges.shape[1] - 1)
    c0, c1 = cdf.gather(1, below), cdf.gather(1, above)
    b0, b1 = edges.gather(1, below), edges.gather(1, above)
    t = ((u - c0) / (c1 - c0).clamp(min=1e-8)).clamp(0, 1)
    out = b0 + t * (b1 - b0)
    return torch.sort(out, -1).values.detach()


def volume_weights(sigma: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    delta = edges[:, 1:] - edges[:, :-1]
    sd = sigma * delta
    trans = torch.exp(-torch.cat([torch.zeros_like(sd[:, :1]), torch.cumsum(sd, -1)[:, :-1]], -1))
    return (1 - torch.exp(-sd)) * trans


def anneal_power(step: int, cfg: SamplerConfig) -> float:
    frac = min(max(step / max(cfg.anneal_steps, 1), 0.0), 1.0)
    b = cfg.anneal_slope
    return (b * frac) / ((b - 1) * frac + 1)


def render_logits(logits: torch.Tensor, weights: torch.Tensor, slot_mask: torch.Tensor, mode: str) -> torch.Tensor:
    """Per-pixel object logits (R, C) from per-sample logits (R, S, C) and weights (R, S) (detached unless the mask
    losses may shape the density: `ModelConfig.mask_shapes`).

    "probs": log of the weighted per-sample probabilities, the light that leaves the box counted as background,
    so the mask losses reach the very samples whose probabilities pick k. "logits": weighted logits (official)."""
    if mode == "logits":
        return pixel_logits((weights[..., None] * logits).sum(1), None, slot_mask, mode)
    acc = weights.sum(1, keepdim=True).detach()
    if weights.requires_grad:  # only where along the ray the light comes from may change, not how much of it:
        # else "transparent" is the cheapest background
        weights = weights / weights.sum(1, keepdim=True).clamp(min=1e-6) * acc
    return pixel_logits((weights[..., None] * torch.softmax(logits, -1)).sum(1), acc[:, 0], slot_mask, mode)


def pixel_logits(mixed: torch.Tensor, acc: torch.Tensor | None, slot_mask: torch.Tensor, mode: str) -> torch.Tensor:
    """Pixel object logits (R, C) from the weighted sum over a ray's samples `mixed` (R, C): of the logits in mode
    "logits"; of the probabilities in mode "probs", the light that leaves the box (1 - acc (R,)) counted as
    background (`render_logits`; the fast renderer sums the samples itself)."""
    if mode == "logits":
        return mixed.masked_fill(~slot_mask, -1e4)
    p = torch.cat([mixed[:, :-1], mixed[:, -1:] + (1 - acc[:, None]).clamp(min=0)], -1)
    return torch.log(p.clamp(min=1e-6)).masked_fill(~slot_mask, -1e4)


def render_rays(model: LiveSceneModel, origins: torch.Tensor, dirs: torch.Tensor, values: torch.Tensor,
                box: tuple[torch.Tensor, torch.Tensor], cfg: SamplerConfig, *, step: int = 10 ** 9,
                gen: torch.Generator | None = None, with_logits: bool = True) -> RenderOut:
    """origins, dirs (R, 3) world (dirs unit length); values (R, max_objects) states per ray.

    `gen` given = training (jittered samples, annealed proposal weights); None = deterministic rendering."""
    lo, hi = box
    near, far = ray_box(origins, dirs, lo, hi, cfg.near)

    def points(edges: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """World points (R*S, 3) at the bins' middles, with their ray directions and states."""
        mid = 0.5 * (edges[:, 1:] + edges[:, :-1])
        s = mid.shape[1]
        pts = origins[:, None, :] + dirs[:, None, :] * mid[..., None]
        return pts.reshape(-1, 3), dirs.repeat_interleave(s, 0), values.repeat_interleave(s, 0)

    r = origins.shape[0]
    edges = uniform_edges(near, far, cfg.proposal_samples[0], gen)
    proposals = []
    power = anneal_power(step, cfg) if gen is not None else 1.0
    for level, prop in enumerate(model.proposals):
        pts, d, vals = points(edges)
        if model.proposals_read_k:
            with torch.no_grad():
                place = model.place(pts, d, vals, box, grad_logits=False)
            xyz, k = place.xyz, place.k
        else:
            xyz, k = model.to_field(pts, box), None
        sigma = prop(xyz, k).view(r, -1)
        w = volume_weights(sigma, edges)
        proposals.append((edges, w))
        n_next = cfg.proposal_samples[level + 1] if level + 1 < len(model.proposals) else cfg.samples
        edges = pdf_edges(edges, w.detach() ** power, n_next, gen)
    pts, d, vals = points(edges)
    place = model.place(pts, d, vals, box, grad_logits=with_logits)
    s = edges.shape[1] - 1
    sigma, rgb = model.field(place.xyz, place.k, place.dirs)
    w = volume_weights(sigma.view(r, s), edges)
    acc = w.sum(-1)
    mid = 0.5 * (edges[:, 1:] + edges[:, :-1])
    color = (w[..., None] * rgb.view(r, s, 3)).sum(1) + (1 - acc)[:, None] * model.background()
    depth = (w * mid).sum(-1) + (1 - acc) * far
    rendered_logits = None
    if with_logits:
        rendered_logits = render_logits(place.logits.view(r, s, -1), w if model.mask_shapes else w.detach(),
                                        model.slot_mask, model.mask_render)
    return RenderOut(rgb=color, depth=depth, acc=acc, logits=rendered_logits, weights=w, edges=edges,
                     proposals=proposals, near=near, far=far)
