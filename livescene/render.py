"""`livescene render` and `render_view`: any camera at any object states -> RGB, depth, object probabilities.

States: a mapping {name: value} (missing objects take the learned value at `time`), a sequence of values in
mapping.yaml order, or None (all learned values at `time`, i.e. what the scene looked like at that frame).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import torch

from interreal import atomic
from interreal.dataset import Intrinsics
from interreal.video import write_video  # noqa: F401 - part of this module's API

from .data import camera_rays, nearest_views, pixel_directions
from .errors import LiveSceneError
from .sampler import render_rays

StateSpec = Mapping[str, float] | Sequence[float] | np.ndarray | None


def resolve_states(run, states: StateSpec, time: float = 0.0) -> np.ndarray:
    """(M,) values in [0, 1] for the run's objects."""
    names = run.names
    with torch.no_grad():
        learned = run.model.frame_values(torch.tensor([time], dtype=torch.float32, device=run.device))[0]
    vals = learned[: len(names)].cpu().numpy().astype(np.float32)
    if states is None:
        return vals
    if isinstance(states, Mapping):
        for name, v in states.items():
            if name not in names:
                raise LiveSceneError(f"unknown object {name!r}; this run has {names}")
            vals[names.index(name)] = float(v)
        return np.clip(vals, 0, 1)
    arr = np.asarray(states, dtype=np.float32).reshape(-1)
    if arr.shape[0] != len(names):
        raise LiveSceneError(f"got {arr.shape[0]} state values, the run has {len(names)} objects {names}")
    return np.clip(arr, 0, 1)


UNSEEN_TOL = 0.15  # a state this far from every state the nearby training views showed was not seen from there


def learned_frame_states(run) -> np.ndarray:
    """(N, M) the states the run learned for every dataset frame (labels where given, the variable elsewhere)."""
    with torch.no_grad():
        t = torch.as_tensor(run.views.times, device=run.device)
        return run.model.frame_values(t)[:, : run.model.n_objects].cpu().numpy()


def unseen_states(run, learned: np.ndarray, c2w_gl: np.ndarray, states: Mapping[str, float],
                  tol: float = UNSEEN_TOL) -> dict[str, float]:
    """Objects set to a state that no training view near this camera showed (within `tol`) -> the nearest state
    those views did show. Such a part is drawn from a side the capture never saw it at that state, and the field
    does not carry a surface across states and sides: expect it blurred or missing (on the benchmark, a camera
    whose training views all had the door open scored 12.9 dB at door 0.25, its door pixels given to the
    background). learned (N, M) from `learned_frame_states`."""
    views = run.views
    close = nearest_views(np.asarray(views.c2w_gl)[:, :3, 3], views.train, np.asarray(c2w_gl)[:3, 3])
    out = {}
    for name, v in states.items():
        if name not in run.names:
            continue  # render_view names the unknown object
        seen = learned[close, run.names.index(name)]
        j = int(np.argmin(np.abs(seen - v)))
        if abs(seen[j] - v) > tol:
            out[name] = float(seen[j])
    return out


def warn_unseen(run, jobs: list[dict[str, Any]], base_states: Mapping[str, float],
                tol: float = UNSEEN_TOL) -> list[str]:
    """One warning per object that some camera renders at a state never seen from near it (`unseen_states`)."""
    learned = learned_frame_states(run)
    found: dict[str, list[tuple[float, float]]] = {}
    for job in jobs:
        states = {**(job.get("states") or {}), **base_states}
        for name, near in unseen_states(run, learned, job["c2w"], states, tol).items():
            found.setdefault(name, []).append((float(states[name]), near))
    msgs = []
    for name, hits in found.items():
        asked = sorted({round(a, 2) for a, _ in hits})
        shown = sorted({round(n, 2) for _, n in hits})
        msgs.append(f"{name!r} at {_values(asked)}: {len(hits)} of {len(jobs)} renders have no training view near "
                    f"their camera that showed it at that state (those views show {_values(shown)}), so it is drawn "
                    f"from a side the capture never saw it at; it may come out blurred or missing there")
    return msgs


def _values(vals: list[float], most: int = 5) -> str:
    text = ", ".join(f"{v:.2f}" for v in vals[:most])
    return text + (f" ... ({len(vals)} values)" if len(vals) > most else "")


@torch.no_grad()
def render_view(run, c2w_gl: np.ndarray, intrinsics: Intrinsics, states: StateSpec = None, *, time: float = 0.0,
                chunk: int = 8192) -> dict[str, np.ndarray]:
    """Render one camera (4x4 camera-to-world, OpenGL axes as in transforms.json) at the given states.

    Returns rgb (H, W, 3) float32 in [0, 1], depth (H, W) z-depth in world units, acc (H, W),
    probs (H, W, M + 1): softmax of the rendered object logits, background last, and `states` (M,)."""
    model = run.model
    was_training = model.training
    model.eval()
    vals = resolve_states(run, states, time)
    origins, dirs, z_scale = camera_rays(c2w_gl, intrinsics, pixel_directions(intrinsics))
    m = model.n_objects
    values = model.pad_values(torch.as_tensor(vals, device=run.device)[None])
    rgb, depth, acc, probs = [], [], [], []
    o_all = torch.from_numpy(np.ascontiguousarray(origins)).to(run.device)
    d_all = torch.from_numpy(dirs).to(run.device)
    for s in range(0, o_all.shape[0], chunk):
        o, d = o_all[s: s + chunk], d_all[s: s + chunk]
        out = render_rays(model, o, d, values.expand(o.shape[0], -1), run.box, run.config.sampler, gen=None,
                          with_logits=True)
        rgb.append(out.rgb.clamp(0, 1).cpu())
        depth.append(out.depth.cpu())
        acc.append(out.acc.cpu())
        lg = torch.cat([out.logits[:, :m], out.logits[:, -1:]], -1)
        probs.append(torch.softmax(lg, -1).cpu())
    if was_training:
        model.train()
    h, w = intrinsics.h, intrinsics.w
    return {"rgb": torch.cat(rgb).view(h, w, 3).numpy(),
            "depth": (torch.cat(depth).numpy() * z_scale).reshape(h, w).astype(np.float32),
            "acc": torch.cat(acc).view(h, w).numpy(),
            "probs": torch.cat(probs).view(h, w, m + 1).numpy(),
            "states": vals}


# ----------------------------------------------------------------------------------------------------------------
# Cameras
# ----------------------------------------------------------------------------------------------------------------
def _slerp(q0: np.ndarray, q1: np.ndarray, t: float) -> np.ndarray:
    dot = float(np.dot(q0, q1))
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + t * (q1 - q0)
        return q / np.linalg.norm(q)
    th = np.arccos(dot)
    return (np.sin((1 - t) * th) * q0 + np.sin(t * th) * q1) / np.sin(th)


def _mat_to_quat(r: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(r).as_quat()


def _quat_to_mat(q: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(q).as_matrix()


def smooth_path(c2ws: np.ndarray, n: int) -> np.ndarray:
    """n cameras along the dataset trajectory: Catmull-Rom positions through ~8 key cameras, slerped rotations."""
    keys = c2ws[np.linspace(0, len(c2ws) - 1, min(8, len(c2ws))).round().astype(int)]
    if len(keys) == 1:
        return np.repeat(keys, n, 0)
    p = keys[:, :3, 3]
    q = np.stack([_mat_to_quat(k[:3, :3]) for k in keys])
    out = []
    for u in np.linspace(0, len(keys) - 1, n):
        i = min(int(u), len(keys) - 2)
        t = u - i
        p0, p1, p2, p3 = p[max(i - 1, 0)], p[i], p[i + 1], p[min(i + 2, len(keys) - 1)]
        pos = 0.5 * ((2 * p1) + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t * t
                     + (-p0 + 3 * p1 - 3 * p2 + p3) * t ** 3)
        m = np.eye(4)
        m[:3, :3] = _quat_to_mat(_slerp(q[i], q[i + 1], t))
        m[:3, 3] = pos
        out.append(m)
    return np.stack(out)


def read_camera_path(path: Path, default: Intrinsics) -> list[dict[str, Any]]:
    """JSON cameras: {"intrinsics": {...}?, "frames": [{"transform_matrix": 4x4 OpenGL, "states": {...}?}]},
    or nerfstudio's camera_path.json ({"camera_path": [{"camera_to_world": 16 numbers, "fov": deg}]})."""
    meta = json.loads(Path(path).read_text())
    intr = Intrinsics.from_json(meta["intrinsics"]) if "intrinsics" in meta else default
    cams = []
    if "camera_path" in meta:
        w = int(meta.get("render_width", intr.w))
        h = int(meta.get("render_height", intr.h))
        for c in meta["camera_path"]:
            m = np.asarray(c["camera_to_world"], dtype=np.float64).reshape(4, 4)
            f = 0.5 * h / np.tan(np.radians(float(c.get("fov", 50))) / 2)
            cams.append({"c2w": m, "intrinsics": Intrinsics(w=w, h=h, fl_x=f, fl_y=f, cx=w / 2, cy=h / 2,
                                                           camera_model="PINHOLE"), "states": None})
        return cams
    for c in meta.get("frames", []):
        m = np.asarray(c["transform_matrix"], dtype=np.float64)
        ci = Intrinsics.from_json(c["intrinsics"]) if "intrinsics" in c else intr
        cams.append({"c2w": m, "intrinsics": ci, "states": c.get("states")})
    if not cams:
        raise LiveSceneError(f"{path}: no cameras (expected 'frames' or 'camera_path')")
    return cams


def parse_states(items: Sequence[str]) -> dict[str, float]:
    out = {}
    for it in items or []:
        if "=" not in it:
            raise LiveSceneError(f'--state expects "name=value", got {it!r}')
        name, v = it.rsplit("=", 1)
        out[name.strip()] = float(v)
    return out


def parse_sweep(text: str) -> tuple[str, np.ndarray]:
    try:
        name, spec = text.rsplit("=", 1)
        a, b, n = spec.split(":")
        return name.strip(), np.linspace(float(a), float(b), int(n))
    except ValueError as exc:
        raise LiveSceneError(f'--sweep expects "name=start:stop:count", e.g. "door=0:1:30", got {text!r}') from exc


def colorize_probs(probs: np.ndarray) -> np.ndarray:
    """(H, W, M+1) -> RGB uint8: one colour per object, black background, brightness = probability."""
    import matplotlib

    m = probs.shape[-1] - 1
    cols = np.array([matplotlib.colormaps["tab10"](i % 10)[:3] for i in range(m)] + [(0, 0, 0)])
    return (np.clip(probs @ cols, 0, 1) * 255).astype(np.uint8)


def colorize_depth(depth: np.ndarray) -> np.ndarray:
    import matplotlib

    lo, hi = np.percentile(depth, 1), np.percentile(depth, 99)
    d = np.clip((depth - lo) / max(hi - lo, 1e-6), 0, 1)
    return (matplotlib.colormaps["turbo"](1 - d)[..., :3] * 255).astype(np.uint8)


# ----------------------------------------------------------------------------------------------------------------
# CLI
# ----------------------------------------------------------------------------------------------------------------
def add_arguments(p) -> None:
    p.add_argument("run", type=Path, help="run folder of `livescene train`")
    p.add_argument("--out", type=Path, default=None, help="folder for PNGs (default RUN/renders)")
    p.add_argument("--cameras", default="dataset",
                   help="dataset (the dataset's cameras), held-out, path (a smooth path along them) or a JSON file")
    p.add_argument("--frames", default="", help="dataset frame positions to render, e.g. 0,8,16 (default: all / 8)")
    p.add_argument("--count", type=int, default=30, help="cameras on a smooth path")
    p.add_argument("--state", action="append", default=[], metavar='"NAME=VALUE"', help="fix an object's state (repeatable)")
    p.add_argument("--command", default=None, metavar='"open the fridge"',
                   help='a spoken command: open / close / half open an object found by text (needs the language extra)')
    p.add_argument("--sweep", default=None, metavar='"NAME=A:B:N"', help="sweep one object's state (first camera)")
    p.add_argument("--time", type=float, default=None, help="learned states of this normalised frame time for free objects")
    p.add_argument("--scale", type=float, default=1.0, help="resolution scale of the rendered images")
    p.add_argument("--video", type=Path, default=None, help="also write an H.264 MP4 of the RGB frames")
    p.add_argument("--fps", type=int, default=15)
    p.add_argument("--depth", action="store_true", help="also write depth maps (colour PNG + 16-bit mm PNG)")
    p.add_argument("--probs", action="store_true", help="also write object-probability maps")
    p.add_argument("--device", default="auto")
    p.epilog = ('examples:\n'
                '  livescene render out/run --cameras held-out --depth --probs\n'
                '  livescene render out/run --sweep "fridge door=0:1:30" --video out/door.mp4\n'
                '  livescene render out/run --command "open the fridge" --cameras held-out\n'
                '  livescene render out/run --cameras path --count 60 --state "fridge door=0.3" --video out/path.mp4\n'
                '  livescene render out/run --cameras cams.json   # {"frames": [{"transform_matrix": ..., "states": {...}}]}\n'
                '\na part set to a state that no training view near a camera showed is named in a warning:\n'
                'it is drawn from a side the capture never saw it at, and may come out blurred or missing')


def main(args) -> int:
    from tqdm import tqdm

    from .trainer import load_run

    from .device import configure_threads

    configure_threads(0)
    run = load_run(args.run, device=args.device)
    views = run.views
    base_states = parse_states(args.state)
    if args.command:  # livescene.language: "open the fridge" -> {"fridge door": 1.0}
        from .language import apply_command
        base_states.update(apply_command(run, args.command))
    jobs: list[dict[str, Any]] = []
    if args.cameras in ("dataset", "held-out"):
        pos = [int(x) for x in args.frames.split(",") if x.strip()] if args.frames else (
            views.held_out if args.cameras == "held-out" else list(range(0, len(views.times), 8)))
        for i in pos:
            jobs.append({"c2w": views.c2w_gl[i], "intrinsics": views.intrinsics[i], "states": None,
                         "time": float(views.times[i]), "name": views.dataset.frames[i].fid})
    elif args.cameras == "path":
        for j, m in enumerate(smooth_path(views.c2w_gl, args.count)):
            jobs.append({"c2w": m, "intrinsics": views.intrinsics[0], "states": None,
                         "time": j / max(args.count - 1, 1), "name": f"path_{j:04d}"})
    else:
        for j, c in enumerate(read_camera_path(Path(args.cameras), views.intrinsics[0])):
            jobs.append({**c, "time": 0.0, "name": f"cam_{j:04d}"})
    if not jobs:
        raise LiveSceneError("no cameras to render (check --cameras / --frames)")
    if args.sweep:
        name, values = parse_sweep(args.sweep)
        first = jobs[0]
        jobs = [{**first, "states": {name: float(v)}, "name": f"{first['name']}_{name.replace(' ', '_')}_{j:03d}"}
                for j, v in enumerate(values)]
    for msg in warn_unseen(run, jobs, base_states):
        print(f"livescene render: warning: {msg}", file=sys.stderr)
    out_dir = args.out or (args.run / "renders")
    frames = []
    for job in tqdm(jobs, desc="render"):
        intr = job["intrinsics"]
        if args.scale != 1.0:
            intr = intr.scaled(max(1, round(intr.w * args.scale)), max(1, round(intr.h * args.scale)))
        states = {**(job.get("states") or {}), **base_states}
        t = args.time if args.time is not None else job["time"]
        out = render_view(run, job["c2w"], intr, states or None, time=t)
        rgb8 = (out["rgb"] * 255).round().astype(np.uint8)
        atomic.write_image(out_dir / f"{job['name']}.png", rgb8)
        if args.depth:
            atomic.write_image(out_dir / f"{job['name']}_depth.png", colorize_depth(out["depth"]))
            atomic.write_image(out_dir / f"{job['name']}_depth_mm.png",
                               np.clip(out["depth"] * 1000, 0, 65535).astype(np.uint16))
        if args.probs:
            atomic.write_image(out_dir / f"{job['name']}_probs.png", colorize_probs(out["probs"]))
        frames.append(rgb8)
    if args.video:
        write_video(args.video, frames, fps=args.fps)
    print(f"livescene render: {len(frames)} views -> {out_dir}" + (f", {args.video}" if args.video else ""))
    return 0
