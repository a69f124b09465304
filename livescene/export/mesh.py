"""Meshes of a trained run: the static scene and each object, cut from the radiance field's density where the
probability field gives them the space, coloured from the field.

Who owns a point follows `LiveSceneModel.place` (the renderer's rule). A rigid part (`livescene.articulation`) is
read in its rest frame at state 0, where the rest frame is the world: its mesh is the part at rest, ready to be
moved by its joint. The static scene is what the background owns once every rigid part's claim is left out, so
it is whole behind the parts (a fridge's inside, a drawer's slot): at state 0 a closed door hides it, at any other
state it is what the views that saw the door open trained. An object without a rigid motion is read in the world
at the state asked for (its k-axis carries its change).

Surface: marching cubes (scikit-image) of the owner's density at the run's surface level (`livescene.export.level`:
measured where the renderer draws surfaces in the training views), on a zero-padded grid so every piece is closed
(collision and inertia need volumes). Small disconnected pieces (floaters) are dropped, the rest is simplified
(quadric decimation, `fast_simplification` through trimesh) and each vertex takes the colour the field renders
along a short ray that looks at it along its normal (`vertex_colors`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import trimesh
from scipy.spatial.transform import Rotation
from skimage.measure import marching_cubes

from interreal import atomic

from ..articulation import KIND_CODES
from ..errors import MissingExtraError
from ..occupancy import grid_for
from ..sampler import volume_weights

CHUNK = 1 << 16  # points per field call
MIN_PIECE_SHARE = 0.002  # pieces with fewer faces than this share of the mesh's are floaters (the largest is kept)
COLOR_SAMPLES = 8  # samples on the short ray that colours a vertex ...
COLOR_REACH = 1.5  # ... from this many voxels outside the surface to as many inside
MARGIN_CLIP = 4.0  # the implicit function's values are clipped to [-1, this]: only its zero crossing matters
MIN_PART_CELLS = 48  # a part's grid has at least this many cells along its longest side
KIND_NAMES = {v: k for k, v in KIND_CODES.items()}


@dataclass
class Owner:
    """One exported piece: the static scene (`obj` -1) or object `obj`, read in its own frame."""

    name: str
    obj: int
    kind: str  # "static", "hinge", "slide", or "fixed" (an object without a rigid motion)
    state: float = 0.0  # the state a fixed object is read at (rigid parts are read at rest)
    motion: dict = field(default_factory=dict)  # hinge / slide: axis, origin, range (world units of the run)

    @property
    def rigid(self) -> bool:
        return self.kind in ("hinge", "slide")


def owners(run, states: dict[str, float]) -> list[Owner]:
    """The static scene and every object of the run, with the motion its checkpoint was trained with."""
    model = run.model
    out = [Owner("static", -1, "static")]
    rigid = model.motions.rigid(model.n_objects) if model.motions is not None else []
    for i, name in enumerate(run.names):
        if i in rigid:
            m = model.motions
            motion = {"axis": m.axis[i].cpu().numpy().astype(float), "origin": m.origin[i].cpu().numpy().astype(float),
                      "range": float(m.range[i])}
            out.append(Owner(name, i, KIND_NAMES[int(m.kind[i])], 0.0, motion))
        else:
            out.append(Owner(name, i, "fixed", float(states.get(name, 0.0))))
    return out


class FieldReader:
    """Density, ownership and colour of each owner at the states of an export (no gradients, in chunks)."""

    def __init__(self, run, owner_list: list[Owner]):
        self.model = run.model
        self.box = run.box
        self.device = run.device
        model = self.model
        self.values = torch.zeros(model.cfg.max_objects, device=self.device)
        for o in owner_list:
            if o.obj >= 0 and not o.rigid:
                self.values[o.obj] = o.state  # rigid parts are read at rest: their slots stay 0
        self.rigid = [o.obj for o in owner_list if o.rigid]
        self.grid = grid_for(run, build=False)  # the checkpoint's (or cached) grid; None: every node is read

    def occupied(self, threshold: float):
        """points (P, 3) world -> bool (P,): in a cell whose densest state reaches `threshold` (None: no grid).
        A rigid part's rest frame at state 0 is the world, which the grid covers."""
        return self.grid.tester(threshold) if self.grid is not None else None

    def _k(self, owner: Owner, n: int) -> torch.Tensor:
        if owner.obj < 0:
            k = float(self.model.background_k)
        else:
            k = 0.0 if owner.rigid else owner.state
        return torch.full((n,), k, device=self.device)

    @torch.no_grad()
    def density(self, owner: Owner, pts: torch.Tensor) -> torch.Tensor:
        """The owner's field density (P,) at points of its frame, ownership left aside."""
        out = torch.empty(pts.shape[0], device=self.device)
        for s in range(0, pts.shape[0], CHUNK):
            p = pts[s: s + CHUNK]
            out[s: s + CHUNK] = self.model.field.density(self.model.to_field(p, self.box), self._k(owner, p.shape[0]))[0]
        return out

    @torch.no_grad()
    def margin(self, owner: Owner, pts: torch.Tensor) -> torch.Tensor:
        """(P,) how far inside the owner's region points of its frame are, in log-probability: positive exactly
        where `LiveSceneModel.owner` gives it the point at the export's states (the most probable object, at
        least the rejection threshold; the static scene: no object reaches it), continuous across the border so
        that a surface cut there lies on it, not on a voxel staircase. The static scene competes only with
        objects that have no rigid motion."""
        model = self.model
        s_rej = float(model.cfg.reject_threshold)
        log_s = math.log(s_rej) if s_rej > 0 else None
        n_obj = model.n_objects
        out = torch.empty(pts.shape[0], device=self.device)
        for s in range(0, pts.shape[0], CHUNK):
            p = pts[s: s + CHUNK]
            vals = self.values.expand(p.shape[0], -1)
            logits = model.place(p, torch.zeros_like(p), vals, self.box, grad_logits=False).logits
            if owner.obj < 0 and self.rigid:
                logits[:, self.rigid] = -1e4
            lp = torch.log_softmax(logits, -1)[:, :n_obj]  # the objects' log-probabilities
            if owner.obj < 0:
                competing = n_obj - (len(self.rigid) if self.rigid else 0)
                if competing == 0:
                    m = torch.full((p.shape[0],), MARGIN_CLIP, device=self.device)
                elif log_s is None:  # no rejection: an object always owns the point
                    m = torch.full((p.shape[0],), -MARGIN_CLIP, device=self.device)
                else:
                    m = log_s - lp.max(-1).values
            else:
                mine = lp[:, owner.obj]
                others = lp.clone()
                others[:, owner.obj] = -float("inf")
                m = mine - others.max(-1).values if n_obj > 1 else torch.full_like(mine, MARGIN_CLIP)
                if log_s is not None:
                    m = torch.minimum(m, mine - log_s)
            out[s: s + CHUNK] = m.clamp(-MARGIN_CLIP, MARGIN_CLIP)
        return out

    @torch.no_grad()
    def color(self, owner: Owner, pts: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        """RGB (P, 3) of the owner's field at points seen along unit directions dirs (its frame)."""
        out = torch.empty(pts.shape[0], 3, device=self.device)
        for s in range(0, pts.shape[0], CHUNK):
            p = pts[s: s + CHUNK]
            _, h = self.model.field.density(self.model.to_field(p, self.box), self._k(owner, p.shape[0]))
            out[s: s + CHUNK] = self.model.field.color(h, dirs[s: s + CHUNK])
        return out


def grid_box(run, owner: Owner, resolution: int) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int]]:
    """(lo, hi, nodes per axis) of the owner's grid: the scene box for the static scene and fixed objects, a rigid
    part's hull box (where it can be at rest) when it has one, with near-cubic voxels. A part gets at least
    MIN_PART_CELLS cells along its longest side but never voxels finer than the scene's (`resolution` there)."""
    lo, hi = (t.detach().cpu().numpy().astype(np.float64) for t in run.box)
    scene_cell = float((hi - lo).max()) / resolution
    cell = scene_cell
    m = run.model.motions
    if owner.rigid and m is not None and bool(m.hull_set[owner.obj]):
        lo = m.hull_lo[owner.obj].cpu().numpy().astype(np.float64)
        hi = m.hull_hi[owner.obj].cpu().numpy().astype(np.float64)
        cell = min(scene_cell, float((hi - lo).max()) / MIN_PART_CELLS)
    nodes = tuple(int(max(2, math.ceil(float(e) / cell) + 1)) for e in (hi - lo))
    return lo, lo + (np.array(nodes) - 1) * cell, nodes


def sample_grid(reader: FieldReader, owner: Owner, lo: np.ndarray, hi: np.ndarray, nodes: tuple[int, int, int],
                level: float, progress: Callable[[int], None] | None = None) -> np.ndarray:
    """The owner's implicit surface function on the grid's nodes (X, Y, Z), positive inside: the smaller of its
    density's excess over the level (sigma / level - 1) and its ownership margin (`FieldReader.margin`), so the
    solid is the part of the dense space the owner owns. Nodes in cells of the run's occupancy grid (max density
    over states, `livescene.occupancy`) below half the level are not read (most of a scene is air), and the
    margin is asked only where the density reaches half the level: below it the node is outside either way."""
    axes = [torch.linspace(float(lo[d]), float(hi[d]), nodes[d], device=reader.device) for d in range(3)]
    yz = torch.stack(torch.meshgrid(axes[1], axes[2], indexing="ij"), -1).reshape(-1, 2)
    occupied = reader.occupied(0.5 * level)
    out = np.full(nodes, -1.0, np.float32)
    for i in range(nodes[0]):  # one slab at a time: memory stays small, progress moves
        pts = torch.cat([axes[0][i].expand(yz.shape[0], 1), yz], 1)
        read = occupied(pts).nonzero()[:, 0] if occupied is not None else torch.arange(len(pts), device=pts.device)
        if len(read):
            g = torch.full((len(pts),), -1.0, device=pts.device)
            g[read] = (reader.density(owner, pts[read]) / level - 1.0).clamp(-1.0, MARGIN_CLIP)
            dense = read[g[read] >= -0.5]
            if len(dense):
                g[dense] = torch.minimum(g[dense], reader.margin(owner, pts[dense]))
            out[i] = g.reshape(nodes[1], nodes[2]).cpu().numpy()
        if progress is not None:
            progress(1)
    return out


def surface(volume: np.ndarray, lo: np.ndarray, cell: float):
    """trimesh.Trimesh of the zero level set of `volume` (X, Y, Z; positive inside) whose node (0, 0, 0) sits at
    `lo`, faces outward; None when nothing is inside. The volume is padded with outside, so every piece is closed."""
    if not (volume > 0).any():
        return None
    vol = np.pad(volume, 1, constant_values=-1.0)
    verts, faces, _, _ = marching_cubes(vol, level=0.0, spacing=(cell, cell, cell), allow_degenerate=False)
    verts = verts + (np.asarray(lo) - cell)
    return trimesh.Trimesh(verts, faces[:, ::-1], process=True)  # scikit-image winds faces inward for a solid


def drop_floaters(mesh, share: float = MIN_PIECE_SHARE):
    """The mesh without its disconnected pieces smaller than `share` of its faces (the largest always stays)."""
    if len(mesh.faces) == 0:
        return mesh
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    counts = np.bincount(labels)
    keep = counts >= max(1, share * len(mesh.faces))
    keep[np.argmax(counts)] = True
    mesh = mesh.submesh([np.nonzero(keep[labels])[0]], append=True)
    mesh.remove_unreferenced_vertices()
    return mesh


def simplify(mesh, faces: int):
    """At most `faces` faces (quadric decimation); a smaller mesh is returned as it is."""
    if faces <= 0 or len(mesh.faces) <= faces:
        return mesh
    try:
        out = mesh.simplify_quadric_decimation(face_count=int(faces))
    except ImportError as exc:
        raise MissingExtraError("export", f"mesh simplification ({exc})") from exc
    return out if len(out.faces) else mesh


def vertex_colors(reader: FieldReader, owner: Owner, mesh, cell: float) -> np.ndarray:
    """uint8 RGBA (V, 4): what the field renders along a short ray looking at each vertex against its normal
    (from COLOR_REACH voxels outside to as many inside; the nearest sample's colour where that ray is clear)."""
    v = torch.tensor(np.array(mesh.vertices), dtype=torch.float32, device=reader.device)
    n = torch.tensor(np.array(mesh.vertex_normals), dtype=torch.float32, device=reader.device)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    t = torch.linspace(COLOR_REACH, -COLOR_REACH, COLOR_SAMPLES + 1, device=reader.device) * cell
    mids = 0.5 * (t[1:] + t[:-1])
    pts = (v[:, None, :] + mids[None, :, None] * n[:, None, :]).reshape(-1, 3)
    dirs = (-n[:, None, :]).expand(-1, COLOR_SAMPLES, -1).reshape(-1, 3)
    sigma = reader.density(owner, pts).view(-1, COLOR_SAMPLES)
    rgb = reader.color(owner, pts, dirs).view(-1, COLOR_SAMPLES, 3)
    edges = (-t).expand(sigma.shape[0], -1)  # distances along the looking ray, increasing
    w = volume_weights(sigma, edges)
    total = w.sum(-1, keepdim=True)
    mid = rgb[:, COLOR_SAMPLES // 2]
    col = torch.where(total > 1e-3, (w[..., None] * rgb).sum(1) / total.clamp_min(1e-9), mid)
    rgba = np.full((len(v), 4), 255, np.uint8)
    rgba[:, :3] = (col.clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()
    return rgba


@dataclass
class PartMesh:
    """An exported piece: its owner and its coloured mesh (world units; a rigid part at rest)."""

    owner: Owner
    mesh: object  # trimesh.Trimesh, or None when the field gives the owner no surface
    cell: float
    seconds: float = 0.0
    faces_before: int = 0


def extract(run, owner: Owner, reader: FieldReader, resolution: int, faces: int, level: float,
            progress: Callable[[int], None] | None = None) -> PartMesh:
    """The owner's coloured, simplified mesh: the surface where its density reaches `level`."""
    t0 = time.perf_counter()
    lo, hi, nodes = grid_box(run, owner, resolution)
    cell = float((hi - lo)[0] / (nodes[0] - 1))
    volume = sample_grid(reader, owner, lo, hi, nodes, level, progress)
    mesh = surface(volume, lo, cell)
    before = 0
    if mesh is not None:
        before = len(mesh.faces)
        mesh = simplify(drop_floaters(mesh), faces)
        mesh.visual.vertex_colors = vertex_colors(reader, owner, mesh, cell)
    return PartMesh(owner, mesh, cell, time.perf_counter() - t0, before)


def grid_steps(run, owner_list: list[Owner], resolution: int) -> int:
    """Slabs `extract` will read for these owners (a progress bar's total)."""
    return sum(grid_box(run, o, resolution)[2][0] for o in owner_list)


def posed(part: PartMesh, state: float):
    """A copy of a part's mesh at `state`: a rigid part moved by its motion, anything else as it is."""
    m = part.mesh.copy()
    o = part.owner
    if o.rigid:
        m.apply_transform(motion_matrix(o, state))
    return m


def motion_matrix(owner: Owner, state: float) -> np.ndarray:
    """4x4 world transform of a rigid part at `state` from its rest pose (`interreal.dataset.Articulation.pose`)."""
    mo = owner.motion
    axis = np.asarray(mo["axis"], float)
    amount = float(state) * float(mo["range"])
    m = np.eye(4)
    if owner.kind == "slide":
        m[:3, 3] = axis * amount
        return m
    rot = Rotation.from_rotvec(axis * amount).as_matrix()
    origin = np.asarray(mo["origin"], float)
    m[:3, :3] = rot
    m[:3, 3] = origin - rot @ origin
    return m


def save_mesh(mesh, path, **options) -> None:
    """Write a mesh (format from the suffix: obj, ply, glb, ...) atomically."""
    path = Path(path)
    data = mesh.export(file_type=path.suffix.lstrip(".").lower(), **options)
    atomic.write_bytes(path, data.encode() if isinstance(data, str) else data)
