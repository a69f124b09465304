"""The fast renderer's image: which pixels are traced, which are interpolated, which are reused.

A trained field renders smooth images (walls, floors, the fog of a short training): most pixels are what their
neighbours predict. So the fast renderer (`render_view(fast=True)`) traces a coarse lattice of pixels (every
`stride`-th row and column) and fills each finer lattice level (stride / 2, ... 1) in turn: a pixel whose 2 or 4
lattice neighbours agree (colour, opacity and object probabilities within `tolerance`, depth within
`DEPTH_TOLERANCE` of its distance), or lie on a smooth curve (second differences within `BEND` x `tolerance`,
at lattice spacings up to 1/`SMOOTH_STEPS` of the image), is interpolated, the others are traced (`refine`).
Edges, texture and object boundaries are traced; flat regions and shading gradients cost a ray per `stride` x
`stride` pixels. tolerance 0 traces every pixel.

Same camera, other states (a slider in the viewer, a state sweep): with every object moving rigidly, a sample
outside a part's hull is never that part's, so a pixel whose ray meets no moved part's hull, at the old states nor
at the new ones, renders the same. `changed_pixels` finds the others by projecting those hulls into the camera, and
`render_image` re-traces only them, reusing the rest from the first image of that camera.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import replace
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F

from interreal.conventions import opengl_to_opencv

from .data import camera_rays, pixel_directions
from .march import TERMINATE_T, FixedStates, MarchStats, march_rays, rest_transform
from .occupancy import grid_for

STRIDE = 4  # pixels between traced lattice points at the coarsest level (a power of 2)
TOLERANCE = 0.04  # spread among a pixel's lattice neighbours (colour, opacity, probabilities) it may be filled over
DEPTH_TOLERANCE = 0.05  # ... and their depths' spread relative to the nearest: a depth edge is traced
BEND = 2.0  # second differences up to this multiple of the tolerance still count as a straight line (`refine`'s
# smooth test): linear interpolation then errs by about a quarter of the tolerance, half of what the spread test
# allows (a step of `tolerance` between two neighbours), and the curved estimates used there are exact for quadratic
# shading. On the demo's run at 320x240, 1 thread: 19 % of the pixels traced (24 % at BEND 1, 35 % without the test),
# 41.7 dB to the exact render, 0.08 dB below its PSNR against the recorded frame
SMOOTH_STEPS = 80  # ... asked only where the lattice spacing is at most 1/80 of the image's longer side: the points
# a second difference spans (3 spacings) must be close together in the scene, where its detail is; on the demo's
# run at 160x120, 4-pixel spacings let thin detail through (0.22 dB against the recorded frame, 0.14 without them)
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


def smooth_by(tolerance: float, depth_tolerance: float = DEPTH_TOLERANCE) -> Callable[[torch.Tensor, torch.Tensor],
                                                                                     torch.Tensor]:
    """(deviations (P, F) from a straight line, depth last; reference depth (P,)) -> bool (P,): within the
    tolerances, so a pixel on that line is interpolated even where its neighbours differ (a gradient)."""

    def smooth(dev: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        return (dev[:, :-1].amax(-1) <= tolerance) & (dev[:, -1] <= depth_tolerance * depth.clamp(min=1e-6))

    return smooth


Smooth = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@torch.no_grad()
def refine(hp: int, wp: int, stride: int, trace: Tracer, agree: Callable[[torch.Tensor], torch.Tensor],
           device: torch.device | str = "cpu", smooth: Smooth | None = None,
           smooth_spacing: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Features (hp * wp, F) of a lattice of hp x wp pixels (`padded` sizes) and which were traced (bool): the
    coarse lattice traced, each finer level interpolated where `agree` says its lattice neighbours agree.

    With `smooth` (`smooth_by`) a pixel whose neighbours differ is interpolated too where they lie on a smooth
    curve: a pixel halfway along a lattice edge when the second differences along that line (the lattice points
    one step further out on both sides) are within it, since linear interpolation there errs by about 1/8 of
    them; a cell's centre when its four edge midpoints (traced or interpolated just before) are within it of
    their corners' means, i.e. the cell is close to bilinear. There the curved estimate is used (the cubic through
    the four points on the line; twice the edge midpoints' mean less the corners' mean at a centre: both exact
    for quadratic shading), clamped to the range of the points it is made from. Shading gradients, wider than
    `agree`'s tolerance across a lattice step, are then interpolated; steps and texture are not (large second
    differences). `smooth_spacing`: the widest lattice spacing (pixels) at which `smooth` is asked (default: every
    level). Each level does its edge midpoints first, then its cell centres: without `smooth` the same result as
    one pass.
    """
    if stride < 1 or stride & (stride - 1):
        raise ValueError(f"stride must be a power of 2, got {stride}")
    ys, xs = torch.arange(0, hp, stride, device=device), torch.arange(0, wp, stride, device=device)
    first = (ys[:, None] * wp + xs[None, :]).reshape(-1)
    got = trace(first)
    values = got.new_zeros(hp * wp, got.shape[1])
    traced = torch.zeros(hp * wp, dtype=torch.bool, device=device)
    values[first], traced[first] = got, True

    def fill(pix: torch.Tensor, ok: torch.Tensor, estimate: torch.Tensor) -> None:
        values[pix[ok]] = estimate[ok]
        todo = pix[~ok]
        if len(todo):
            values[todo], traced[todo] = trace(todo), True

    s = stride
    while s > 1:
        h = s // 2
        curve = smooth if s <= (stride if smooth_spacing is None else smooth_spacing) else None
        # edge midpoints (both directions in one batch): between lattice points a and b, a2 and b2 one step out
        rows = torch.meshgrid(_steps(0, hp, s, device), _steps(h, wp, s, device), indexing="ij")
        cols = torch.meshgrid(_steps(h, hp, s, device), _steps(0, wp, s, device), indexing="ij")
        y = torch.cat([rows[0].reshape(-1), cols[0].reshape(-1)])
        x = torch.cat([rows[1].reshape(-1), cols[1].reshape(-1)])
        dy = torch.cat([torch.zeros(rows[0].numel(), dtype=torch.long, device=device),
                        torch.ones(cols[0].numel(), dtype=torch.long, device=device)])
        dx = 1 - dy
        a, b = (y - h * dy) * wp + x - h * dx, (y + h * dy) * wp + x + h * dx
        va, vb = values[a], values[b]
        ok = agree(torch.stack([va, vb, va, vb], 1))
        estimate = 0.5 * (va + vb)
        if curve is not None:  # at the border a2 (b2) is a (b) itself: the spread of a and b
            a2 = (y - (h + s) * dy).clamp(min=0) * wp + (x - (h + s) * dx).clamp(min=0)
            b2 = (y + (h + s) * dy).clamp(max=hp - 1) * wp + (x + (h + s) * dx).clamp(max=wp - 1)
            va2, vb2 = values[a2], values[b2]
            bend = torch.maximum((va2 - 2 * va + vb).abs(), (va - 2 * vb + vb2).abs())
            curved = curve(bend, torch.minimum(va[:, -1], vb[:, -1]))
            cubic = _within((9 * (va + vb) - va2 - vb2) / 16, torch.stack([va2, va, vb, vb2], 1))
            estimate = torch.where(curved[:, None], cubic, estimate)
            ok |= curved
        fill(y * wp + x, ok, estimate)
        yy, xx = torch.meshgrid(_steps(h, hp, s, device), _steps(h, wp, s, device), indexing="ij")
        y, x = yy.reshape(-1), xx.reshape(-1)
        corners = torch.stack([(y - h) * wp + x - h, (y - h) * wp + x + h, (y + h) * wp + x - h,
                               (y + h) * wp + x + h], -1)
        cv = values[corners]  # (P, 4, F)
        ok = agree(cv)
        estimate = cv.mean(1)
        if curve is not None:
            mids = values[torch.stack([(y - h) * wp + x, (y + h) * wp + x, y * wp + x - h, y * wp + x + h], -1)]
            pairs = torch.stack([cv[:, 0] + cv[:, 1], cv[:, 2] + cv[:, 3], cv[:, 0] + cv[:, 2],
                                 cv[:, 1] + cv[:, 3]], 1) * 0.5
            curved = curve((mids - pairs).abs().amax(1), cv[:, :, -1].amin(1))
            quadratic = _within(2 * mids.mean(1) - estimate, torch.cat([cv, mids], 1))
            estimate = torch.where(curved[:, None], quadratic, estimate)
            ok |= curved
        fill(y * wp + x, ok, estimate)
        s = h
    return values, traced


def _within(estimate: torch.Tensor, around: torch.Tensor) -> torch.Tensor:
    """estimate (P, F) clamped to the range of the points it was made from (P, K, F): no overshoot at a step that
    slipped through, and colours and probabilities stay in [0, 1]."""
    return torch.minimum(torch.maximum(estimate, around.amin(1)), around.amax(1))


def _steps(start: int, stop: int, step: int, device: torch.device | str) -> torch.Tensor:
    """torch.arange that is empty (not an error) when start >= stop (a lattice one pixel wide)."""
    return torch.arange(start, max(start, stop), step, device=device)


def reach_pixels(grid: Any, c2w_gl: np.ndarray, intrinsics: Any) -> np.ndarray | None:
    """bool (H, W): pixels whose ray may meet a cell a rigid part can reach at some state (`OccupancyGrid.reach`),
    by projecting each such cell's corners; the others render the same at every state. None (every pixel)
    for a camera with lens distortion or a reach cell at the camera."""
    if grid is None or grid.reach is None or intrinsics.has_distortion():
        return None
    cells = grid.reach.reshape(-1).nonzero()[:, 0].cpu().numpy()
    if not len(cells):
        return np.zeros((intrinsics.h, intrinsics.w), bool)
    shape = np.array(grid.shape)
    lo = grid.lo.cpu().numpy().astype(np.float64)
    size = (grid.hi.cpu().numpy().astype(np.float64) - lo) / shape
    idx = np.stack([cells // (shape[1] * shape[2]), (cells // shape[2]) % shape[1], cells % shape[2]], -1)
    return box_pixels(lo + (idx[:, None, :] + _OFFSETS[None]) * size, c2w_gl, intrinsics)


_OFFSETS = np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), -1).reshape(8, 3)
HULL_POOL = 2  # a part's hull cells are projected in blocks of this many a side: 64^3 cells -> 32^3 boxes at most
# (on the demo 9 ms a mask, 36 % of the pixels for its fridge door; single cells 55 ms and 32 %)


def box_pixels(corners: np.ndarray, c2w_gl: np.ndarray, intrinsics: Any) -> np.ndarray | None:
    """bool (H, W): pixels whose ray may meet one of the boxes with world corners (C, 8, 3) (a box's image lies
    within its corners' bounding rectangle, a pixel of margin on each side); None (every pixel) for a box at the
    camera plane."""
    h, w = intrinsics.h, intrinsics.w
    out = np.zeros((h, w), bool)
    if not len(corners):
        return out
    c2w = opengl_to_opencv(np.asarray(c2w_gl, dtype=np.float64))
    cam = (corners - c2w[:3, 3]) @ c2w[:3, :3]  # camera frame (OpenCV: z forward)
    z = cam[..., 2]
    front = (z > 0).any(1)  # boxes wholly behind the camera are never met
    scale = np.linalg.norm(corners[:, 7] - corners[:, 0], axis=-1)
    cam, z, scale = cam[front], z[front], scale[front]
    if not len(z):
        return out
    if (z.min(1) <= 1e-3 * scale).any():  # a box at the camera plane: any pixel
        return None
    u = intrinsics.fl_x * cam[..., 0] / z + intrinsics.cx
    v = intrinsics.fl_y * cam[..., 1] / z + intrinsics.cy
    # pixel i's ray goes through i + 0.5: a pixel of margin on each side
    u0, u1 = np.floor(u.min(1)).astype(np.int64) - 1, np.ceil(u.max(1)).astype(np.int64) + 1
    v0, v1 = np.floor(v.min(1)).astype(np.int64) - 1, np.ceil(v.max(1)).astype(np.int64) + 1
    keep = (u1 >= 0) & (u0 < w) & (v1 >= 0) & (v0 < h)
    u0, u1 = np.clip(u0[keep], 0, w), np.clip(u1[keep], 0, w)
    v0, v1 = np.clip(v0[keep], 0, h), np.clip(v1[keep], 0, h)
    marks = np.zeros((h + 1, w + 1), np.int64)  # rectangles by a 2-D difference array: O(boxes + pixels)
    np.add.at(marks, (v0, u0), 1)
    np.add.at(marks, (v0, u1), -1)
    np.add.at(marks, (v1, u0), -1)
    np.add.at(marks, (v1, u1), 1)
    return marks.cumsum(0).cumsum(1)[:h, :w] > 0


def hull_pixels(model: Any, values: torch.Tensor, objects: list[int], c2w_gl: np.ndarray,
                intrinsics: Any) -> np.ndarray | None:
    """bool (H, W): pixels whose ray may meet the hull (`PartMotions.hull`) of one of the rigid parts `objects`
    at the states `values` (max_objects,). A sample outside a part's hull is never that part's (`FixedStates`'
    gate), so when only these parts' states change, a ray that meets none of their hulls at the old and at the
    new states renders the same. None (every pixel): a part without a hull, lens distortion, or a hull at the
    camera."""
    m = model.motions
    if intrinsics.has_distortion() or any(not bool(m.hull_set[o]) for o in objects):
        return None
    boxes = []
    for o in objects:
        hull = m.hull[o]
        pool = HULL_POOL if all(n % HULL_POOL == 0 for n in hull.shape) else 1
        blocks = F.max_pool3d(hull[None, None].float(), pool)[0, 0] > 0 if pool > 1 else hull
        cells = blocks.reshape(-1).nonzero()[:, 0].cpu().numpy()
        if not len(cells):
            continue
        shape = np.array(blocks.shape)
        lo = m.hull_lo[o].cpu().numpy().astype(np.float64)
        size = (m.hull_hi[o].cpu().numpy().astype(np.float64) - lo) / shape
        idx = np.stack([cells // (shape[1] * shape[2]), (cells // shape[2]) % shape[1], cells % shape[2]], -1)
        rest = lo + (idx[:, None, :] + _OFFSETS[None]) * size  # (C, 8, 3)
        rt, off = (t.detach().cpu().numpy().astype(np.float64) for t in rest_transform(model, o, values[o]))
        boxes.append((rest - off) @ rt.T)  # rest = world @ rt + off, rt a rotation
    return box_pixels(np.concatenate(boxes) if boxes else np.zeros((0, 8, 3)), c2w_gl, intrinsics)


def _caches(run: Any) -> OrderedDict:
    """The run's last fast images by (camera, size, settings), oldest first (`CACHED_CAMERAS` of them)."""
    if getattr(run, "_image_caches", None) is None:
        run._image_caches = OrderedDict()
    return run._image_caches


class ImageCache:
    """A fast image of one camera (features per lattice pixel) and the states it was drawn at: a render of the
    same camera at other states re-traces only the pixels whose rays meet a moved part's hull (`changed_pixels`)
    and reuses the rest."""

    def __init__(self, key: tuple, values: torch.Tensor, states: torch.Tensor):
        self.key, self.values, self.states = key, values, states
        self.masks: dict[tuple[int, ...], np.ndarray | None] = {}  # moved parts -> their hulls' pixels at `states`


def changed_pixels(model: Any, cache: ImageCache, new: torch.Tensor, c2w_gl: np.ndarray,
                   intrinsics: Any) -> torch.Tensor:
    """bool (H * W,): the pixels a change of the states (max_objects,) from the cached image's to `new` may alter,
    with every object moving rigidly: those whose ray meets a moved part's hull at either state (`hull_pixels`)."""
    n = intrinsics.h * intrinsics.w
    moved = tuple(o for o in range(model.n_objects) if float(cache.states[o]) != float(new[o]))
    if not moved:
        return torch.zeros(n, dtype=torch.bool)
    if moved not in cache.masks:  # a slider dragged: the same parts move again and again from the cached states
        cache.masks[moved] = hull_pixels(model, cache.states, list(moved), c2w_gl, intrinsics)
    masks = [cache.masks[moved], hull_pixels(model, new, list(moved), c2w_gl, intrinsics)]
    if any(mk is None for mk in masks):
        return torch.ones(n, dtype=torch.bool)
    return torch.from_numpy((masks[0] | masks[1]).reshape(-1))


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
    origins, dirs, z_scale = camera_rays(c2w_gl, lattice, pixel_directions(lattice))
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
    affected = None
    if fixed.gate_decides and getattr(run, "checkpoint", None):
        key = (np.asarray(c2w_gl, dtype=np.float64).tobytes(), repr(intrinsics), threshold, term, stride, tolerance,
               id(grid))
        cache = _caches(run).get(key)
        if cache is not None:
            affected = changed_pixels(model, cache, fixed.values, c2w_gl, lattice).to(device)

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
        redo = affected[idx]
        if bool(redo.any()):
            out[redo] = march(idx[redo])
        return out

    if stride > 1:
        feats, traced = refine(hp, wp, stride, trace, agree_by(tolerance), device, smooth_by(BEND * tolerance),
                               max(h, w) // SMOOTH_STEPS)
    else:
        feats = trace(torch.arange(hp * wp, device=device))
        traced = torch.ones(hp * wp, dtype=torch.bool, device=device)
    reused = 0 if cache is None else int((~affected & traced).sum())
    if key is not None and cache is None:
        caches = _caches(run)
        caches[key] = ImageCache(key, feats.clone(), fixed.values.clone())
        while len(caches) > CACHED_CAMERAS:
            caches.popitem(last=False)
    elif cache is not None:
        _caches(run).move_to_end(key)
    feats = feats.view(hp, wp, -1)[:h, :w].reshape(h * w, -1).cpu()
    z_scale = z_scale.reshape(hp, wp)[:h, :w].reshape(-1)  # z-depth = distance * z_scale
    return {"rgb": feats[:, :3], "acc": feats[:, 3], "probs": feats[:, 4: 5 + m], "depth": feats[:, -1],
            "z_scale": z_scale, "march": stats, "traced": int(traced.view(hp, wp)[:h, :w].sum()),
            "rays_reused": reused}
