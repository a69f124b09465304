"""PLY point clouds with object ids: points spread evenly over the exported surfaces (by area), each with the
colour of its surface and the id of its owner (`object`: -1 the static scene, i the object of mapping.yaml's id i),
at chosen states. Binary little-endian: x y z (float32), red green blue (uint8), object (int32)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from interreal import atomic

from .mesh import PartMesh, posed

STATIC_ID = -1


def surface_points(parts: list[PartMesh], states: dict[str, float], count: int, seed: int = 0
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(xyz (N, 3), rgb uint8 (N, 3), object id (N,)): `count` points over all surfaces, shared out by area."""
    meshes = [(p, posed(p, float(states.get(p.owner.name, 0.0)))) for p in parts if p.mesh is not None]
    areas = np.array([m.area for _, m in meshes], float)
    if not len(meshes) or areas.sum() <= 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), np.zeros(0, np.int32)
    shares = np.maximum(1, np.round(count * areas / areas.sum())).astype(int)
    xyz, rgb, ids = [], [], []
    for (part, m), n in zip(meshes, shares):
        pts, face = trimesh.sample.sample_surface(m, int(n), seed=seed)
        bary = trimesh.triangles.points_to_barycentric(m.triangles[face], pts)
        cols = np.asarray(m.visual.vertex_colors, float)[m.faces[face]][..., :3]  # (n, 3 corners, 3)
        xyz.append(pts.astype(np.float32))
        rgb.append(np.clip((bary[..., None] * cols).sum(1), 0, 255).round().astype(np.uint8))
        ids.append(np.full(len(pts), part.owner.obj if part.owner.obj >= 0 else STATIC_ID, np.int32))
    return np.concatenate(xyz), np.concatenate(rgb), np.concatenate(ids)


def write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray, ids: np.ndarray, comment: str = "") -> Path:
    """A binary PLY with an `object` property per vertex."""
    rec = np.empty(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                                    ("blue", "u1"), ("object", "<i4")])
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec["red"], rec["green"], rec["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    rec["object"] = ids
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {c}" for c in comment.splitlines() if c]
    lines += [f"element vertex {len(rec)}", "property float x", "property float y", "property float z",
              "property uchar red", "property uchar green", "property uchar blue", "property int object",
              "end_header"]
    atomic.write_bytes(path, ("\n".join(lines) + "\n").encode() + rec.tobytes())
    return path


def read_ply(path: Path) -> np.ndarray:
    """The records `write_ply` wrote (a structured array): for tests and scripts."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
                   ("object", "<i4")])
    return np.frombuffer(data[end:], dtype=dt)
