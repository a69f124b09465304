"""Fast ray marching of a trained run at fixed object states: what `render.render_view` uses unless asked for the
exact renderer (`fast=False`, `--exact`).

The exact renderer (`sampler.render_rays`) reads every sample of every level (68 per ray on the CPU preset), and
for each asks the probability field who owns it and turns it into each rigid part's rest frame with a per-sample
rotation. At fixed states most of that is the same for every sample, and most samples lie in air or behind a
surface. Here the samples are placed exactly as there (the same proposal levels and inverse-CDF resampling), and:
- what depends only on the states is computed once per render (`FixedStates`): each rigid part's rest transform
  (one 3x3 matrix) and its hull as one flat table (the gate: one transform and one lookup a sample), the
  probability field's first layer with the states folded into its bias;
- in a scene whose objects all move rigidly, a sample outside every part's hull belongs to the background without
  asking the probability field (the hull gate alone decides it: its object logits are `GATED_LOGIT`), and the
  rendered object logits sum only the other samples' softmax (`pixel_logits`);
- what depends only on the ray is computed once per ray: the colour net's view-direction half (`RayColor`);
- samples in cells of the occupancy grid (`livescene.occupancy`) whose densest state is below its threshold are
  not read (density 0): empty-space skipping;
- each level is marched front to back in segments, and a ray whose transmittance fell below `TERMINATE_T` stops
  (early ray termination); the colour is read only for samples that carry weight.
Only the skipped samples' density (below the grid threshold) and the light behind 1e-4 transmittance differ.

Not folded, though exact: the k-planes at the few k a render reads (the background's, each state, 0) into feature
lines per state. On the CPU the lines cost as many grid_sample taps as the planes they replace (stacked as rows), and
the x and y lines folded into one plane (their product is bilinear) made a K-planes read 15 % faster at 32 and 64
cells and 9 % slower at 128 (5 % over the field's three scales, 2 % of a render; 1 thread): not worth a second
code path for the field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import torch

from .articulation import KIND_CODES, rotate
from .config import SamplerConfig
from .field import GATED_LOGIT, LiveSceneModel
from .sampler import pdf_edges, pixel_logits, ray_box, uniform_edges, volume_weights

TERMINATE_T = 1e-4  # a ray stops once less than this share of its light can still come from further on
SEGMENT = 8  # samples per ray read between two termination checks
COLOR_MIN_WEIGHT = 1e-5  # samples lighter than this get no colour read (at most 20 x 1e-5 of a pixel's value)


@dataclass
class MarchStats:
    """What a render read: sample slots over all levels, density reads, colour reads (tests and benchmarks)."""

    rays: int = 0
    samples: int = 0
    evaluated: int = 0
    colored: int = 0
    per_level: list[int] = field(default_factory=list)

    def as_dict(self) -> dict[str, float]:
        return {"rays": self.rays, "samples": self.samples, "evaluated": self.evaluated, "colored": self.colored,
                "evaluated_per_ray": self.evaluated / max(self.rays, 1)}


def rest_transform(model: LiveSceneModel, obj: int, value: float | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(rt (3, 3), offset (3,)) with rest = world @ rt + offset for object `obj`'s rigid motion at state `value`
    (`PartMotions.to_rest` for one state: the same Rodrigues turn, built once as a matrix)."""
    m = model.motions
    value = torch.as_tensor(value, dtype=m.axis.dtype, device=m.axis.device)
    amount = value * m.range[obj]
    kind = int(m.kind[obj])
    angle = -amount if kind == KIND_CODES["hinge"] else amount * 0
    shift = amount * m.axis[obj] if kind == KIND_CODES["slide"] else torch.zeros_like(m.axis[obj])
    eye = torch.eye(3, dtype=m.axis.dtype, device=m.axis.device)
    rt = rotate(eye, m.axis[obj].expand(3, 3), angle.expand(3))  # row i: R e_i, so v @ rt = R v
    return rt, m.origin[obj] - m.origin[obj] @ rt - shift


class FixedStates:
    """Everything a render needs that depends only on the states (M,) it is drawn at: computed once per render."""

    def __init__(self, model: LiveSceneModel, values: torch.Tensor):
        self.model = model
        self.values = values.reshape(-1)  # (max_objects,)
        n = model.n_objects
        self.rigid = model.motions.rigid(n) if model.motions is not None else []
        self.nonrigid = any(o not in self.rigid for o in range(n))
        keep = torch.ones_like(self.values)
        keep[self.rigid] = 0
        self.bias_world = model.prob.folded_bias(self.values * keep)
        self.bias_rest = model.prob.folded_bias(torch.zeros_like(self.values))
        moves = [rest_transform(model, o, self.values[o]) for o in self.rigid]
        self.rt = torch.stack([m[0] for m in moves]) if moves else None  # (K, 3, 3)
        self.offset = torch.stack([m[1] for m in moves]) if moves else None  # (K, 3)
        self.hulls = [model.motions.padded_hull(o) for o in self.rigid]  # padded once per render
        # the hull gate decides ownership alone only where no object is read in the world frame and a sample
        # below the rejection threshold is the background's
        self.gate_decides = not self.nonrigid and model.cfg.reject_threshold > 0 and n > 0
        slots = model.slot_mask
        self.default_logits = torch.where(slots, torch.full_like(slots, GATED_LOGIT, dtype=torch.float32),
                                          torch.full_like(slots, -1e4, dtype=torch.float32)).to(self.values.device)
        self.default_logits[-1] = 0.0  # a sample outside every hull: background, object logits gated

    def rest(self, j: int, pts: torch.Tensor) -> torch.Tensor:
        """World points (N, 3) -> the j-th rigid part's rest frame at these states."""
        return torch.addmm(self.offset[j], pts, self.rt[j])

    def gate(self, pts: torch.Tensor) -> torch.Tensor:
        """(K, N) bool: inside each rigid part's hull (`PartMotions.inside_one` of the rest points)."""
        m = self.model.motions
        return torch.stack([m.inside_one(o, self.rest(j, pts), self.hulls[j]) for j, o in enumerate(self.rigid)])

    def place(self, pts: torch.Tensor, dirs: torch.Tensor, box: tuple[torch.Tensor, torch.Tensor],
              want_logits: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """`LiveSceneModel.place` at these states: (field xyz, view dirs, k, logits or None) of world samples."""
        p = self.place_sparse(pts, dirs, box, want_logits)
        logits = None
        if want_logits:
            logits = self.default_logits.expand(pts.shape[0], -1).clone() if p.decided is not None else p.logits
            if p.decided is not None:
                logits[p.decided] = p.logits
        return p.xyz, p.view, p.k, logits

    def place_sparse(self, pts: torch.Tensor, dirs: torch.Tensor, box: tuple[torch.Tensor, torch.Tensor],
                     want_logits: bool = True) -> Placed:
        """`place` with the logits only of the samples the probability field decides (`Placed.decided`; the
        others have `default_logits`), so a renderer can leave their softmax out."""
        model = self.model
        xyz = model.to_field(pts, box)
        n = pts.shape[0]
        if not self.rigid:
            logits = model.prob.forward_folded(xyz, self.bias_world).masked_fill(~model.slot_mask, -1e4)
            return Placed(xyz, dirs, self._k(logits)[0], logits, None, None)
        gate = self.gate(pts)
        ia = gate.any(0).nonzero()[:, 0] if self.gate_decides else torch.arange(n, device=pts.device)
        k = torch.full((n,), float(model.background_k), device=pts.device, dtype=pts.dtype)
        group = torch.zeros(n, dtype=torch.long, device=pts.device)
        la = None
        if len(ia):  # the samples whose owner the probability field decides
            la = model.prob.forward_folded(xyz[ia], self.bias_world)
            la[:, self.rigid] = GATED_LOGIT
            gate_a = gate[:, ia]
            sel = [g.nonzero()[:, 0] for g in gate_a]
            sizes = [len(x) for x in sel]
            if sum(sizes):
                inputs = torch.cat([model.to_field(self.rest(j, pts[ia[x]]), box) for j, x in enumerate(sel)])
                raw = model.prob.forward_folded(inputs, self.bias_rest).split(sizes)
                for j, o in enumerate(self.rigid):
                    la[sel[j], o] = raw[j][:, o]
            la = la.masked_fill(~model.slot_mask, -1e4)
            k[ia], group[ia] = self._k(la)
        view = dirs
        moved = (group > 0).nonzero()[:, 0]
        if len(moved):
            xyz, view = xyz.clone(), dirs.clone()
            for j in range(len(self.rigid)):
                m = moved[group[moved] == j + 1]
                if len(m):
                    xyz[m] = model.to_field(self.rest(j, pts[m]), box)
                    view[m] = dirs[m] @ self.rt[j]
        if la is None:
            la = self.default_logits.new_zeros(0, self.default_logits.shape[0])
        return Placed(xyz, view, k, la if want_logits else None, ia if self.gate_decides else None, moved)

    def _k(self, logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(k (N,), owner group (N,): 0 world, j + 1 the j-th rigid part) by `select_k`'s rule."""
        model = self.model
        idx, owned = model.owner(logits)
        k = torch.where(owned, self.values[idx], torch.full_like(self.values[idx], model.background_k))
        if not self.rigid:
            return k, None
        group_of = torch.zeros(self.values.shape[0], dtype=torch.long, device=logits.device)
        group_of[self.rigid] = torch.arange(1, len(self.rigid) + 1, device=logits.device)
        group = torch.where(owned, group_of[idx], torch.zeros_like(idx))
        if model.cfg.part_k == "rest":
            k = torch.where(group > 0, torch.zeros_like(k), k)
        return k, group


@dataclass
class Placed:
    """`FixedStates.place_sparse`: where the fields read each sample, and the logits of those the probability
    field decided (`decided`: their sample indices; None = every sample's logits)."""

    xyz: torch.Tensor  # (N, 3) field coordinates
    view: torch.Tensor  # (N, 3) view directions in the owner's frame
    k: torch.Tensor  # (N,)
    logits: torch.Tensor | None  # (len(decided) or N, C), None when not asked for
    decided: torch.Tensor | None  # (D,) sample indices of `logits`; None: all samples
    moved: torch.Tensor | None  # (P,) samples read in a rigid part's frame (their view turned); None: none can be


Reader = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]  # (points (P, 3), ray index (P,)) -> density (P,)


def march_level(origins: torch.Tensor, dirs: torch.Tensor, edges: torch.Tensor, read: Reader,
                occupied: Callable[[torch.Tensor], torch.Tensor] | None, stats: MarchStats | None,
                terminate: float = TERMINATE_T) -> tuple[torch.Tensor, list[tuple[torch.Tensor, torch.Tensor]]]:
    """Densities (R, S) at the bins' middles, read front to back in segments: only in occupied cells and only
    while the ray's transmittance is above `terminate` (elsewhere 0). Also the (ray, sample) indices read."""
    mid = 0.5 * (edges[:, 1:] + edges[:, :-1])
    delta = edges[:, 1:] - edges[:, :-1]
    r, s = mid.shape
    pts = origins[:, None, :] + dirs[:, None, :] * mid[..., None]
    occ = occupied(pts.reshape(-1, 3)).view(r, s) if occupied is not None else None
    sigma = torch.zeros(r, s, device=edges.device, dtype=edges.dtype)
    tau = torch.zeros(r, device=edges.device, dtype=edges.dtype)
    stop = -math.log(terminate)
    alive = torch.ones(r, dtype=torch.bool, device=edges.device)
    read_at = []
    for a in range(0, s, SEGMENT):
        b = min(a + SEGMENT, s)
        sel = alive[:, None].expand(r, b - a) if occ is None else occ[:, a:b] & alive[:, None]
        ri, si = sel.nonzero(as_tuple=True)
        si = si + a
        if len(ri):
            sigma[ri, si] = read(pts[ri, si], ri)
            read_at.append((ri, si))
        if stats is not None:
            stats.evaluated += len(ri)
        if b < s:
            tau = tau + (sigma[:, a:b] * delta[:, a:b]).sum(1)
            alive = alive & (tau < stop)
            if not bool(alive.any()):
                break
    if stats is not None:
        stats.samples += r * s
        stats.per_level.append(sum(len(x[0]) for x in read_at))
    return sigma, read_at


@torch.no_grad()
def march_rays(model: LiveSceneModel, fixed: FixedStates, origins: torch.Tensor, dirs: torch.Tensor,
               box: tuple[torch.Tensor, torch.Tensor], cfg: SamplerConfig,
               occupied: Callable[[torch.Tensor], torch.Tensor] | None = None, with_logits: bool = True,
               stats: MarchStats | None = None, terminate: float = TERMINATE_T) -> dict[str, torch.Tensor]:
    """`sampler.render_rays` (deterministic, at fixed states) with skipping: rgb (R, 3), depth (R,) along the
    ray, acc (R,), logits (R, max_objects + 1) or None. `occupied(points (P, 3)) -> bool (P,)`: the grid test;
    `terminate`: the transmittance at which a ray stops (larger: faster, the light left is the background's)."""
    lo, hi = box
    near, far = ray_box(origins, dirs, lo, hi, cfg.near)
    r = origins.shape[0]
    if stats is not None:
        stats.rays += r
    edges = uniform_edges(near, far, cfg.proposal_samples[0], None)
    for level, prop in enumerate(model.proposals):
        if model.proposals_read_k:
            def read(pts, ri, prop=prop):
                xyz, _, k, _ = fixed.place(pts, dirs[ri], box, want_logits=False)
                return prop(xyz, k)
        else:
            def read(pts, ri, prop=prop):
                return prop(model.to_field(pts, box), None)
        sigma, _ = march_level(origins, dirs, edges, read, occupied, stats, terminate)
        w = volume_weights(sigma, edges)
        n_next = cfg.proposal_samples[level + 1] if level + 1 < len(model.proposals) else cfg.samples
        edges = pdf_edges(edges, w, n_next, None)
    kept: list[tuple[torch.Tensor, Placed]] = []  # (the sigma net's output, placement) per read

    def read_final(pts, ri):
        placed = fixed.place_sparse(pts, dirs[ri], box, want_logits=with_logits)
        sigma, h = model.field.density(placed.xyz, placed.k)
        kept.append((h, placed))
        return sigma

    sigma, read_at = march_level(origins, dirs, edges, read_final, occupied, stats, terminate)
    s = sigma.shape[1]
    w = volume_weights(sigma, edges)
    acc = w.sum(-1)
    rgb = torch.zeros(r, s, 3, device=w.device, dtype=w.dtype)
    term = RayColor(model, dirs)
    n_cls = model.slot_mask.shape[0]
    mixed = torch.zeros(r, n_cls, device=w.device, dtype=w.dtype) if with_logits else None  # sum of w x probs (logits)
    decided_w = torch.zeros(r, device=w.device, dtype=w.dtype)  # ... the weight that has its own logits
    for (ri, si), (h, placed) in zip(read_at, kept):
        ws = w[ri, si]
        if mixed is not None:
            rows = ri if placed.decided is None else ri[placed.decided]
            wd = ws if placed.decided is None else ws[placed.decided]
            lg = placed.logits if model.mask_render == "logits" else torch.softmax(placed.logits, -1)
            mixed.index_add_(0, rows, wd[:, None] * lg)
            decided_w.index_add_(0, rows, wd)
        heavy = (ws > COLOR_MIN_WEIGHT).nonzero()[:, 0]
        if len(heavy):
            rgb[ri[heavy], si[heavy]] = term.color(h[heavy], ri[heavy], heavy, placed)
            if stats is not None:
                stats.colored += len(heavy)
    mid = 0.5 * (edges[:, 1:] + edges[:, :-1])
    color = (w[..., None] * rgb).sum(1) + (1 - acc)[:, None] * model.background()
    depth = (w * mid).sum(-1) + (1 - acc) * far
    out_logits = None
    if mixed is not None:  # the samples without logits of their own have `default_logits`
        undecided = (acc - decided_w).clamp(min=0)[:, None]
        default = fixed.default_logits if model.mask_render == "logits" else torch.softmax(fixed.default_logits, -1)
        out_logits = pixel_logits(mixed + undecided * default, acc, model.slot_mask, model.mask_render)
    return {"rgb": color, "depth": depth, "acc": acc, "logits": out_logits}


class RayColor:
    """The colour net with its view-direction half done once per ray (`RadianceField.view_term`): the samples of a
    ray share the direction (a sample read in a rigid part's frame, its direction turned, gets its own)."""

    def __init__(self, model: LiveSceneModel, dirs: torch.Tensor):
        self.field = model.field
        self.per_ray = self.field.view_term(dirs)  # (R, hidden)

    def color(self, h: torch.Tensor, rays: torch.Tensor, which: torch.Tensor, placed: Placed) -> torch.Tensor:
        """RGB (P, 3) of samples with sigma-net outputs h (P, 1 + geo) on rays `rays` (P,); `which` (P,): their
        positions in `placed` (whose `moved` samples read a turned direction)."""
        view = self.per_ray[rays]
        if placed.moved is not None and len(placed.moved):
            turned = torch.zeros(len(placed.view), dtype=torch.bool, device=h.device)
            turned[placed.moved] = True
            sel = turned[which].nonzero()[:, 0]
            if len(sel):
                view[sel] = self.field.view_term(placed.view[which[sel]])
        return self.field.color_from(view, h)
