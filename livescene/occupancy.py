"""Occupancy grid of a trained run: per cell of the scene box, the largest density the field gives there at any
object state, so the fast renderer (`livescene.march`) can skip the cells that are empty at every state.

A world point is read, depending on who owns it, as the background (world frame, the background's k), as an object
without a rigid motion (world frame, k = its state, any state) or as a rigid part (its rest frame at the part's
state, only inside the part's hull, k = 0 or its state; `livescene.articulation`). The grid takes the maximum of all
of them: the static field at the background's k; the field over the k axis's nodes where some object has no rigid
motion; and each rigid part's rest-frame density carried through a sweep of its motion, in steps of at most half a
cell. Densities are read at every cell corner (a cell takes its corners' maximum) and the result is dilated by a
cell, so a thin surface between sample points is kept. Built once after training and saved in the checkpoint
(`trainer.Trainer.fit`); for runs trained before, built on first use and cached next to the checkpoint
(`RUN/occupancy.pt`, `grid_for`).
"""

from __future__ import annotations

import io
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import torch
import torch.nn.functional as F

from interreal import atomic

from .articulation import KIND_CODES
from .field import LiveSceneModel
from .march import rest_transform

GRID_VERSION = 2  # 2: with `reach`
MAX_RES = 128  # cells along the box's longest axis at most; at least MIN_RES, else the field's finest plane
MIN_RES = 16  # resolution. Cells are near cubes (a thin box gets fewer cells across): one size for every axis
SWEEP_SHARE = 2  # objects moved along the k axis alone are swept on a lattice this many times coarser first
MAX_SWEEP_STEPS = 512
MIN_CELL_OPACITY = 1e-4  # rigid parts are swept only where denser than this threshold (`threshold`): lower
# thresholds than this are not honoured for them
CELL_OPACITY = 1e-3  # default threshold: a cell is empty where its densest state lets less than this much light
# stop over one cell length (a ray crossing the whole box through such cells loses at most ~20 %, in practice the
# air's density is orders below it: see recipes/bench_render.py for the measured trade-off)
CACHE_NAME = "occupancy.pt"
FLOAT16_MAX = 6.0e4


@dataclass
class OccupancyGrid:
    """Max density over states per cell (X, Y, Z) of the box (lo, hi), for the checkpoint at `step`."""

    density: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor
    step: int
    info: dict[str, Any] = field(default_factory=dict)
    # (X, Y, Z) bool: cells a rigid part's hull reaches at some state, dilated a cell. A ray none of whose samples
    # falls in one renders the same at every state when every object moves rigidly (`render_view`'s state cache)
    reach: torch.Tensor | None = None
    _masks: dict[float, torch.Tensor] = field(default_factory=dict, repr=False)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.density.shape)

    def threshold(self, opacity: float = CELL_OPACITY) -> float:
        """The density at which one cell length lets `opacity` of the light stop."""
        return cell_threshold(self.lo, self.hi, self.shape, opacity)

    def mask(self, threshold: float | None = None) -> torch.Tensor:
        """Flat bool (G**3,) of the occupied cells at `threshold` (default: `threshold()`)."""
        t = self.threshold() if threshold is None else float(threshold)
        if t not in self._masks:
            self._masks[t] = (self.density.float() >= t).reshape(-1)
        return self._masks[t]

    def occupied_fraction(self, threshold: float | None = None) -> float:
        return float(self.mask(threshold).float().mean())

    def tester(self, threshold: float | None = None, reach: bool = False) -> Callable[[torch.Tensor], torch.Tensor]:
        """points (P, 3) world -> bool (P,): in an occupied cell (`reach`: a cell a rigid part can reach), or
        outside the box (the fields read such a point at the box's border: never skipped)."""
        mask = self.reach.reshape(-1) if reach else self.mask(threshold)
        dims = torch.tensor(self.shape, device=self.lo.device)
        scale = dims / (self.hi - self.lo)
        stride = torch.tensor([self.shape[1] * self.shape[2], self.shape[2], 1], device=self.lo.device)

        def occupied(pts: torch.Tensor) -> torch.Tensor:
            cell = ((pts - self.lo) * scale).floor().long()
            inside = ((cell >= 0) & (cell < dims)).all(-1)
            cell = torch.minimum(cell.clamp(min=0), dims - 1)
            return mask[(cell * stride).sum(-1)] | ~inside  # outside the box (a ray that misses it): always read

        return occupied

    def to(self, device: torch.device | str) -> OccupancyGrid:
        if _same_device(self.density.device, torch.device(device)):
            return self
        return OccupancyGrid(self.density.to(device), self.lo.to(device), self.hi.to(device), self.step, self.info,
                             None if self.reach is None else self.reach.to(device))

    def state(self) -> dict[str, Any]:
        """What the checkpoint stores (CPU tensors, float16 densities)."""
        return {"version": GRID_VERSION, "step": self.step, "density": self.density.detach().cpu(),
                "lo": self.lo.detach().cpu(), "hi": self.hi.detach().cpu(), "info": dict(self.info),
                "reach": None if self.reach is None else self.reach.detach().cpu()}

    @classmethod
    def from_state(cls, state: dict[str, Any], device: torch.device | str = "cpu") -> OccupancyGrid | None:
        """None for a grid of another version (rebuilt on use)."""
        if not state or state.get("version") != GRID_VERSION:
            return None
        reach = state.get("reach")
        return cls(state["density"].to(device), state["lo"].to(device), state["hi"].to(device), int(state["step"]),
                   dict(state.get("info", {})), None if reach is None else reach.to(device))


def _same_device(a: torch.device, b: torch.device) -> bool:
    """cuda and cuda:0 are one device (torch.device equality says no)."""
    return a.type == b.type and (a.index or 0) == (b.index or 0)


def cell_threshold(lo: torch.Tensor, hi: torch.Tensor, shape: tuple[int, int, int], opacity: float) -> float:
    """The density at which one (shortest) cell length lets `opacity` of the light stop."""
    cell = float(((hi - lo) / torch.tensor(shape, device=lo.device)).min())
    return -math.log1p(-opacity) / max(cell, 1e-12)


def default_resolution(model: LiveSceneModel) -> int:
    """Cells along the longest axis: the field's finest plane resolution, within [MIN_RES, MAX_RES] (finer cells
    than the field's own add no detail to where it is empty)."""
    finest = model.cfg.resolution * max(model.cfg.scales)
    return int(min(MAX_RES, max(MIN_RES, finest)))


def grid_shape(lo: torch.Tensor, hi: torch.Tensor, resolution: int) -> tuple[int, int, int]:
    """Cells per axis: `resolution` along the longest, near-cubic cells."""
    ext = (hi - lo).float()
    return tuple(int(max(MIN_RES // 2, round(resolution * float(e / ext.max())))) for e in ext)


def _lattice(lo: torch.Tensor, hi: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
    """The corner points ((X + 1) (Y + 1) (Z + 1), 3) (ij order) of a grid of `shape` cells over the box."""
    axes = [torch.linspace(float(lo[d]), float(hi[d]), shape[d] + 1, device=lo.device) for d in range(3)]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def _corner_max(values: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
    """Corner values -> per cell the largest of its 8 corners (X, Y, Z)."""
    return F.max_pool3d(values.view(1, 1, *(n + 1 for n in shape)), 2, stride=1)[0, 0]


def _dilate(grid: torch.Tensor) -> torch.Tensor:
    return F.max_pool3d(grid[None, None], 3, stride=1, padding=1)[0, 0]


class _Densities:
    """The radiance field's density at normalised points and k, in chunks, counting the reads."""

    def __init__(self, model: LiveSceneModel, box: tuple[torch.Tensor, torch.Tensor], chunk: int = 1 << 16):
        self.model, self.box, self.chunk, self.reads = model, box, chunk, 0

    def world(self, pts: torch.Tensor, k: float) -> torch.Tensor:
        """Density (P,) at world points (normalised with the scene box, as `place` does) read at k."""
        out = torch.empty(pts.shape[0], device=pts.device)
        for s in range(0, pts.shape[0], self.chunk):
            xyz = self.model.to_field(pts[s: s + self.chunk], self.box)
            out[s: s + self.chunk] = self.model.field.density(xyz, torch.full_like(xyz[:, 0], k))[0]
        self.reads += pts.shape[0]
        return out


def _part_density(dens: _Densities, model: LiveSceneModel, obj: int, box: tuple[torch.Tensor, torch.Tensor],
                  shape: tuple[int, int, int], k_values: list[float]
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(lo, hi, density (H, H, H)) of a rigid part in its rest frame: the field's max over `k_values` inside its
    hull (zero outside: the gate keeps the part from owning anything there)."""
    m = model.motions
    if bool(m.hull_set[obj]):
        lo, hi, hull = m.hull_lo[obj], m.hull_hi[obj], m.hull[obj]
    else:  # no hull: the part may own any point of its rest frame
        lo, hi = box
        hull = torch.ones(shape, dtype=torch.bool, device=lo.device)
    return lo, hi, _masked_corner_max(dens, lo, hi, hull, k_values)


def _masked_corner_max(dens: "_Densities", lo: torch.Tensor, hi: torch.Tensor, cells: torch.Tensor,
                       k_values: list[float]) -> torch.Tensor:
    """(X, Y, Z) max over `k_values` of the density at each set cell's corners, 0 in the other cells: only the
    corners of the cells set in `cells` (bool (X, Y, Z)) are read from the field."""
    shape = tuple(cells.shape)
    touched = F.max_pool3d(F.pad(cells.float(), (1, 1, 1, 1, 1, 1))[None, None], 2, stride=1)[0, 0] > 0
    nodes = _lattice(lo, hi, shape)
    at = touched.reshape(-1).nonzero()[:, 0]
    values = torch.zeros(nodes.shape[0], device=lo.device)
    for k in k_values:
        values[at] = torch.maximum(values[at], dens.world(nodes[at], k))
    return _corner_max(values, shape) * cells


def _sweep_steps(model: LiveSceneModel, obj: int, lo: torch.Tensor, hi: torch.Tensor, cell: float) -> int:
    """States to visit so that no point of the part's box moves more than a cell between two of them."""
    m = model.motions
    rng = abs(float(m.range[obj]))
    if int(m.kind[obj]) == KIND_CODES["hinge"]:
        corners = torch.stack(torch.meshgrid(*[torch.stack([lo[d], hi[d]]) for d in range(3)], indexing="ij"),
                              -1).reshape(-1, 3) - m.origin[obj]
        axis = m.axis[obj]
        radial = corners - (corners @ axis)[:, None] * axis
        travel = rng * float(radial.norm(dim=-1).max())
    else:
        travel = rng * float(m.axis[obj].norm())
    return int(min(MAX_SWEEP_STEPS, max(2, math.ceil(travel / cell) + 1)))


def _sweep_part(grid: torch.Tensor, reach: torch.Tensor, model: LiveSceneModel, obj: int,
                part: tuple[torch.Tensor, ...], box: tuple[torch.Tensor, torch.Tensor], floor: float) -> int:
    """Carry a rigid part's rest-frame density through its motion into the world grid (in place): points spread
    at most a world cell apart over every rest cell denser than `floor` are moved to each swept state (at most a
    cell apart too), and the world cell a point lands in takes its density if larger. Returns the states swept."""
    plo, phi, dens = part
    shape = grid.shape
    blo, bhi = box
    cell = (bhi - blo) / torch.tensor(shape, device=blo.device)
    steps = _sweep_steps(model, obj, plo, phi, float(cell.min()))
    h = dens.shape
    at = (dens.reshape(-1) > 0).nonzero()[:, 0]  # the hull (a density > 0 inside it): `reach`
    if not len(at):
        return steps
    rest_cell = (phi - plo) / torch.tensor(h, device=blo.device)
    sub = int(max(1, math.ceil(float((rest_cell / cell.min()).max()))))  # points per rest cell and axis
    offs = (torch.stack(torch.meshgrid(*[torch.arange(sub, device=blo.device)] * 3, indexing="ij"), -1)
            .reshape(-1, 3) + 0.5) / sub
    idx = torch.stack([at // (h[1] * h[2]), (at // h[2]) % h[1], at % h[2]], -1)
    pts = (plo + (idx[:, None, :] + offs[None]) * rest_cell).reshape(-1, 3)
    val = dens.reshape(-1)[at].repeat_interleave(offs.shape[0])
    dense = val >= floor
    flat, reached = grid.view(-1), reach.view(-1)
    dims = torch.tensor(shape, device=blo.device)
    stride = torch.tensor([shape[1] * shape[2], shape[2], 1], device=blo.device)
    for s in torch.linspace(0, 1, steps, device=blo.device):
        rt, off = rest_transform(model, obj, s)
        c = (((pts - off) @ rt.T - blo) / cell).floor().long()  # rest = world @ rt + off, rt a rotation
        ok = ((c >= 0) & (c < dims)).all(-1)
        idx = (c * stride).sum(-1)
        reached[idx[ok]] = True
        ok &= dense
        flat.scatter_reduce_(0, idx[ok], val[ok], reduce="amax")
    return steps


def _max_over_k(dens: _Densities, lo: torch.Tensor, hi: torch.Tensor, shape: tuple[int, int, int],
                k_values: list[float], floor: float) -> torch.Tensor:
    """Per cell the field's max density in the world frame over `k_values`: on a lattice SWEEP_SHARE times
    coarser first, then at full resolution only in the coarse cells (and their neighbours) denser than `floor`."""
    coarse_shape = tuple(max(2, d // SWEEP_SHARE) for d in shape)
    nodes = _lattice(lo, hi, coarse_shape)
    sweep = torch.zeros(nodes.shape[0], device=lo.device)
    for k in k_values:
        sweep = torch.maximum(sweep, dens.world(nodes, k))
    coarse = _dilate(_corner_max(sweep, coarse_shape))
    near = F.interpolate(coarse[None, None], size=shape, mode="nearest")[0, 0] >= floor
    return _masked_corner_max(dens, lo, hi, near, k_values)


@torch.no_grad()
def build_grid(model: LiveSceneModel, box: tuple[torch.Tensor, torch.Tensor], step: int = 0,
               resolution: int | None = None, clock: Callable[[], float] = time.perf_counter) -> OccupancyGrid:
    """The occupancy grid of `model` over the scene box (lo, hi) (world units), for the checkpoint at `step`
    (`clock` times the build: the trainer passes its own)."""
    t0 = clock()
    was_training = model.training
    model.eval()
    lo, hi = box[0].float(), box[1].float()
    shape = grid_shape(lo, hi, resolution or default_resolution(model))
    dens = _Densities(model, (lo, hi))
    grid = _corner_max(dens.world(_lattice(lo, hi, shape), model.background_k), shape)
    n = model.n_objects
    rigid = model.motions.rigid(n) if model.motions is not None else []
    k_nodes = [i / max(model.cfg.k_resolution - 1, 1) for i in range(max(model.cfg.k_resolution, 1))]
    free = [o for o in range(n) if o not in rigid]
    floor = cell_threshold(lo, hi, shape, MIN_CELL_OPACITY)
    if free:  # objects moved along the k axis alone: any state, in the world frame
        grid = torch.maximum(grid, _max_over_k(dens, lo, hi, shape, k_nodes, floor))
    swept = {}
    reach = torch.zeros(shape, dtype=torch.bool, device=lo.device)
    for o in rigid:
        ks = [0.0] if model.cfg.part_k == "rest" else k_nodes
        part = _part_density(dens, model, o, (lo, hi), shape, ks)
        swept[o] = _sweep_part(grid, reach, model, o, part, (lo, hi), floor)
    grid = _dilate(grid).clamp(max=FLOAT16_MAX).half()
    if was_training:
        model.train()
    out = OccupancyGrid(grid, lo.clone(), hi.clone(), int(step),
                        reach=_dilate(reach.float()) > 0 if rigid else None)
    out.info = {"shape": list(shape), "field_reads": dens.reads, "swept_states": swept,
                "k_nodes": len(k_nodes) if free else 0, "min_threshold": floor,
                "build_s": round(clock() - t0, 3), "occupied": round(out.occupied_fraction(), 4)}
    return out


def build_cost(model: LiveSceneModel, box: tuple[torch.Tensor, torch.Tensor], shrink: int = 4,
               clock: Callable[[], float] = time.perf_counter) -> float:
    """Seconds `build_grid` will take, from a build at 1/`shrink` of the resolution scaled by the cell count (the
    work is a field read per corner and state): a time-limited training reserves it before its last step."""
    lo, hi = box[0].float(), box[1].float()
    full = default_resolution(model)
    build_grid(model, box, resolution=MIN_RES, clock=clock)  # warm: a cold first read (CUDA's kernels loading) would be scaled up
    small = build_grid(model, box, resolution=max(MIN_RES, full // shrink), clock=clock)
    cells = [math.prod(grid_shape(lo, hi, res)) for res in (full, max(MIN_RES, full // shrink))]
    return small.info["build_s"] * cells[0] / cells[1]


def grid_for(run, build: bool = True) -> OccupancyGrid | None:
    """The run's occupancy grid: the one its checkpoint carries, else the cached one next to it
    (RUN/occupancy.pt, for runs trained before grids), else built now and cached (when `build`). None for a
    model that has no saved checkpoint (being trained: its grid would be stale after the next step)."""
    grid = getattr(run, "occupancy", None)
    if isinstance(grid, OccupancyGrid):
        run.occupancy = grid = grid.to(run.device)
        return grid
    ckpt = getattr(run, "checkpoint", None)
    if ckpt is None:
        return None
    cache = Path(run.run_dir) / CACHE_NAME
    lo, hi = run.box
    if cache.exists():
        try:
            saved = torch.load(cache, map_location="cpu", weights_only=False)
            grid = OccupancyGrid.from_state(saved.get("grid"), run.device)
            if (grid is not None and saved.get("checkpoint") == Path(ckpt).name and grid.step == run.step
                    and torch.allclose(grid.lo, lo.float()) and torch.allclose(grid.hi, hi.float())):
                run.occupancy = grid
                return grid
        except Exception:  # noqa: BLE001 - a broken or foreign cache is rebuilt
            pass
    if not build:
        return None
    grid = build_grid(run.model, (lo, hi), run.step)
    run.occupancy = grid
    try:
        buf = io.BytesIO()
        torch.save({"checkpoint": Path(ckpt).name, "grid": grid.state()}, buf)
        atomic.write_bytes(cache, buf.getvalue())
    except OSError:  # a read-only run folder: the grid lives for this process only
        pass
    return grid
