"""URDF of a trained run: a fixed base link for the static scene and one link per object, joined to the base by a
revolute (hinge) or prismatic (slide) joint from the part's motion, or a fixed joint when it has none.

Each link has a visual mesh (OBJ with vertex colours) and convex collision pieces (V-HACD through trimesh:
simulators collide convex shapes, and MuJoCo would otherwise take a whole room's convex hull), an inertial from
those pieces at a uniform density, and paths relative to the URDF. A hinge's link frame sits on its axis at the
measured origin, a slide's and a fixed object's at the middle of its mesh; joint limits are the state range
0..1 times the motion's range. Lengths are metres when the capture gives a scale (`metres_per_unit`), else the
dataset's world units (the file says which). A `<mujoco>` element keeps MuJoCo's URDF reader from stripping the
meshes' folder and dropping the visual meshes; other readers ignore it.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import QhullError

from interreal import atomic

from ..errors import MissingExtraError
from .mesh import PartMesh, save_mesh, simplify

DENSITY = 500.0  # kg per cubic metre (or per cubic unit without a scale): a wooden or hollow object's
MIN_MASS = 1e-3  # kg: a sliver of a part still gets a mass a simulator integrates stably
MIN_INERTIA = 1e-9  # kg m^2 added to the inertia's diagonal, so it stays positive definite
EFFORT, VELOCITY = 100.0, 1.0  # joint limits URDF requires; a captured scene measures neither
HULLS_PART, HULLS_STATIC = 16, 32  # convex pieces at most per moving part / for the static scene
VHACD_RESOLUTION = 50_000  # voxels V-HACD reads a mesh with (its default 400k costs 4x the time)
VHACD_FACES = 10_000  # the mesh is simplified to this many faces first (V-HACD voxelises it anyway)


def link_name(name: str, taken: set[str]) -> str:
    """A URDF-safe, unique link name for an object name ("fridge door" -> "fridge_door")."""
    base = re.sub(r"[^A-Za-z0-9_]+", "_", name).strip("_") or "part"
    if base[0].isdigit():
        base = "part_" + base
    out, i = base, 2
    while out in taken:
        out, i = f"{base}_{i}", i + 1
    taken.add(out)
    return out


def convex_pieces(mesh, static: bool) -> list:
    """Convex pieces (trimesh.Trimesh list) covering the mesh. The static scene is voxelised hollow (a room's
    walls enclose air, which a flood fill would make solid); a part is filled."""
    try:
        pieces = simplify(mesh, VHACD_FACES).convex_decomposition(
            maxConvexHulls=HULLS_STATIC if static else HULLS_PART, resolution=VHACD_RESOLUTION,
            fillMode="surface" if static else "flood", asyncACD=False)
    except ImportError as exc:
        raise MissingExtraError("export", f"URDF collision meshes (convex decomposition: {exc})") from exc
    out = [h for h in (_hull(p["vertices"] if isinstance(p, dict) else p.vertices) for p in pieces) if h is not None]
    return out or [h for h in [_hull(mesh.vertices)] if h is not None]


def _hull(points):
    """The convex hull of points as a closed mesh, or None for a degenerate (flat, tiny) piece."""
    pts = np.unique(np.asarray(points, float), axis=0)
    if len(pts) < 4:
        return None
    try:
        hull = trimesh.convex.convex_hull(pts)
    except (QhullError, ValueError):
        return None
    return hull if hull.volume > 0 and len(hull.faces) >= 4 else None


@dataclass
class Inertial:
    mass: float
    com: np.ndarray  # (3,) in the link frame
    inertia: np.ndarray  # (3, 3) about the centre of mass, link axes


def inertial(pieces: list, density: float) -> Inertial:
    """Mass, centre of mass and inertia of the union of closed convex pieces at a uniform density (positive; the
    least mass about the origin when there is no piece)."""
    if not pieces:
        return Inertial(MIN_MASS, np.zeros(3), np.eye(3) * MIN_INERTIA)
    solid = trimesh.util.concatenate(pieces)
    props = solid.mass_properties  # volume integrals add over closed, outward-facing pieces
    volume = max(float(props.volume), 0.0)
    mass = max(density * volume, MIN_MASS)
    com = np.asarray(props.center_mass if volume > 0 else solid.bounds.mean(0), float)
    inertia = np.asarray(props.inertia, float) * (mass / max(float(props.mass), 1e-30)) if volume > 0 \
        else np.zeros((3, 3))
    inertia = 0.5 * (inertia + inertia.T) + np.eye(3) * MIN_INERTIA
    return Inertial(mass, com, inertia)


def _xyz(v) -> str:
    return " ".join(f"{float(x):.9g}" for x in v)


def _geometry(parent: ET.Element, tag: str, name: str, filename: str) -> None:
    el = ET.SubElement(parent, tag, name=name)
    ET.SubElement(el, "origin", xyz="0 0 0", rpy="0 0 0")
    geo = ET.SubElement(el, "geometry")
    ET.SubElement(geo, "mesh", filename=filename, scale="1 1 1")


def _link(robot: ET.Element, name: str, visual: str | None, collisions: list[str], inert: Inertial) -> None:
    link = ET.SubElement(robot, "link", name=name)
    i = ET.SubElement(link, "inertial")
    ET.SubElement(i, "origin", xyz=_xyz(inert.com), rpy="0 0 0")
    ET.SubElement(i, "mass", value=f"{inert.mass:.9g}")
    t = inert.inertia
    ET.SubElement(i, "inertia", ixx=f"{t[0, 0]:.9g}", ixy=f"{t[0, 1]:.9g}", ixz=f"{t[0, 2]:.9g}",
                  iyy=f"{t[1, 1]:.9g}", iyz=f"{t[1, 2]:.9g}", izz=f"{t[2, 2]:.9g}")
    if visual is not None:
        _geometry(link, "visual", f"{name}_visual", visual)
    for j, c in enumerate(collisions):
        _geometry(link, "collision", f"{name}_collision_{j}", c)


def link_origin(part: PartMesh, scale: float) -> np.ndarray:
    """Where a part's link frame sits in the world (scaled): on a hinge's axis, else the middle of its mesh."""
    o = part.owner
    if o.kind == "hinge":
        return np.asarray(o.motion["origin"], float) * scale
    return np.asarray(part.mesh.bounds, float).mean(0) * scale


def write_urdf(parts: list[PartMesh], out: Path, name: str, scale: float, units: str,
               density: float = DENSITY, progress=None) -> dict:
    """Write OUT/<name>.urdf and OUT/meshes/; returns what was written per link (joints, files, masses).
    parts[0] is the static scene (the base link, empty when it has no surface); objects without a mesh are left
    out (and named in the result)."""
    out = Path(out)
    (out / "meshes").mkdir(parents=True, exist_ok=True)
    robot = ET.Element("robot", name=re.sub(r"[^A-Za-z0-9_]+", "_", name) or "scene")
    robot.append(ET.Comment(f" lengths in {units}; masses from a uniform density of {density:g} kg per cubic "
                            f"{'metre' if units == 'metres' else 'unit'}; written by `livescene export` "))
    mj = ET.SubElement(robot, "mujoco")
    ET.SubElement(mj, "compiler", meshdir=".", strippath="false", discardvisual="false", balanceinertia="true")
    taken: set[str] = set()
    report: dict = {"links": [], "skipped": []}
    base = link_name("base", taken)
    for part in parts:
        o = part.owner
        if part.mesh is None:
            report["skipped"].append(o.name)
            if o.obj < 0:  # no static surface: the joints still need their fixed base
                _link(robot, base, None, [], Inertial(MIN_MASS, np.zeros(3), np.eye(3) * MIN_INERTIA))
            if progress:
                progress(1)
            continue
        lname = base if o.obj < 0 else link_name(o.name, taken)
        origin = np.zeros(3) if o.obj < 0 else link_origin(part, scale)
        mesh = part.mesh.copy()
        mesh.apply_scale(scale)
        mesh.apply_translation(-origin)
        visual = f"meshes/{lname}.obj"
        save_mesh(mesh, out / visual, include_normals=True, include_color=True)
        pieces = convex_pieces(mesh, static=o.obj < 0)
        cols = []
        for j, piece in enumerate(pieces):
            rel = f"meshes/{lname}_collision_{j}.obj"
            save_mesh(piece, out / rel, include_normals=False, include_color=False)
            cols.append(rel)
        inert = inertial(pieces, density)
        _link(robot, lname, visual, cols, inert)
        entry = {"object": o.name, "link": lname, "visual": visual, "collision": cols, "mass": inert.mass,
                 "faces": len(mesh.faces)}
        if o.obj >= 0:
            entry["joint"] = _joint(robot, part, lname, base, origin, scale)
        report["links"].append(entry)
        if progress:
            progress(1)
    ET.indent(robot)
    path = out / f"{robot.get('name')}.urdf"
    atomic.write_text(path, '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n")
    report["urdf"] = path.name
    return report


def _joint(robot: ET.Element, part: PartMesh, child: str, parent: str, origin: np.ndarray, scale: float) -> dict:
    o = part.owner
    kind = {"hinge": "revolute", "slide": "prismatic"}.get(o.kind, "fixed")
    j = ET.SubElement(robot, "joint", name=f"{child}_joint", type=kind)
    ET.SubElement(j, "parent", link=parent)
    ET.SubElement(j, "child", link=child)
    ET.SubElement(j, "origin", xyz=_xyz(origin), rpy="0 0 0")
    entry = {"name": f"{child}_joint", "type": kind, "origin": origin.tolist()}
    if kind != "fixed":
        axis = np.asarray(o.motion["axis"], float)
        amount = float(o.motion["range"]) * (scale if kind == "prismatic" else 1.0)
        lower, upper = min(0.0, amount), max(0.0, amount)
        ET.SubElement(j, "axis", xyz=_xyz(axis))
        ET.SubElement(j, "limit", lower=f"{lower:.9g}", upper=f"{upper:.9g}", effort=f"{EFFORT:g}",
                      velocity=f"{VELOCITY:g}")
        entry.update(axis=axis.tolist(), lower=lower, upper=upper, per_state=amount)
    else:
        entry["state"] = o.state
    return entry
