"""The fast renderer's image: which pixels are traced, which are interpolated, which are reused.

A trained field renders smooth images (walls, floors, the fog of a short training): most pixels are what their
neighbours predict. So the fast renderer (`render_view(fast=True)`) traces a coarse lattice of pixels (every
`stride`-th row and column) and fills each finer lattice level (stride / 2, ... 1) in turn: a pixel whose 2 or 4
lattice neighbours agree (colour, opacity and object probabilities within `tolerance`, depth within
`DEPTH_TOLERANCE` of its distance) is interpolated bilinearly, the others are traced (`refine`). Edges, texture and
object boundaries are traced; flat regions cost a ray per `stride` x `stride` pixels. tolerance 0 traces every pixel.

Same camera, other states (a slider in the viewer, a state sweep): with every object moving rigidly, a pixel whose
ray meets no cell of the occupancy grid that a part can reach (`OccupancyGrid.reach`) renders the same at every
state. `reach_pixels` finds those pixels by projecting the reach cells into the camera, and `render_image` reuses
them from the previous image of that camera.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import replace
from typing import Any, Callable

import numpy as np
import torch

from interreal.conventions import opengl_to_opencv

from .data import camera_rays, pixel_directions
from .march import TERMINATE_T, FixedStates, MarchStats, march_rays
from .occupancy import grid_for

STRIDE = 4  # pixels between traced lattice points at the coarsest level (a power of 2)
TOLERANCE = 0.04  # spread among a pixel's lattice neighbours (colour, opacity, probabilities) it may be filled over
DEPTH_TOLERANCE = 0.05  # ... and their depths' spread relative to the nearest: a depth edge is traced
CACHED_CAMERAS = 4  # images kept for reuse: the viewer's drag and rest sizes of a camera or two
SKIP_WORTH = 0.9  # the occupancy grid is asked only when less than this share of its cells is occupied

Tracer = Callable[[torch.Tensor], torch.Tensor]  # flat pixel indices (P,) -> features (P, F)


def padded(n: int, stride: int) -> int:
    """Lattice size covering n pixels: (a multiple of stride) + 1, so every pixel has lattice points on both sides
    (the ones beyond the image are traced like any other pixel)."""
    return (max(n, 1) - 1 + stride - 1) // stride * stride + 1


def agree_by(tolerance: float, depth_tolerance: float = DEPTH_TOLERANCE) -> Callable[[torch.Tensor], torch.Tensor]:
    """corners (P, 4, F) with depth last -> bool (P,): their spread is within the tolerances."""

    def agree(corners: torch.Tensor) -> torch.Tensor:
        spread = corners.amax(1) - corners.amin(1)  # (P, F)
        depth = corners[:, :, -1]
        return (spread[:, :-1].amax(-1) <= tolerance) & (spread[:, -1] <= depth_tolerance * depth.amin(1).clamp(min=1e-6))

    return agree


@torch.no_grad()
def refine(hp: int, wp: int, stride: int, trace: Tracer, agree: Callable[[torch.Tensor], torch.Tensor],
           device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Features (hp * wp, F) of a lattice of hp x wp pixels (`padded` sizes) and which were traced (bool): the
    coarse lattice traced, each finer level interpolated where `agree` says its lattice neighbours agree."""
    if stride < 1 or stride & (stride - 1):
        raise ValueError(f"stride must be a power of 2, got {stride}")
    ys, xs = torch.arange(0, hp, stride, device=device), torch.arange(0, wp, stride, device=device)
    first = (ys[:, None] * wp + xs[None, :]).reshape(-1)
    got = trace(first)
    values = got.new_zeros(hp * wp, got.shape[1])
    traced = torch.zeros(hp * wp, dtype=torch.bool, device=device)
    values[first], traced[first] = got, True
    s = stride
    while s > 1:
        h = s // 2
        yy, xx = torch.meshgrid(torch.arange(0, hp, h, device=device), torch.arange(0, wp, h, device=device),
                                indexing="ij")
        new = (yy % s != 0) | (xx % s != 0)
        y, x = yy[new], xx[new]
        y0, x0 = y - y % s, x - x % s
        y1, x1 = torch.where(y % s == 0, y0, y0 + s), torch.where(x % s == 0, x0, x0 + s)
        corners = torch.stack([y0 * wp + x0, y0 * wp + x1, y1 * wp + x0, y1 * wp + x1], -1)
        cv = values[corners]  # (P, 4, F)
        ok = agree(cv)
        ty, tx = ((y - y0).to(cv.dtype) / s)[:, None], ((x - x0).to(cv.dtype) / s)[:, None]
        w = torch.cat([(1 - ty) * (1 - tx), (1 - ty) * tx, ty * (1 - tx), ty * tx], -1)
        pix = y * wp + x
        values[pix[ok]] = (w[ok, :, None] * cv[ok]).sum(1)
        todo = pix[~ok]
        if len(todo):
            values[todo], traced[todo] = trace(todo), True
        s = h
    return values, traced


def reach_pixels(grid: Any, c2w_gl: np.ndarray, intrinsics: Any) -> np.ndarray | None:
    """bool (H, W): pixels whose ray may meet a cell a rigid part can reach at some state (`OccupancyGrid.reach`),
    by projecting each such cell's bounding sphere; the others render the same at every state. None (every pixel)
    for a camera with lens distortion or a reach cell at the camera."""
    if grid is None or grid.reach is None or intrinsics.has_distortion():
        return None
    h, w = intrinsics.h, intrinsics.w
    cells = grid.reach.reshape(-1).nonzero()[:, 0].cpu().numpy()
    out = np.zeros((h, w), bool)
    if not len(cells):
        return out
    shape = np.array(grid.shape)
    lo, hi = grid.lo.cpu().numpy().astype(np.float64), grid.hi.cpu().numpy().astype(np.float64)
    size = (hi - lo) / shape
    idx = np.stack([cells // (shape[1] * shape[2]), (cells // shape[2]) % shape[1], cells % shape[2]], -1)
    offsets = np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), -1).reshape(8, 3)
    corners = lo + (idx[:, None, :] + offsets[None]) * size  # (C, 8, 3): a cell's image is inside its corners'
    c2w = opengl_to_opencv(np.asarray(c2w_gl, dtype=np.float64))
    cam = (corners - c2w[:3, 3]) @ c2w[:3, :3]  # camera frame (OpenCV: z forward)
    z = cam[..., 2]
    front = (z > 0).any(1)  # cells wholly behind the camera are never met
    cam, z = cam[front], z[front]
    if not len(z):
        return out
    if (z.min(1) <= 1e-3 * float(np.linalg.norm(size))).any():  # a reach cell at the camera plane: any pixel
        return None
    u = intrinsics.fl_x * cam[..., 0] / z + intrinsics.cx
    v = intrinsics.fl_y * cam[..., 1] / z + intrinsics.cy
    # pixel i's ray goes through i + 0.5: a pixel of margin on each side
    u0, u1 = np.floor(u.min(1)).astype(np.int64) - 1, np.ceil(u.max(1)).astype(np.int64) + 1
    v0, v1 = np.floor(v.min(1)).astype(np.int64) - 1, np.ceil(v.max(1)).astype(np.int64) + 1
    keep = (u1 >= 0) & (u0 < w) & (v1 >= 0) & (v0 < h)
    u0, u1, v0, v1 = np.clip(u0[keep], 0, w), np.clip(u1[keep], 0, w), np.clip(v0[keep], 0, h), np.clip(v1[keep], 0, h)
    marks = np.zeros((h + 1, w + 1), np.int64)  # rectangles by a 2-D difference array: O(cells + pixels)
    np.add.at(marks, (v0, u0), 1)
    np.add.at(marks, (v0, u1), -1)
    np.add.at(marks, (v1, u0), -1)
    np.add.at(marks, (v1, u1), 1)
    return marks.cumsum(0).cumsum(1)[:h, :w] > 0


def _caches(run: Any) -> OrderedDict:
    """The run's last fast images by (camera, size, settings), oldest first (`CACHED_CAMERAS` of them)."""
    if getattr(run, "_image_caches", None) is None:
        run._image_caches = OrderedDict()
    return run._image_caches


class ImageCache:
    """The last fast image of one camera (features per lattice pixel, which pixels a state change may alter): a
    render of the same camera at other states reuses the rest."""

    def __init__(self, key: tuple, values: torch.Tensor, affected: torch.Tensor):
        self.key, self.values, self.affected = key, values, affected


@torch.no_grad()
def render_image(run: Any, c2w_gl: np.ndarray, intrinsics: Any, values: torch.Tensor, *, chunk: int,
                 occupancy: Any = None, threshold: float | None = None, terminate: float | None = None,
                 stride: int = STRIDE, tolerance: float = TOLERANCE) -> dict[str, Any]:
    """The fast render of one camera at states `values` (1, max_objects): rgb (H*W, 3), depth (H*W,) along the
    ray, acc (H*W,), probs (H*W, M + 1), `march` (`MarchStats`), `traced` and `rays_reused` (pixel counts).
    occupancy: None = the run's grid (`occupancy.grid_for`), False = none, or an `OccupancyGrid`."""
    model, device = run.model, run.device
    m = model.n_objects
    if tolerance <= 0:
        stride = 1
    h, w = intrinsics.h, intrinsics.w
    hp, wp = (padded(h, stride), padded(w, stride)) if stride > 1 else (h, w)
    lattice = replace(intrinsics, w=wp, h=hp)
    origins, dirs, _ = camera_rays(c2w_gl, lattice, pixel_directions(lattice))
    o_all = torch.from_numpy(np.ascontiguousarray(origins)).to(device)
    d_all = torch.from_numpy(np.ascontiguousarray(dirs)).to(device)
    grid = grid_for(run) if occupancy is None else (occupancy or None)
    grid = grid.to(device) if grid is not None else None
    # a grid that skips little costs more to ask than it saves (a short training leaves fog in every cell)
    tester = grid.tester(threshold) if grid is not None and grid.occupied_fraction(threshold) < SKIP_WORTH else None
    fixed = FixedStates(model, values[0])
    stats = MarchStats()
    term = terminate or TERMINATE_T
    cache, key = None, None
    if grid is not None and grid.reach is not None and fixed.gate_decides and getattr(run, "checkpoint", None):
        key = (np.asarray(c2w_gl, dtype=np.float64).tobytes(), repr(intrinsics), threshold, term, stride, tolerance,
               id(grid))
        cache = _caches(run).get(key)

    def march(idx: torch.Tensor) -> torch.Tensor:
        parts = []
        for s in range(0, len(idx), chunk):
            sel = idx[s: s + chunk]
            out = march_rays(model, fixed, o_all[sel], d_all[sel], run.box, run.config.sampler, tester, True,
                             stats, term)
            lg = torch.cat([out["logits"][:, :m], out["logits"][:, -1:]], -1)
            parts.append(torch.cat([out["rgb"].clamp(0, 1), out["acc"][:, None], torch.softmax(lg, -1),
                                    out["depth"][:, None]], -1))
        return torch.cat(parts) if parts else o_all.new_zeros(0, m + 6)

    def trace(idx: torch.Tensor) -> torch.Tensor:
        if cache is None:
            return march(idx)
        out = cache.values[idx].clone()
        redo = cache.affected[idx]
        if bool(redo.any()):
            out[redo] = march(idx[redo])
        return out

    if stride > 1:
        feats, traced = refine(hp, wp, stride, trace, agree_by(tolerance), device)
    else:
        feats = trace(torch.arange(hp * wp, device=device))
        traced = torch.ones(hp * wp, dtype=torch.bool, device=device)
    reused = 0 if cache is None else int((~cache.affected & traced).sum())
    if key is not None and cache is None:
        mask = reach_pixels(grid, c2w_gl, lattice)
        affected = torch.ones(hp * wp, dtype=torch.bool) if mask is None else torch.from_numpy(mask.reshape(-1))
        caches = _caches(run)
        caches[key] = ImageCache(key, feats.clone(), affected.to(device))
        while len(caches) > CACHED_CAMERAS:
            caches.popitem(last=False)
    elif cache is not None:
        _caches(run).move_to_end(key)
    feats = feats.view(hp, wp, -1)[:h, :w].reshape(h * w, -1).cpu()
    return {"rgb": feats[:, :3], "acc": feats[:, 3], "probs": feats[:, 4: 5 + m], "depth": feats[:, -1],
            "march": stats, "traced": int(traced.view(hp, wp)[:h, :w].sum()), "rays_reused": reused}
