"""The density level of an exported surface, measured from the run's own views.

A radiance field has no surface, only density, and what density a trained field gives a wall depends on the
scene, the training and the model (the demo's run keeps walls near 10 a unit, a few hundred toy steps near 5 with
0.5 of fog; a level set from the voxel size missed the demo's walls entirely). So the level is calibrated where
the renderer draws surfaces: along rays of the training views, at the frames' learned states, each ray's median
depth (where half its light has stopped) is where a surface should be. A level L makes the surface cross a ray
before that depth exactly when the ray's running maximum of density up to there reaches L; the level is the
LEVEL_QUANTILE of those running maxima, so that share of the opaque rays is crossed at or before its median depth.
"""

from __future__ import annotations

import numpy as np
import torch

from ..data import camera_rays
from ..sampler import ray_box, volume_weights

LEVEL_QUANTILE = 0.25  # 75 % of the views' opaque rays find the surface by their median depth
CALIBRATION_RAYS = 2048
CALIBRATION_SAMPLES = 128  # uniform samples a ray
CALIBRATION_VIEWS = 16  # training views the rays are drawn from (evenly spread)
MIN_OPACITY = 0.5  # rays that stop less light than this (through the box) are skipped: no surface on them


@torch.no_grad()
def ray_profiles(run, rays: int = CALIBRATION_RAYS, samples: int = CALIBRATION_SAMPLES, seed: int = 0
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """(density (R, S), edges (R, S + 1)): the rendered density along rays of the training views, each at its
    frame's learned states, read as the renderer places samples (`LiveSceneModel.place`)."""
    views, model, dev = run.views, run.model, run.device
    frames = views.train or list(range(len(views.times)))
    pick = [frames[i] for i in np.unique(np.linspace(0, len(frames) - 1, CALIBRATION_VIEWS).round().astype(int))]
    rng = np.random.default_rng(seed)
    per = max(1, rays // len(pick))
    origins, dirs, values = [], [], []
    t = torch.as_tensor(views.times[pick], dtype=torch.float32, device=dev)
    states = model.frame_values(t)  # (V, max_objects)
    for j, f in enumerate(pick):
        o, d, _ = camera_rays(views.c2w_gl[f], views.intrinsics[f])
        idx = rng.choice(len(o), size=min(per, len(o)), replace=False)
        origins.append(torch.as_tensor(o[idx], dtype=torch.float32))
        dirs.append(torch.as_tensor(d[idx], dtype=torch.float32))
        values.append(states[j].expand(len(idx), -1))
    o = torch.cat(origins).to(dev)
    d = torch.cat(dirs).to(dev)
    vals = torch.cat(values)
    lo, hi = run.box
    near, far = ray_box(o, d, lo, hi, float(run.config.sampler.near))
    u = torch.linspace(0, 1, samples + 1, device=dev)
    edges = near[:, None] + (far - near)[:, None] * u
    mids = 0.5 * (edges[:, 1:] + edges[:, :-1])
    sigma = torch.empty(mids.shape, device=dev)
    step = max(1, (1 << 16) // samples)
    for s in range(0, len(o), step):
        p = o[s: s + step, None, :] + mids[s: s + step, :, None] * d[s: s + step, None, :]
        n = p.shape[0] * p.shape[1]
        dd = d[s: s + step, None, :].expand_as(p).reshape(n, 3)
        vv = vals[s: s + step, None, :].expand(-1, samples, -1).reshape(n, -1)
        place = model.place(p.reshape(n, 3), dd, vv, run.box, grad_logits=False)
        sigma[s: s + step] = model.field.density(place.xyz, place.k)[0].view(-1, samples)
    return sigma, edges


def level_from_profiles(sigma: torch.Tensor, edges: torch.Tensor, quantile: float = LEVEL_QUANTILE
                        ) -> tuple[float | None, float]:
    """(level, air): the LEVEL_QUANTILE of the running maximum of density up to each opaque ray's median depth
    (None: no ray of the views is opaque), and the median density in front of the surfaces (before a tenth of
    each ray's light has stopped): a level near the air's means the field has fog, not surfaces."""
    w = volume_weights(sigma, edges)
    cum = w.cumsum(-1)
    opaque = cum[:, -1] >= MIN_OPACITY
    if not bool(opaque.any()):
        return None, float(sigma.median())
    cum, sig = cum[opaque], sigma[opaque]
    median = (cum < 0.5).sum(-1).clamp(max=sigma.shape[1] - 1)  # the first sample past half the light
    run_max = torch.cummax(sig, -1).values.gather(1, median[:, None])[:, 0]
    front = sig[cum < 0.1]
    air = float(front.median()) if front.numel() else 0.0
    return float(torch.quantile(run_max, quantile)), air


def calibrate_level(run, seed: int = 0) -> tuple[float | None, float]:
    """(surface level, air density) of the run's field (density a unit length), measured on its training views."""
    sigma, edges = ray_profiles(run, seed=seed)
    return level_from_profiles(sigma, edges)
