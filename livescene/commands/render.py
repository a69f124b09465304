"""`livescene render RUN`: cameras (the dataset's, held-out, a smooth path or a JSON file) x states -> PNGs, an
optional video and RUN/renders/render.json, through `render.render_view`."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from interreal import atomic
from interreal.video import write_video

from ..device import configure_threads
from ..errors import LiveSceneError, writing
from ..language import apply_command
from ..render import (RenderMeter, choose_cameras, colorize_depth, colorize_probs, parse_states, parse_sweep,
                      read_camera_path, render_view, smooth_path, warn_unseen)
from ..run import load_run, unfinished_note


def add_arguments(p) -> None:
    p.add_argument("run", type=Path, help="run folder of `livescene train`")
    p.add_argument("--out", type=Path, default=None, help="folder for PNGs (default RUN/renders)")
    p.add_argument("--cameras", default="dataset",
                   help="dataset (the dataset's cameras), held-out, path (a smooth path along them) or a JSON file")
    p.add_argument("--frames", default="",
                   help="positions within the --cameras set, e.g. 0,8,16: with dataset the dataset's frames, with "
                        "held-out the held-out frames (0 = the first held-out frame), with path or a JSON file its "
                        "cameras (default: every 8th dataset frame, every held-out frame, every path/JSON camera)")
    p.add_argument("--count", type=int, default=30, help="cameras on a smooth path")
    p.add_argument("--state", action="append", default=[], metavar='"NAME=VALUE"', help="fix an object's state (repeatable)")
    p.add_argument("--command", default=None, metavar='"open the fridge"',
                   help='a spoken command: open / close / half open an object found by text (needs the language extra)')
    p.add_argument("--sweep", default=None, metavar='"NAME=A:B:N"',
                   help="sweep one object's state from each camera --cameras/--frames choose (with the default "
                        "--cameras dataset and no --frames: from the first dataset frame)")
    p.add_argument("--time", type=float, default=None, help="learned states of this normalised frame time for free objects")
    p.add_argument("--scale", type=float, default=1.0, help="resolution scale of the rendered images")
    p.add_argument("--video", type=Path, default=None, help="also write an H.264 MP4 of the RGB frames")
    p.add_argument("--fps", type=int, default=15)
    p.add_argument("--depth", action="store_true", help="also write depth maps (colour PNG + 16-bit mm PNG)")
    p.add_argument("--probs", action="store_true", help="also write object-probability maps")
    p.add_argument("--device", default="auto")
    p.add_argument("--dataset", type=Path, default=None,
                   help="the run's dataset where it is now, when it was moved (a run renders with its dataset's "
                        "cameras, frame times and object names; it is validated like any other read)")
    p.add_argument("--exact", action="store_true",
                   help="the exact renderer (every sample read; slower), e.g. to compare with the fast default")
    p.epilog = ('examples:\n'
                '  livescene render out/run --cameras held-out --depth --probs\n'
                '  livescene render out/run --sweep "fridge door=0:1:30" --video out/door.mp4\n'
                '  livescene render out/run --cameras held-out --frames 0 --sweep "fridge door=0:1:30"  # 1st held-out\n'
                '  livescene render out/run --command "open the fridge" --cameras held-out\n'
                '  livescene render out/run --cameras path --count 60 --state "fridge door=0.3" --video out/path.mp4\n'
                '  livescene render out/run --cameras cams.json   # {"frames": [{"transform_matrix": ..., "states": {...}}]}\n'
                '\na part set to a state that no training view near a camera showed is named in a warning:\n'
                'it is drawn from a side the capture never saw it at, and may come out blurred or missing')


def main(args) -> int:
    configure_threads(0)
    check_render_args(args)
    base_states = parse_states(args.state)  # before the run loads: a bad state costs nothing
    run = load_run(args.run, device=args.device, dataset=args.dataset)
    if note := unfinished_note(args.run, run.step):
        print(note, file=sys.stderr)
    views = run.views
    unknown = [n for n in base_states if n not in run.names]
    if unknown:
        raise LiveSceneError(f"--state: unknown object {unknown[0]!r}; this run has {run.names}")
    if args.command:  # livescene.language: "open the fridge" -> {"fridge door": 1.0}
        base_states.update(apply_command(run, args.command))
    jobs: list[dict[str, Any]] = []
    if args.cameras in ("dataset", "held-out"):
        for i in (views.held_out if args.cameras == "held-out" else range(len(views.times))):
            jobs.append({"c2w": views.c2w_gl[i], "intrinsics": views.intrinsics[i], "states": None,
                         "time": float(views.times[i]), "name": views.dataset.frames[i].fid})
    elif args.cameras == "path":
        for j, m in enumerate(smooth_path(views.c2w_gl, args.count)):
            jobs.append({"c2w": m, "intrinsics": views.intrinsics[0], "states": None,
                         "time": j / max(args.count - 1, 1), "name": f"path_{j:04d}"})
    else:
        for j, c in enumerate(read_camera_path(Path(args.cameras), views.intrinsics[0])):
            jobs.append({**c, "time": 0.0, "name": f"cam_{j:04d}"})
    jobs = choose_cameras(jobs, args)
    if not jobs:
        raise LiveSceneError("no cameras to render (check --cameras / --frames)")
    if args.sweep:
        name, values = parse_sweep(args.sweep)
        jobs = [{**cam, "states": {name: float(v)}, "name": f"{cam['name']}_{name.replace(' ', '_')}_{j:03d}"}
                for cam in jobs for j, v in enumerate(values)]
    for msg in warn_unseen(run, jobs, base_states):
        print(f"livescene render: warning: {msg}", file=sys.stderr)
    out_dir = args.out or (args.run / "renders")
    frames: list[np.ndarray] = []
    written: list[Path] = []  # removed again when the disk fills or a folder is read-only: no half output
    meter = RenderMeter()
    with writing(out_dir, cleanup=written):
        _render_jobs(run, jobs, base_states, args, out_dir, frames, written, meter)
        if args.video:
            written.append(args.video)
            write_video(args.video, frames, fps=args.fps)
        speed = meter.report()  # RUN/renders/render.json: what was rendered and how fast
        written.append(out_dir / "render.json")
        atomic.write_json(out_dir / "render.json", {"run": str(args.run), "step": run.step, "views": len(frames),
                                                    "video": str(args.video) if args.video else None,
                                                    "names": [j["name"] for j in jobs], "speed": speed})
    print(f"livescene render: {len(frames)} views -> {out_dir}" + (f", {args.video}" if args.video else "")
          + f" ({speed['renderer']} renderer, {speed['seconds_per_frame'] or 0:.2f} s a frame, "
            f"{speed['rays_per_s'] or 0:,} rays/s)")
    return 0


def check_render_args(args) -> None:
    """Numbers of the command line that would render nothing or garbage: refused with the option named."""
    if args.time is not None and not (np.isfinite(args.time) and 0.0 <= args.time <= 1.0):
        raise LiveSceneError(f"--time {args.time}: a normalised frame time in [0, 1]")
    if not (np.isfinite(args.scale) and 0.0 < args.scale <= 16.0):
        raise LiveSceneError(f"--scale {args.scale}: a resolution scale in (0, 16]")
    if not 1 <= args.count <= 100_000:
        raise LiveSceneError(f"--count {args.count}: between 1 and 100000 cameras")
    if not 1 <= args.fps <= 240:
        raise LiveSceneError(f"--fps {args.fps}: between 1 and 240")
    if args.cameras not in ("dataset", "held-out", "path") and not Path(args.cameras).is_file():
        raise LiveSceneError(f"--cameras {args.cameras!r}: use dataset, held-out, path or an existing JSON file")


def _render_jobs(run, jobs, base_states, args, out_dir: Path, frames: list, written: list[Path],
                 meter: RenderMeter | None = None) -> None:
    for job in tqdm(jobs, desc="render"):
        intr = job["intrinsics"]
        if args.scale != 1.0:
            intr = intr.scaled(max(1, round(intr.w * args.scale)), max(1, round(intr.h * args.scale)))
        states = {**(job.get("states") or {}), **base_states}
        t = args.time if args.time is not None else job["time"]
        out = render_view(run, job["c2w"], intr, states or None, time=t, fast=not getattr(args, "exact", False))
        if meter is not None:
            meter.add(out)
        rgb8 = (out["rgb"] * 255).round().astype(np.uint8)
        images = {f"{job['name']}.png": rgb8}
        if args.depth:
            images[f"{job['name']}_depth.png"] = colorize_depth(out["depth"])
            images[f"{job['name']}_depth_mm.png"] = np.clip(out["depth"] * 1000, 0, 65535).astype(np.uint16)
        if args.probs:
            images[f"{job['name']}_probs.png"] = colorize_probs(out["probs"])
        for name, image in images.items():
            written.append(out_dir / name)
            atomic.write_image(out_dir / name, image)
        frames.append(rgb8)
