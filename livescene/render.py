"""`render_view`: any camera at any object states -> RGB, depth, object probabilities (`livescene render` is
`commands/render.py`); cameras along a path or from a JSON file, state parsing, colour maps.

States: a mapping {name: value} (missing objects take the learned value at `time`), a sequence of values in
mapping.yaml order, or None (all learned values at `time`, i.e. what the scene looked like at that frame).
"""

from __future__ import annotations

import json
import time as _time
from pathlib import Path
from typing import Any, Mapping, Sequence

import matplotlib
import numpy as np
import torch
from scipy.spatial.transform import Rotation

from interreal.dataset import Intrinsics
from interreal.video import write_video  # noqa: F401 - part of this module's API

from .data import camera_rays, check_intrinsics, check_pose, nearest_views, pixel_directions
from .errors import LiveSceneError
from .adaptive import STRIDE, TOLERANCE, render_image
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


class RenderMeter:
    """Frames, rays and seconds of the renders it is given (`add`): the speed `eval` and `render` report."""

    def __init__(self) -> None:
        self.frames, self.rays, self.seconds, self.fast = 0, 0, 0.0, set()

    def add(self, out: dict[str, Any]) -> dict[str, Any]:
        """Count one `render_view` result; returns it."""
        self.frames += 1
        self.rays += int(out["rays"])
        self.seconds += float(out["seconds"])
        self.fast.add(bool(out["fast"]))
        return out

    def report(self) -> dict[str, Any]:
        kind = {frozenset([True]): "fast", frozenset([False]): "exact"}.get(frozenset(self.fast), "mixed")
        return {"renderer": kind, "frames": self.frames, "rays": self.rays, "render_s": round(self.seconds, 3),
                "seconds_per_frame": round(self.seconds / self.frames, 4) if self.frames else None,
                "rays_per_s": round(self.rays / self.seconds) if self.seconds > 0 else None}


EXACT_CHUNK = 8192  # rays per batch of the exact renderer
FAST_CHUNK = {"cpu": 8192, "cuda": 1 << 16}  # ... of the fast one (on 2 cores 32768 was 1.3x slower than 8192)


@torch.no_grad()
def render_view(run, c2w_gl: np.ndarray, intrinsics: Intrinsics, states: StateSpec = None, *, time: float = 0.0,
                chunk: int | None = None, fast: bool = True, occupancy: Any = None,
                threshold: float | None = None, terminate: float | None = None,
                tolerance: float | None = None, stride: int | None = None) -> dict[str, Any]:
    """Render one camera (4x4 camera-to-world, OpenGL axes as in transforms.json) at the given states.

    Returns rgb (H, W, 3) float32 in [0, 1], depth (H, W) z-depth in world units, acc (H, W),
    probs (H, W, M + 1): softmax of the rendered object logits, background last, `states` (M,), and `seconds`
    (wall time of this render), `rays`, `fast`, `march` (what the fast renderer read: `march.MarchStats`),
    `traced` (pixels traced, the others interpolated) and `rays_reused` (from the last image of this camera).

    fast: the fast renderer (`livescene.adaptive` over `livescene.march`: a coarse lattice of pixels traced and
    flat regions and gradients interpolated, empty-space skipping with the run's occupancy grid, early ray
    termination, state-dependent work done once per call, pixels whose rays meet no moved part's hull reused
    across states); False = the exact renderer, every sample of every level of every pixel read, for comparison.
    occupancy: None = the run's grid (`occupancy.grid_for`: the checkpoint's, else cached next to it or built on
    first use; none for a model being trained), False = no grid, or an `OccupancyGrid`. threshold: the grid's
    density threshold (default its `threshold()`). terminate: transmittance at which a ray stops (default
    `march.TERMINATE_T`). tolerance: how far a pixel's traced neighbours may disagree for it to be interpolated
    (default `adaptive.TOLERANCE`; 0 traces every pixel); stride: pixels between the coarsest traced ones
    (default `adaptive.STRIDE`).
    Thread-safe for concurrent calls on one run only if they do not build its grid at the same time."""
    t_start = _time.perf_counter()
    model = run.model
    was_training = model.training
    model.eval()
    vals = resolve_states(run, states, time)
    m = model.n_objects
    values = model.pad_values(torch.as_tensor(vals, device=run.device)[None])
    h, w = intrinsics.h, intrinsics.w
    chunk = chunk or (FAST_CHUNK.get(run.device.type, EXACT_CHUNK) if fast else EXACT_CHUNK)
    try:
        if fast:
            res = render_image(run, c2w_gl, intrinsics, values, chunk=chunk, occupancy=occupancy,
                               threshold=threshold, terminate=terminate, stride=stride or STRIDE,
                               tolerance=TOLERANCE if tolerance is None else tolerance)
        else:
            res = _render_exact(run, c2w_gl, intrinsics, values, chunk)
    finally:
        if was_training:
            model.train()
    z_scale = res["z_scale"]
    return {"rgb": res["rgb"].view(h, w, 3).numpy(),
            "depth": (res["depth"].numpy() * z_scale).reshape(h, w).astype(np.float32),
            "acc": res["acc"].view(h, w).numpy(),
            "probs": res["probs"].view(h, w, m + 1).numpy(),
            "states": vals, "seconds": _time.perf_counter() - t_start, "rays": h * w, "fast": bool(fast),
            "march": res["march"].as_dict() if fast else None,
            "traced": res.get("traced", h * w), "rays_reused": res.get("rays_reused", 0)}


def sweep_camera(run, name: str, candidates: list[int], scale: float = 0.25,
                 tol: float = 0.1) -> tuple[int, float]:
    """The view, of `candidates` (frame positions), from which object `name`'s state sweep (the other objects
    closed) shows most: the most of the object's rendered pixels (at state 0 or 1) changing colour by more than `tol`
    between the two, rendered at `scale`. A door seen edge-on, or hidden behind another part, barely changes; seen
    from the front, most of it does. Returns (position, the share of its pixels that change there)."""
    v = run.views
    k = list(v.names).index(name)
    best = (candidates[0], -1, 0.0)
    for i in candidates:
        intr = v.intrinsics[i]
        small = intr.scaled(max(8, round(intr.w * scale)), max(8, round(intr.h * scale)))
        shots = [render_view(run, v.c2w_gl[i], small, sweep_states(v.names, name, s), time=float(v.times[i]))
                 for s in (0.0, 1.0)]
        part = (shots[0]["probs"][..., k] > 0.5) | (shots[1]["probs"][..., k] > 0.5)
        changed = (np.abs(shots[0]["rgb"] - shots[1]["rgb"]).mean(-1) > tol) & part
        if int(changed.sum()) > best[1]:
            best = (i, int(changed.sum()), float(changed.sum() / max(part.sum(), 1)))
    return best[0], best[2]


def sweep_states(names: Sequence[str], name: str, value: float) -> dict[str, float]:
    """States for one frame of `name`'s sweep: it at `value`, every other object closed (none in the way)."""
    return {n: (float(value) if n == name else 0.0) for n in names}


def _render_exact(run, c2w_gl: np.ndarray, intrinsics: Intrinsics, values: torch.Tensor, chunk: int
                  ) -> dict[str, torch.Tensor]:
    """`sampler.render_rays` over every pixel: rgb (H*W, 3), depth along the ray, acc, probs (H*W, M + 1), and the
    rays' depth scale (`camera_rays`)."""
    origins, dirs, z_scale = camera_rays(c2w_gl, intrinsics, pixel_directions(intrinsics))
    o_all = torch.from_numpy(np.ascontiguousarray(origins)).to(run.device)
    d_all = torch.from_numpy(dirs).to(run.device)
    m = run.model.n_objects
    rgb, depth, acc, probs = [], [], [], []
    for s in range(0, o_all.shape[0], chunk):
        o, d = o_all[s: s + chunk], d_all[s: s + chunk]
        out = render_rays(run.model, o, d, values.expand(o.shape[0], -1), run.box, run.config.sampler, gen=None,
                          with_logits=True)
        rgb.append(out.rgb.clamp(0, 1).cpu())
        depth.append(out.depth.cpu())
        acc.append(out.acc.cpu())
        probs.append(torch.softmax(torch.cat([out.logits[:, :m], out.logits[:, -1:]], -1), -1).cpu())
    cat = (lambda parts, *shape: torch.cat(parts) if parts else torch.zeros(0, *shape))
    return {"rgb": cat(rgb, 3), "depth": cat(depth), "acc": cat(acc), "probs": cat(probs, m + 1), "z_scale": z_scale}


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
    return Rotation.from_matrix(r).as_quat()


def _quat_to_mat(q: np.ndarray) -> np.ndarray:
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
    or nerfstudio's camera_path.json ({"camera_path": [{"camera_to_world": 16 numbers, "fov": deg}]}).
    Every camera is checked (shape, finite, a rotation; states finite in [0, 1]): LiveSceneError names the entry."""
    try:
        meta = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise LiveSceneError(f"--cameras {path}: not a readable JSON file ({exc})") from exc
    try:
        return _camera_entries(Path(path), meta, default)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise LiveSceneError(f"--cameras {path}: malformed ({type(exc).__name__}: {exc}); expected {{\"frames\": "
                             f"[{{\"transform_matrix\": 4x4, \"states\": {{...}}?}}]}} or nerfstudio's camera_path") from exc


def _camera_entries(path: Path, meta: Any, default: Intrinsics) -> list[dict[str, Any]]:
    if not isinstance(meta, dict):
        raise LiveSceneError(f"--cameras {path}: expected a JSON object with 'frames' or 'camera_path'")
    intr = check_intrinsics(Intrinsics.from_json(meta["intrinsics"]), f"{path} intrinsics") \
        if "intrinsics" in meta else default
    cams = []
    if "camera_path" in meta:
        w = int(meta.get("render_width", intr.w))
        h = int(meta.get("render_height", intr.h))
        for i, c in enumerate(meta["camera_path"]):
            where = f"{path} camera_path[{i}]"
            m = check_pose(c["camera_to_world"], where)
            fov = float(c.get("fov", 50))
            if not 0 < fov < 180:
                raise LiveSceneError(f"{where}: fov {fov} is not an angle in (0, 180) degrees")
            f = 0.5 * h / np.tan(np.radians(fov) / 2)
            cams.append({"c2w": m, "intrinsics": check_intrinsics(
                Intrinsics(w=w, h=h, fl_x=f, fl_y=f, cx=w / 2, cy=h / 2, camera_model="PINHOLE"), where),
                "states": None})
        if not cams:
            raise LiveSceneError(f"{path}: 'camera_path' lists no cameras")
        return cams
    for i, c in enumerate(meta.get("frames", [])):
        where = f"{path} frames[{i}]"
        m = check_pose(c["transform_matrix"], where)
        ci = check_intrinsics(Intrinsics.from_json(c["intrinsics"]), where) if "intrinsics" in c else intr
        states = c.get("states")
        if states is not None:
            if not isinstance(states, dict):
                raise LiveSceneError(f"{where}: 'states' must be {{object name: value}}, got {states!r}")
            states = {str(n): check_state(str(n), v, f"{where} states") for n, v in states.items()}
        cams.append({"c2w": m, "intrinsics": ci, "states": states})
    if not cams:
        raise LiveSceneError(f"{path}: no cameras (expected 'frames' or 'camera_path')")
    return cams


def check_state(name: str, value: Any, where: str) -> float:
    """A state value a user asked for: a finite number in [0, 1] (0 = closed, 1 = fully open). The model has
    seen nothing outside [0, 1], and NaN renders black: both are refused, not clipped or extrapolated."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise LiveSceneError(f"{where}: state of {name!r} is {value!r}, not a number") from None
    if not np.isfinite(v) or not 0.0 <= v <= 1.0:
        raise LiveSceneError(f"{where}: state {value!r} of {name!r} is outside [0, 1] (0 = closed, 1 = fully open); "
                             f"the model cannot extrapolate beyond the states it was trained on")
    return v


def parse_states(items: Sequence[str]) -> dict[str, float]:
    out = {}
    for it in items or []:
        if "=" not in it:
            raise LiveSceneError(f'--state expects "name=value", got {it!r}')
        name, v = it.rsplit("=", 1)
        out[name.strip()] = check_state(name.strip(), v, "--state")
    return out


def parse_sweep(text: str) -> tuple[str, np.ndarray]:
    try:
        name, spec = text.rsplit("=", 1)
        a, b, n = spec.split(":")
        count = int(n)
    except ValueError as exc:
        raise LiveSceneError(f'--sweep expects "name=start:stop:count", e.g. "door=0:1:30", got {text!r}') from exc
    if not 1 <= count <= 100_000:
        raise LiveSceneError(f"--sweep {text!r}: count {count} must be between 1 and 100000")
    name = name.strip()
    lo, hi = check_state(name, a, "--sweep"), check_state(name, b, "--sweep")
    return name, np.linspace(lo, hi, count)


def colorize_probs(probs: np.ndarray) -> np.ndarray:
    """(H, W, M+1) -> RGB uint8: one colour per object, black background, brightness = probability."""
    m = probs.shape[-1] - 1
    cols = np.array([matplotlib.colormaps["tab10"](i % 10)[:3] for i in range(m)] + [(0, 0, 0)])
    return (np.clip(probs @ cols, 0, 1) * 255).astype(np.uint8)


def colorize_depth(depth: np.ndarray) -> np.ndarray:
    lo, hi = np.percentile(depth, 1), np.percentile(depth, 99)
    d = np.clip((depth - lo) / max(hi - lo, 1e-6), 0, 1)
    return (matplotlib.colormaps["turbo"](1 - d)[..., :3] * 255).astype(np.uint8)


def choose_cameras(jobs: list[dict[str, Any]], args) -> list[dict[str, Any]]:
    """The cameras of the --cameras set that --frames names (positions within that set, so `--cameras held-out
    --frames 0` is the first held-out frame, never dataset frame 0); without --frames every 8th dataset frame
    (one for --sweep), or every camera of the other sets."""
    if args.frames:
        return [jobs[i] for i in frame_positions(args.frames, len(jobs), args.cameras)]
    if args.cameras == "dataset":
        return jobs[:1] if args.sweep else jobs[::8]
    return jobs


def frame_positions(text: str, n: int, cameras: str = "dataset") -> list[int]:
    """`--frames 0,8,16`: positions within the --cameras set of n cameras, each in [0, n)."""
    try:
        pos = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise LiveSceneError(f"--frames {text!r}: frame positions separated by commas, e.g. 0,8,16") from None
    bad = [i for i in pos if not 0 <= i < n]
    if bad:
        what = "the dataset" if cameras == "dataset" else f"--cameras {cameras}"
        raise LiveSceneError(f"--frames: position {bad[0]} is not a frame of {what} ({n} cameras: 0 to {n - 1})")
    return pos
