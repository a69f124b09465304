"""The LiveScene model: a 4-D K-planes radiance field whose fourth axis is the interaction value k,
an interaction probability field that tells each 3-D sample which object it belongs to, proposal density
fields, and the learnable per-frame variable that gives each frame's object states.

Coordinates given to the fields are normalised to [-1, 1] by the scene box, then warped per axis towards where the
SfM points are (`AxisWarp`, `LiveSceneModel.to_field`); k is in [0, 1] (mapped to [-1, 1]).
Object slots are fixed (`max_objects`) so the parameter count does not depend on the scene's object count;
the background is the last probability slot. With rigid part motions (`model.motion`, `livescene.articulation`)
a moving part's samples are read in its rest frame: `LiveSceneModel.place` decides, per sample, who owns it and
where the fields read it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from .appearance import FrameAppearance
from .articulation import PartMotions
from .config import ModelConfig
from .errors import LiveSceneError

MOTION_MODES = ("auto", "rigid", "none")
GATED_LOGIT = -30.0  # a rigid part's logit outside its hull: probability ~1e-13, yet a finite weighted sum
BACKGROUND_K = -1.0  # k of samples that belong to no object: not a state; KPlanes reads it from a node of its own


DENSITY_LOGIT_MAX = 40.0  # exp(40) ~ 2e17: opaque at any step size, and far from float32's overflow at 88.7


class _TruncExp(torch.autograd.Function):
    """exp with its gradient clamped, so a large density logit cannot blow up a step (as in Instant-NGP), and its
    value capped: one logit spiking past 88.7 (seen at 4.7 M parameters) made an inf density, inf x 0 step = NaN,
    and the same batch diverged again after every rollback."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x.clamp(max=DENSITY_LOGIT_MAX))

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(max=15.0))


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    return _TruncExp.apply(x)


def mlp(n_in: int, hidden: int, n_out: int, layers: int = 1) -> nn.Sequential:
    mods: list[nn.Module] = []
    d = n_in
    for _ in range(layers):
        mods += [nn.Linear(d, hidden), nn.ReLU(inplace=True)]
        d = hidden
    mods.append(nn.Linear(d, n_out))
    return nn.Sequential(*mods)


def spherical_harmonics(dirs: torch.Tensor, bands: int) -> torch.Tensor:
    """Real SH basis of unit directions (N, 3) for `bands` bands (1..4) -> (N, bands**2)."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, 0.28209479177387814)]
    if bands > 1:
        out += [-0.48860251190291987 * y, 0.48860251190291987 * z, -0.48860251190291987 * x]
    if bands > 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [1.0925484305920792 * x * y, -1.0925484305920792 * y * z, 0.94617469575755997 * zz - 0.31539156525251999,
                -1.0925484305920792 * x * z, 0.54627421529603959 * (xx - yy)]
    if bands > 3:
        out += [0.59004358992664352 * y * (-3.0 * xx + yy), 2.8906114426405538 * x * y * z,
                0.45704579946446572 * y * (1.0 - 5.0 * zz), 0.3731763325901154 * z * (5.0 * zz - 3.0),
                0.45704579946446572 * x * (1.0 - 5.0 * zz), 1.4453057213202769 * z * (xx - yy),
                0.59004358992664352 * x * (-xx + 3.0 * yy)]
    return torch.stack(out, -1)


class KPlanes(nn.Module):
    """Multi-scale planes xy, xz, yz (and xk, yk, zk when `k_resolution` > 0), Hadamard product per scale,
    concatenated across scales. The three planes of a group are stacked so one grid_sample call reads them.

    With `background_slice` the k axis has one node more, read only by background samples (k < 0): static space
    then never shares features with an object's state 0, and no interpolation crosses from states into it."""

    def __init__(self, resolutions: list[int], k_resolution: int, features: int,
                 init: tuple[float, float] = (0.1, 0.5), background_slice: bool = False):
        super().__init__()
        self.features = features
        self.k_resolution = k_resolution
        self.background_slice = background_slice and k_resolution > 0
        rows = k_resolution + int(self.background_slice)
        self.spatial = nn.ParameterList(
            [nn.Parameter(torch.empty(3, features, r, r).uniform_(*init)) for r in resolutions])
        self.kplanes = nn.ParameterList(
            [nn.Parameter(torch.ones(3, features, rows, r)) for r in resolutions] if k_resolution > 0 else [])

    @property
    def out_dim(self) -> int:
        return self.features * len(self.spatial)

    def state_rows(self, plane: torch.Tensor) -> torch.Tensor:
        """The rows of a k-plane (3, C, rows, R) that states read (the background node left out)."""
        return plane[:, :, : self.k_resolution]

    def k_coordinate(self, k: torch.Tensor) -> torch.Tensor:
        """k (N,): a state in [0, 1], or < 0 for background -> grid coordinate in [-1, 1] on the k axis."""
        if not self.background_slice:
            return k.clamp(0, 1) * 2 - 1
        top = 1 - 2 / self.k_resolution  # state 1 sits on the last state node, one node below the background's
        return torch.where(k < 0, torch.ones_like(k), -1 + k.clamp(0, 1) * (top + 1))

    def forward(self, xyz: torch.Tensor, k: torch.Tensor | None = None) -> torch.Tensor:
        """xyz (N, 3) in [-1, 1]; k (N,) states in [0, 1] (< 0: background) or None -> (N, features * scales)."""
        n = xyz.shape[0]
        x, y, z = xyz.unbind(-1)
        gs = torch.stack([torch.stack([x, y], -1), torch.stack([x, z], -1), torch.stack([y, z], -1)]).view(3, 1, n, 2)
        gk = None
        if k is not None and len(self.kplanes):
            k = self.k_coordinate(k)
            gk = torch.stack([torch.stack([x, k], -1), torch.stack([y, k], -1),
                              torch.stack([z, k], -1)]).view(3, 1, n, 2)
        outs = []
        for i, plane in enumerate(self.spatial):
            f = F.grid_sample(plane, gs, mode="bilinear", padding_mode="border", align_corners=True)
            f = f[:, :, 0].prod(0)  # (C, N)
            if gk is not None:
                fk = F.grid_sample(self.kplanes[i], gk, mode="bilinear", padding_mode="border", align_corners=True)
                f = f * fk[:, :, 0].prod(0)
            outs.append(f)
        return torch.cat(outs, 0).t()


class RadianceField(nn.Module):
    """4-D K-planes -> density and view-dependent colour."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.bands = cfg.sh_degree
        self.grid = KPlanes([cfg.resolution * s for s in cfg.scales], cfg.k_resolution, cfg.features,
                            background_slice=cfg.background_k == "slice")
        self.sigma_net = mlp(self.grid.out_dim, cfg.hidden, 1 + cfg.geo_features)
        self.color_net = mlp(cfg.sh_degree ** 2 + cfg.geo_features, cfg.hidden, 3, layers=2)

    def forward(self, xyz: torch.Tensor, k: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        sigma, h = self.density(xyz, k)
        return sigma, self.color(h, dirs)

    def density(self, xyz: torch.Tensor, k: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """(sigma (N,), the sigma net's output (N, 1 + geo_features)): the density alone, so a renderer can leave
        the colour out where the light never reaches (`livescene.march`)."""
        h = self.sigma_net(self.grid(xyz, k))
        return trunc_exp(h[:, 0] - 1.0), h

    def color(self, h: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        """RGB (N, 3) from `density`'s output and the view directions."""
        return torch.sigmoid(self.color_net(torch.cat([spherical_harmonics(dirs, self.bands), h[:, 1:]], -1)))

    def view_term(self, dirs: torch.Tensor) -> torch.Tensor:
        """(N, hidden): the view directions' share of the colour net's first layer, bias included. Samples of one
        ray share it, so a renderer computes it once per ray (`color_from`)."""
        first = self.color_net[0]
        n_sh = self.bands ** 2
        return torch.addmm(first.bias, spherical_harmonics(dirs, self.bands), first.weight[:, :n_sh].t())

    def color_from(self, view: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """RGB (N, 3) from a `view_term` (N, hidden) and `density`'s output: `color` to float rounding."""
        first = self.color_net[0]
        pre = torch.addmm(view, h[:, 1:], first.weight[:, self.bands ** 2:].t())
        return torch.sigmoid(self.color_net[1:](pre))


class ProposalField(nn.Module):
    """A small single-scale 4-D K-planes density used to place the next level's samples."""

    def __init__(self, resolution: int, k_resolution: int, features: int, hidden: int, background_slice: bool):
        super().__init__()
        self.grid = KPlanes([resolution], k_resolution, features, init=(0.1, 0.15), background_slice=background_slice)
        self.net = mlp(self.grid.out_dim, hidden, 1)

    def forward(self, xyz: torch.Tensor, k: torch.Tensor | None) -> torch.Tensor:
        return trunc_exp(self.net(self.grid(xyz, k))[:, 0] - 1.0)


class ProbabilityField(nn.Module):
    """3-D planes + an MLP conditioned on the current interaction values -> logits over object slots + background.

    Conditioning on the values lets an object's region move with its state (an open door occupies other space)."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.max_objects = cfg.max_objects
        self.grid = KPlanes([cfg.prob_resolution], 0, cfg.prob_features, init=(0.1, 0.15))
        self.net = mlp(self.grid.out_dim + cfg.max_objects, cfg.prob_hidden, cfg.max_objects + 1)

    def forward(self, xyz: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
        """xyz (N, 3); values (N, max_objects) -> logits (N, max_objects + 1), background last."""
        feat = torch.sigmoid(self.grid(xyz))
        return self.net(torch.cat([feat, values], -1))

    def folded_bias(self, values: torch.Tensor) -> torch.Tensor:
        """The first layer's bias with fixed values (max_objects,) folded in: at fixed states the values are the
        same for every sample, so `forward_folded` skips their share of the first layer."""
        first = self.net[0]
        return first.bias + first.weight[:, self.grid.out_dim:] @ values

    def forward_folded(self, xyz: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        """`forward` at the values folded into `bias` (`folded_bias`)."""
        first = self.net[0]
        feat = torch.sigmoid(self.grid(xyz))
        return self.net[1:](F.linear(feat, first.weight[:, : self.grid.out_dim], bias))


class FrameVariable(nn.Module):
    """The learnable per-frame variable: a 1-D feature line over normalised frame time (+ a positional
    encoding), decoded by a small MLP to one value in [0, 1] per object slot.

    Linear interpolation touches only the two nodes around a frame's time, so a loss on labelled frames
    updates only their nodes (and the shared decoder)."""

    FREQS = (1.0, 0.0316)

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.line = nn.Parameter(torch.rand(cfg.var_resolution, cfg.var_features))
        self.net = mlp(cfg.var_features, cfg.var_hidden, cfg.max_objects)

    def embed(self, t: torch.Tensor) -> torch.Tensor:
        r = self.line.shape[0]
        pos = t.clamp(0, 1) * (r - 1)
        i0 = pos.floor().long().clamp(0, max(r - 2, 0))
        i1 = (i0 + 1).clamp(max=r - 1)
        w = (pos - i0.to(pos.dtype)).unsqueeze(-1)
        emb = self.line[i0] * (1 - w) + self.line[i1] * w
        ang = 2 * math.pi * t.unsqueeze(-1) * torch.tensor(self.FREQS, device=t.device, dtype=t.dtype)
        pe = torch.cat([torch.sin(ang), torch.cos(ang)], -1)
        if pe.shape[-1] < emb.shape[-1]:
            pe = F.pad(pe, (0, emb.shape[-1] - pe.shape[-1]))
        return emb + pe[..., : emb.shape[-1]]  # PE is added (zero-padded / truncated to the feature size)

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        """t (N,) normalised frame time -> (N, max_objects) values in [0, 1]."""
        return torch.sigmoid(self.net(self.embed(t)))


def normalise(pts: torch.Tensor, box: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """World points (..., 3) -> coordinates in [-1, 1] of the scene box (lo, hi), before the model's `AxisWarp`."""
    lo, hi = box
    return ((pts - lo) * (2.0 / (hi - lo)) - 1.0).clamp(-1, 1)


WARP_KNOTS = 33  # knots per axis: the points' quantiles at 32 even steps of probability, and the box's ends


class AxisWarp(nn.Module):
    """A monotone piecewise-linear map of each axis of [-1, 1] onto itself, which spends the planes' cells where the
    scene's surfaces are. A real capture's box holds far walls and floor (its SfM points' 1-99 % range): on the
    shared laptop video it is 7 units long for a 1-unit laptop, so the finest 128-cell plane drew the laptop about
    13 px per cell at 640 px wide, and the held-out frames scored as the frames themselves shrunk 8x. Each axis
    here maps x to `uniform` x + (1 - `uniform`) (2 CDF(x) - 1), CDF the points' own distribution along that axis:
    separable, so the planes stay axis-aligned; a uniform share keeps every cell of empty space some resolution.
    Identity until `fit` (and for runs trained before it: `LiveSceneModel.load_state_dict`)."""

    def __init__(self, knots: int = WARP_KNOTS):
        super().__init__()
        line = torch.linspace(-1.0, 1.0, knots).expand(3, knots).contiguous()
        self.register_buffer("xk", line.clone())  # (3, K) knots in box coordinates, increasing from -1 to 1
        self.register_buffer("fk", line.clone())  # (3, K) where each knot lands in field coordinates
        self._identity: bool | None = True

    @property
    def identity(self) -> bool:
        if self._identity is None:  # cached: a comparison on the GPU would wait for it at every read
            self._identity = bool(torch.equal(self.xk, self.fk))
        return self._identity

    def _load_from_state_dict(self, *args, **kwargs):
        self._identity = None
        super()._load_from_state_dict(*args, **kwargs)

    @torch.no_grad()
    def fit(self, points: torch.Tensor, uniform: float) -> None:
        """points (P, 3) in box coordinates ([-1, 1]; `normalise`); uniform in (0, 1]: the share spread evenly."""
        k = self.xk.shape[1]
        q = torch.linspace(0.0, 1.0, k, dtype=torch.float64)
        inner = torch.quantile(points.double().clamp(-1, 1), q[1:-1], dim=0).t()  # (3, K - 2)
        xk = torch.cat([torch.full((3, 1), -1.0, dtype=q.dtype), inner, torch.ones(3, 1, dtype=q.dtype)], 1)
        for j in range(1, k):  # strictly increasing (many points on one plane give equal quantiles) ...
            xk[:, j] = torch.maximum(xk[:, j], xk[:, j - 1] + 1e-4)
        xk = (xk + 1.0) * (2.0 / (xk[:, -1:] + 1.0)) - 1.0  # ... and ending at 1
        self.xk.copy_(xk.to(self.xk))
        self.fk.copy_((uniform * xk + (1.0 - uniform) * (2.0 * q - 1.0)).to(self.fk))
        self._identity = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (N, 3) box coordinates -> (N, 3) field coordinates."""
        if self.identity:
            return x
        xt = x.t().contiguous()  # (3, N)
        i = torch.searchsorted(self.xk, xt).clamp(1, self.xk.shape[1] - 1)
        x0, x1 = self.xk.gather(1, i - 1), self.xk.gather(1, i)
        f0, f1 = self.fk.gather(1, i - 1), self.fk.gather(1, i)
        return (f0 + (xt - x0) * ((f1 - f0) / (x1 - x0))).t()


@dataclass
class Placement:
    """Where the fields read each sample: its owner's frame (the world, or a rigid part's rest frame)."""

    xyz: torch.Tensor  # (N, 3) field coordinates
    dirs: torch.Tensor  # (N, 3) view directions in the same frame
    k: torch.Tensor  # (N,) interaction value read on the k axis (< 0: the background slice)
    logits: torch.Tensor  # (N, max_objects + 1) ownership logits, background last


class LiveSceneModel(nn.Module):
    def __init__(self, cfg: ModelConfig, n_objects: int):
        super().__init__()
        if n_objects > cfg.max_objects:
            raise LiveSceneError(f"the scene has {n_objects} objects but the model has {cfg.max_objects} slots: "
                             f"raise model.max_objects (--set model.max_objects={n_objects})")
        if cfg.background_k not in ("slice", "zero"):
            raise LiveSceneError(f"model.background_k must be 'slice' or 'zero', not {cfg.background_k!r}")
        if cfg.mask_render not in ("auto", "probs", "logits"):
            raise LiveSceneError(f"model.mask_render must be 'auto', 'probs' or 'logits', not {cfg.mask_render!r}")
        if cfg.mask_shapes not in ("grad", "detach"):
            raise LiveSceneError(f"model.mask_shapes must be 'grad' or 'detach', not {cfg.mask_shapes!r}")
        if cfg.motion not in MOTION_MODES:
            raise LiveSceneError(f"model.motion must be one of {MOTION_MODES}, not {cfg.motion!r}")
        if cfg.part_k not in ("rest", "state"):
            raise LiveSceneError(f"model.part_k must be 'rest' or 'state', not {cfg.part_k!r}")
        if cfg.warp not in ("points", "off"):
            raise LiveSceneError(f"model.warp must be 'points' or 'off', not {cfg.warp!r}")
        if not 0 < cfg.warp_uniform <= 1:
            raise LiveSceneError(f"model.warp_uniform must be in (0, 1], not {cfg.warp_uniform!r}")
        self.cfg = cfg
        self.n_objects = n_objects
        bg_slice = cfg.background_k == "slice"
        self.background_k = BACKGROUND_K if bg_slice else 0.0
        # "auto" is resolved against the dataset by `trainer.build_model`; a model built without it has no motions
        self.motions = PartMotions(cfg.max_objects) if cfg.motion == "rigid" else None
        self.mask_render = cfg.mask_render if cfg.mask_render != "auto" else (
            "probs" if cfg.motion == "rigid" else "logits")
        self.mask_shapes = cfg.mask_shapes == "grad"
        self.warp = AxisWarp()  # box coordinates -> field coordinates (`to_field`); fitted by `trainer.build_model`
        self.field = RadianceField(cfg)
        self.proposals = nn.ModuleList(
            [ProposalField(r, cfg.k_resolution if self.proposals_read_k else 0, cfg.proposal_features,
                           cfg.proposal_hidden, bg_slice) for r in cfg.proposal_resolutions])
        self.prob = ProbabilityField(cfg)
        self.variable = FrameVariable(cfg)
        self.bg_color = nn.Parameter(torch.full((3,), 0.5), requires_grad=cfg.background == "learned")
        self.register_buffer("slot_mask", torch.arange(cfg.max_objects + 1) < n_objects)
        self.slot_mask[-1] = True
        # per-frame colour transform of the training renders only (`livescene.appearance`); None = off
        self.appearance = (FrameAppearance(cfg.appearance, cfg.appearance_frames)
                           if cfg.appearance != "off" else None)

    def to_field(self, pts: torch.Tensor, box: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
        """World points (N, 3) -> the coordinates every field reads: the scene box's, warped (`AxisWarp`)."""
        return self.warp(normalise(pts, box))

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Runs trained before the axis warp have none: theirs is the identity."""
        state = dict(state_dict)
        for name, value in AxisWarp().state_dict().items():
            state.setdefault(f"warp.{name}", value)
        return super().load_state_dict(state, strict=strict, assign=assign)

    def background(self) -> torch.Tensor:
        if self.cfg.background == "learned":
            return torch.sigmoid(self.bg_color)
        return torch.ones(3, device=self.bg_color.device) * (1.0 if self.cfg.background == "white" else 0.0)

    def pad_values(self, values: torch.Tensor) -> torch.Tensor:
        """(N, n_objects) -> (N, max_objects) with empty slots at 0."""
        if values.shape[-1] == self.cfg.max_objects:
            return values
        return F.pad(values, (0, self.cfg.max_objects - values.shape[-1]))

    def frame_values(self, t: torch.Tensor) -> torch.Tensor:
        """The learned states (N, max_objects) at normalised frame times t (N,); empty slots are 0."""
        v = self.variable(t)
        return v * self.slot_mask[:-1].to(v.dtype)

    def logits(self, xyz: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
        logits = self.prob(xyz, values)
        return logits.masked_fill(~self.slot_mask, -1e4)

    @property
    def proposals_read_k(self) -> bool:
        """Rigid parts share field coordinates with the static scene (a closed door's rest frame is where air is
        once it opens), so proposals then tell them apart on the k axis too."""
        return self.cfg.proposal_k or self.cfg.motion == "rigid"

    def place(self, pts: torch.Tensor, dirs: torch.Tensor, values: torch.Tensor,
              box: tuple[torch.Tensor, torch.Tensor], grad_logits: bool = True) -> Placement:
        """Who owns each world sample and where the fields read it. pts, dirs (N, 3); values (N, max_objects).

        Ownership logits come from the probability field read in each candidate owner's frame: the world for the
        background and for objects without a rigid motion (conditioned on the values, as in the paper), each
        rigid part's rest frame for that part (not conditioned: the motion carries its region). The sample then
        takes its most probable object's frame and k (`select_k`'s rule), or the background's."""
        rigid = self.motions.rigid(self.n_objects) if self.motions is not None else []
        warp_values = values if self.cfg.motion_grad else values.detach()
        n = pts.shape[0]
        xyz = [self.to_field(pts, box)]
        view = [dirs]
        with torch.set_grad_enabled(grad_logits and torch.is_grad_enabled()):
            if not rigid:
                logits = self.prob(xyz[0], values)
            else:
                rest_p, rest_d = self.motions.to_rest(pts, dirs, warp_values, rigid)
                xyz += [self.to_field(p, box) for p in rest_p.unbind(0)]
                view += list(rest_d.unbind(0))
                gate = self.motions.inside(rigid, rest_p)  # only a part's hull is read in its frame
                keep = torch.ones(values.shape[1], device=values.device, dtype=values.dtype)
                keep[rigid] = 0
                inputs = [xyz[0]] + [xyz[j + 1][gate[j]] for j in range(len(rigid))]
                sizes = [n] + [int(g.sum()) for g in gate]
                raw = self.prob(torch.cat(inputs), torch.cat([values * keep, values.new_zeros(sum(sizes[1:]),
                                                                                           values.shape[1])]))
                parts = raw.split(sizes)
                cols = list(parts[0].unbind(-1))
                for j, o in enumerate(rigid):
                    col = torch.full((n,), GATED_LOGIT, device=raw.device, dtype=raw.dtype)
                    cols[o] = col.masked_scatter(gate[j], parts[j + 1][:, o])
                logits = torch.stack(cols, -1)
            logits = logits.masked_fill(~self.slot_mask, -1e4)
        groups = len(xyz)
        idx, owned = self.owner(logits)
        k = self.select_k(logits, values, (idx, owned))
        if groups == 1:
            return Placement(xyz[0], dirs, k, logits)
        group_of = torch.zeros(values.shape[1], dtype=torch.long, device=pts.device)
        group_of[rigid] = torch.arange(1, groups, device=pts.device)
        group = torch.where(owned, group_of[idx], torch.zeros_like(idx))
        if self.cfg.part_k == "rest":
            k = torch.where(group > 0, torch.zeros_like(k), k)
        sel = group[None, :, None].expand(1, n, 3)
        return Placement(torch.stack(xyz).gather(0, sel)[0], torch.stack(view).gather(0, sel)[0], k, logits)

    @torch.no_grad()
    def owner(self, logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(most probable object (N,), owned (N,) bool): below the rejection threshold s (or when the scene has
        no object) a sample is the background's."""
        best, idx = torch.softmax(logits, -1)[:, :-1].max(-1)
        owned = best >= self.cfg.reject_threshold if self.cfg.reject_threshold > 0 else torch.ones_like(best, dtype=torch.bool)
        if self.n_objects == 0:
            owned = torch.zeros_like(owned)
        return idx, owned

    def select_k(self, logits: torch.Tensor, values: torch.Tensor,
                 owner: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """Each sample takes the value of its most probable object, or the background value when it is not owned."""
        idx, owned = owner if owner is not None else self.owner(logits)
        k = values.gather(1, idx.unsqueeze(1))[:, 0]
        return torch.where(owned, k, torch.full_like(k, self.background_k))

    def param_count(self) -> int:
        return sum(p.numel() for p in self.parameters() if p.requires_grad)

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {"field": list(self.field.parameters()) + ([self.bg_color] if self.bg_color.requires_grad else []),
                "proposals": list(self.proposals.parameters()),
                "prob": list(self.prob.parameters()),
                "variable": list(self.variable.parameters()),
                **({"appearance": list(self.appearance.parameters())} if self.appearance is not None else {})}
