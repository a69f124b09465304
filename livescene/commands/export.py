"""`livescene export RUN --format urdf|glb|ply|mesh --out DIR`: the trained scene as a simulator-ready articulated
asset (URDF with per-part meshes and joints), a GLB of the scene at any state, point clouds with object ids, or
per-part meshes, through `livescene.export`."""

from __future__ import annotations

import sys
from pathlib import Path

from tqdm import tqdm

from ..device import configure_threads
from ..errors import LiveSceneError, writing
from ..export import DEFAULT_FACES, DEFAULT_POINTS, DEFAULT_RESOLUTION, FORMATS, ExportOptions, check_options, export_run
from ..render import parse_states
from ..run import load_run


def add_arguments(p) -> None:
    p.add_argument("run", type=Path, help="run folder of `livescene train`")
    p.add_argument("--format", default="urdf", metavar="|".join(FORMATS),
                   help="what to write, one or several separated by commas (default urdf): urdf = OUT/scene.urdf "
                        "+ OUT/meshes/ (a base link for the static scene, a link per object with its joint); glb = "
                        "OUT/scene.glb at --state; ply = OUT/points.ply (x y z, colour, object id: -1 static); "
                        "mesh = OUT/parts/<object>.ply (rigid parts at rest)")
    p.add_argument("--out", type=Path, required=True, help="output folder (created; OUT/export.json says what is in it)")
    p.add_argument("--state", action="append", default=[], metavar='"NAME=VALUE"',
                   help="an object's state (repeatable): where glb / ply draw a moving part, and the state an "
                        "object without a rigid motion is read at (default 0, at rest)")
    p.add_argument("--resolution", type=int, default=DEFAULT_RESOLUTION,
                   help=f"voxels along the scene box's longest side (default {DEFAULT_RESOLUTION}; parts get at "
                        f"least 48 across their own box)")
    p.add_argument("--faces", type=int, default=DEFAULT_FACES,
                   help=f"faces per piece at most after simplification (default {DEFAULT_FACES:,})")
    p.add_argument("--points", type=int, default=DEFAULT_POINTS, help=f"points of the PLY cloud (default {DEFAULT_POINTS:,})")
    p.add_argument("--metres-per-unit", type=float, default=None,
                   help="the capture's scale: lengths are written in metres (default: metres for a simulator-truth "
                        "dataset, else the dataset's own world units, said in the URDF and export.json)")
    p.add_argument("--level", type=float, default=None,
                   help="surface density (per unit length); default: measured on the run's training views")
    p.add_argument("--name", default="scene", help="the URDF robot's and file's name (default scene)")
    p.add_argument("--device", default="auto")
    p.add_argument("--dataset", type=Path, default=None, help="the run's dataset where it is now, when it was moved")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.epilog = ('examples:\n'
                '  livescene export out/run --format urdf --out out/asset          # OUT/scene.urdf + OUT/meshes/\n'
                '  livescene export out/run --format glb --state "fridge door=0.5" --out out/glb\n'
                '  livescene export out/run --format urdf,glb,ply,mesh --resolution 256 --out out/all\n'
                '  livescene export out/run --format urdf --metres-per-unit 0.23 --out out/asset   # metric URDF\n'
                '\nthe URDF: a fixed base link (the static scene, whole behind the parts), one link per object joined\n'
                'by a revolute (hinge) or prismatic (slide) joint from the run\'s part motions (articulation.json),\n'
                'limits = state 0..1; objects without a motion become fixed links (with a warning). Visual meshes are\n'
                'OBJ with vertex colours, collision meshes convex pieces (V-HACD), inertials from those at 500 kg/m^3')


def parse_formats(text: str) -> tuple[str, ...]:
    fmts = tuple(dict.fromkeys(f.strip().lower() for f in text.split(",") if f.strip()))
    bad = [f for f in fmts if f not in FORMATS]
    if bad or not fmts:
        raise LiveSceneError(f"--format {text!r}: choose one or more of {', '.join(FORMATS)} (comma-separated)")
    return fmts


def main(args) -> int:
    configure_threads(0)
    opts = ExportOptions(formats=parse_formats(args.format), states=parse_states(args.state),
                         resolution=args.resolution, faces=args.faces, points=args.points,
                         metres_per_unit=args.metres_per_unit, level=args.level, name=args.name)
    check_options(opts)  # before the run loads: a bad option costs nothing
    if args.out.exists() and not args.out.is_dir():
        raise LiveSceneError(f"--out {args.out} is a file: give a folder")
    run = load_run(args.run, device=args.device, dataset=args.dataset)
    bar = tqdm(total=0, unit="step", desc="livescene export", disable=args.no_progress, file=sys.stderr)

    def set_total(n: int) -> None:
        bar.total = n
        bar.refresh()

    with writing(args.out):
        try:
            report = export_run(run, args.out, opts, progress=bar.update, set_total=set_total)
        finally:
            bar.close()
    for w in report["warnings"]:
        print(f"livescene export: warning: {w}", file=sys.stderr)
    pieces = ", ".join(f"{p['object']} ({p['kind']}, {p['faces']:,} faces)" for p in report["pieces"] if p["faces"])
    print(f"livescene export: {', '.join(report['files'])} -> {args.out} in {report['timing']['total_s']:.0f} s; "
          f"{pieces}; lengths in {report['units']}")
    return 0
