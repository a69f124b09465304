"""Export a trained run into the world: per-object meshes (`mesh`), a URDF with joints from the part motions
(`urdf`), a GLB of the scene at any state (`glb`) and point clouds with object ids (`ply`).

`export_run(run, out, formats, ...)` extracts each piece once and writes every asked-for format from it, with
OUT/export.json saying what was written, in which units, at which states and how long each step took.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from interreal import atomic

from ..errors import LiveSceneError
from .glb import write_glb
from .level import calibrate_level
from .mesh import FieldReader, Owner, PartMesh, extract, grid_steps, owners, save_mesh
from .ply import surface_points, write_ply
from .urdf import link_name, write_urdf

FORMATS = ("urdf", "glb", "ply", "mesh")
DEFAULT_RESOLUTION = 160  # voxels along the scene box's longest side
DEFAULT_FACES = 60_000  # faces per piece at most after simplification
DEFAULT_POINTS = 200_000  # points of the PLY cloud
FOG_CONTRAST = 3.0  # a surface level under this many times the air's density is called fog (a warning)


@dataclass
class ExportOptions:
    formats: tuple[str, ...] = ("urdf",)
    states: dict[str, float] = field(default_factory=dict)  # rigid parts' pose (glb, ply), others' read state
    resolution: int = DEFAULT_RESOLUTION
    faces: int = DEFAULT_FACES
    points: int = DEFAULT_POINTS
    metres_per_unit: float | None = None  # None: 1 for a simulator-truth dataset, else the dataset's own units
    level: float | None = None  # surface density; None: measured on the run's views (`level.calibrate_level`)
    name: str = "scene"


def scale_of(run, metres_per_unit: float | None) -> tuple[float, str]:
    """(factor applied to lengths, units name): metres when the capture gives a scale (the simulator's truth
    datasets are metric; `--metres-per-unit` gives one), else the dataset's world units unscaled."""
    if metres_per_unit is not None:
        return float(metres_per_unit), "metres"
    if (run.dataset.root / "reports" / "synth_truth.json").is_file():
        return 1.0, "metres"
    return 1.0, "dataset units"


def check_options(opts: ExportOptions, names: list[str] | None = None) -> None:
    """Refuse options that would export nothing or garbage, naming the option (`names`: the run's objects)."""
    bad = [f for f in opts.formats if f not in FORMATS]
    if bad or not opts.formats:
        raise LiveSceneError(f"--format {','.join(bad) or '(none)'}: choose from {', '.join(FORMATS)}")
    unknown = [n for n in opts.states if names is not None and n not in names]
    if unknown:
        raise LiveSceneError(f"--state: unknown object {unknown[0]!r}; this run has {names}")
    if not 16 <= opts.resolution <= 1024:
        raise LiveSceneError(f"--resolution {opts.resolution}: voxels along the scene's longest side, 16..1024")
    if opts.faces < 100:
        raise LiveSceneError(f"--faces {opts.faces}: at least 100 faces a piece")
    if opts.points < 1:
        raise LiveSceneError(f"--points {opts.points}: at least 1")
    if opts.metres_per_unit is not None and not (0 < opts.metres_per_unit < 1e6):
        raise LiveSceneError(f"--metres-per-unit {opts.metres_per_unit}: a positive scale")
    if opts.level is not None and not (0 < opts.level < 1e8):
        raise LiveSceneError(f"--level {opts.level}: a positive density (per unit length)")


def motion_warnings(owner_list: list[Owner]) -> list[str]:
    """What a reader of the export should know about objects without a rigid motion."""
    fixed = [o for o in owner_list if o.kind == "fixed"]
    if not fixed:
        return []
    if len(fixed) == len(owner_list) - 1:
        return [f"the run has no part motions (articulation.json, `interreal motions DS`, then train): every object "
                f"is exported as a fixed link at its state ({', '.join(f'{o.name}={o.state:g}' for o in fixed)})"]
    return [f"{o.name!r} has no rigid motion in the run: exported as a fixed link at state {o.state:g}" for o in fixed]


def export_run(run, out: Path, opts: ExportOptions, progress: Callable[[int], None] | None = None,
               set_total: Callable[[int], None] | None = None) -> dict:
    """Extract every piece of the run once and write the asked-for formats under `out`; returns the report that
    OUT/export.json holds."""
    check_options(opts, run.names)
    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if (out / "export.json").is_file():  # an earlier export here: its meshes must not outlive it (a URDF of
        for old in [*out.glob("meshes/*.obj"), *out.glob("parts/*.ply")]:  # fewer pieces would leave some behind)
            old.unlink()
    owner_list = owners(run, opts.states)
    warnings = motion_warnings(owner_list)
    scale, units = scale_of(run, opts.metres_per_unit)
    if units != "metres":
        warnings.append("the capture gives no metric scale: lengths are the dataset's world units "
                        "(pass --metres-per-unit for metres)")
    timing: dict[str, float] = {}
    steps = grid_steps(run, owner_list, opts.resolution) + (len(owner_list) if "urdf" in opts.formats else 0)
    if set_total:
        set_total(steps)
    level, air = (opts.level, None) if opts.level is not None else calibrate_level(run)
    if level is None:
        raise LiveSceneError("no training view of the run sees a surface (no ray stops half its light): the run is "
                             "untrained or its views look at nothing; pass --level DENSITY to cut the field anyway")
    if air is not None and level < FOG_CONTRAST * air:
        warnings.append(f"the field is foggy: its surfaces are only {level / max(air, 1e-9):.1f}x as dense as the air "
                        f"in front of them ({level:.3g} vs {air:.3g} a unit), so the meshes are blobs: train longer")
    timing["level_s"] = round(time.perf_counter() - t0, 2)
    reader = FieldReader(run, owner_list)
    parts: list[PartMesh] = [extract(run, o, reader, opts.resolution, opts.faces, level, progress)
                             for o in owner_list]
    for p in parts:
        if p.mesh is None:
            warnings.append(f"{p.owner.name!r}: the field gives it no surface at this resolution: left out")
    timing["meshes_s"] = round(time.perf_counter() - t0 - timing["level_s"], 2)
    report: dict = {"run": str(run.run_dir), "step": run.step, "formats": list(opts.formats), "units": units,
                    "metres_per_unit": scale if units == "metres" else None, "resolution": opts.resolution,
                    "level": level, "level_measured": opts.level is None, "air_density": air,
                    "states": {o.name: (opts.states.get(o.name, 0.0) if o.rigid else o.state)
                               for o in owner_list if o.obj >= 0},
                    "pieces": [_piece_record(p, scale) for p in parts],
                    "files": []}
    if "mesh" in opts.formats:
        (out / "parts").mkdir(exist_ok=True)
        taken = {"static"}
        for p in parts:
            if p.mesh is not None:
                m = p.mesh.copy()
                m.apply_scale(scale)
                path = out / "parts" / f"{'static' if p.owner.obj < 0 else link_name(p.owner.name, taken)}.ply"
                save_mesh(m, path)
                report["files"].append(str(path.relative_to(out)))
    if "glb" in opts.formats:
        write_glb(parts, out / "scene.glb", opts.states, scale)
        report["files"].append("scene.glb")
    if "ply" in opts.formats:
        xyz, rgb, ids = surface_points(parts, opts.states, opts.points)
        names = ", ".join(f"{o.obj}={o.name}" for o in owner_list if o.obj >= 0)
        write_ply(out / "points.ply", xyz * scale, rgb, ids, comment=f"object: -1=static scene, {names}\n"
                                                                     f"units: {units}")
        report["files"].append("points.ply")
    if "urdf" in opts.formats:
        t1 = time.perf_counter()
        report["urdf"] = write_urdf(parts, out, opts.name, scale, units, progress=progress)
        report["files"].append(report["urdf"]["urdf"])
        timing["urdf_s"] = round(time.perf_counter() - t1, 2)
    timing["total_s"] = round(time.perf_counter() - t0, 2)
    report["timing"] = timing
    report["warnings"] = warnings
    atomic.write_json(out / "export.json", report)
    return report


def _piece_record(part: PartMesh, scale: float) -> dict:
    """export.json's entry for one piece: what it is, how fine and large its mesh is, its motion."""
    o = part.owner
    rec = {"object": o.name, "kind": o.kind, "voxel": part.cell * scale, "faces_marched": part.faces_before,
           "faces": 0 if part.mesh is None else len(part.mesh.faces), "seconds": round(part.seconds, 2)}
    if o.rigid:
        rec["motion"] = {k: (np.asarray(v).tolist() if k != "range" else float(v)) for k, v in o.motion.items()}
    return rec
