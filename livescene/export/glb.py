"""GLB of the whole scene at chosen states: the static scene and every object, each a named node, rigid parts moved
by their motion from rest (glTF is y-up; the scene keeps the dataset's axes, the node names its objects)."""

from __future__ import annotations

from pathlib import Path

import trimesh

from interreal import atomic

from .mesh import PartMesh, posed


def scene_at(parts: list[PartMesh], states: dict[str, float], scale: float = 1.0):
    """trimesh.Scene of the parts with meshes, rigid parts at their `states` (default 0: rest)."""
    scene = trimesh.Scene()
    for part in parts:
        if part.mesh is None:
            continue
        m = posed(part, float(states.get(part.owner.name, 0.0)))
        m.apply_scale(scale)
        scene.add_geometry(m, node_name=part.owner.name, geom_name=part.owner.name)
    return scene


def write_glb(parts: list[PartMesh], path: Path, states: dict[str, float], scale: float = 1.0) -> Path:
    """OUT/scene.glb (vertex colours as COLOR_0)."""
    atomic.write_bytes(path, scene_at(parts, states, scale).export(file_type="glb"))
    return path
