"""What `livescene view` renders: a trained run, the views the page asks for, one render at a time.

The page sends a whole view per request (camera-to-world, size, vertical field of view, every object's state), so
the server keeps no camera state and any request can be replayed. Renders run one at a time on the run's model;
while one runs, a newer request makes the waiting older ones pointless, so they are dropped (`LatestWins`) and
dragging a slider stays responsive. Saved views and sweep videos go to RUN/views/.
"""

from __future__ import annotations

import math
import os
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, TypeVar

import cv2
import numpy as np
import torch
from scipy.spatial.transform import Rotation

from interreal import atomic
from interreal.dataset import Intrinsics
from interreal.video import write_video

from ..errors import LiveSceneError
from ..language import apply_command, parse_command
from ..render import colorize_depth, colorize_probs, learned_frame_states, render_view, unseen_states, warn_unseen

LAYERS = ("rgb", "objects", "depth")
MAX_SIDE = 2048  # pixels; a save at a phone's full resolution fits
MAX_SWEEP = 240  # frames
DRAG_SCALE = 0.5  # the low image shown while dragging is rendered at this scale of its size and scaled up ...
DRAG_TOLERANCE = 0.25  # ... with flat regions filled boldly (`livescene.adaptive`): on the demo's run, 1 thread,
# a loaded 2-core CPU, 3.4 frames/s while dragging a slider (2.1 at 0.1)
T = TypeVar("T")


class ViewError(LiveSceneError):
    """A request the viewer cannot render: names the field and what it accepts (HTTP 400)."""


@dataclass(frozen=True)
class View:
    """One camera at one set of object states: everything a render needs."""

    c2w: np.ndarray  # (4, 4) camera-to-world, OpenGL axes as in transforms.json
    w: int
    h: int
    fov_y: float  # degrees
    states: dict[str, float]
    layer: str = "rgb"

    def intrinsics(self) -> Intrinsics:
        f = 0.5 * self.h / math.tan(math.radians(self.fov_y) / 2)
        return Intrinsics(w=self.w, h=self.h, fl_x=f, fl_y=f, cx=self.w / 2, cy=self.h / 2, camera_model="PINHOLE")


def _number(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ViewError(f"{what} must be a finite number, got {value!r}")
    return float(value)


def parse_camera(value: Any) -> np.ndarray:
    """16 numbers (row-major 4x4 camera-to-world) -> (4, 4); a rigid transform or ViewError."""
    flat = np.asarray(value, dtype=object).reshape(-1) if isinstance(value, list) else None
    if flat is None or flat.size != 16:
        raise ViewError("camera.c2w must be 16 numbers (a row-major 4x4 camera-to-world matrix)")
    m = np.array([_number(v, "camera.c2w entries") for v in flat]).reshape(4, 4)
    r = m[:3, :3]
    if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6) or not np.allclose(r @ r.T, np.eye(3), atol=1e-3) \
            or np.linalg.det(r) < 0:
        raise ViewError("camera.c2w must be a rigid transform: an orthonormal right-handed rotation, a translation "
                        "and a last row 0 0 0 1")
    return m


def parse_states(value: Any, names: list[str]) -> dict[str, float]:
    """{name: value in [0, 1]} for objects of this run; ViewError names the unknown object or the bad value."""
    if not isinstance(value, dict):
        raise ViewError('states must be an object {"name": value}')
    out = {}
    for name, v in value.items():
        if name not in names:
            raise ViewError(f"unknown object {name!r}; this run has {names}")
        x = _number(v, f"state of {name!r}")
        if not 0.0 <= x <= 1.0:
            raise ViewError(f"state of {name!r} is {x:g}: states are in [0, 1] (0 = closed, 1 = fully open)")
        out[name] = x
    return out


def parse_view(data: Any, names: list[str], max_side: int = MAX_SIDE) -> View:
    """The page's JSON {camera: {c2w, w, h, fov_y}, states, layer?} -> View, or ViewError (HTTP 400)."""
    if not isinstance(data, dict) or not isinstance(data.get("camera"), dict):
        raise ViewError('expected {"camera": {"c2w": [16 numbers], "w": W, "h": H, "fov_y": degrees}, '
                        '"states": {name: value}}')
    cam = data["camera"]
    size = [_number(cam.get(k), f"camera.{k}") for k in ("w", "h")]
    if any(s != int(s) or not 8 <= s <= max_side for s in size):
        raise ViewError(f"camera.w and camera.h must be whole numbers in [8, {max_side}], got {size}")
    fov = _number(cam.get("fov_y"), "camera.fov_y")
    if not 1.0 <= fov <= 170.0:
        raise ViewError(f"camera.fov_y is {fov:g} degrees: expected 1 to 170")
    layer = data.get("layer", "rgb")
    if layer not in LAYERS:
        raise ViewError(f"layer must be one of {LAYERS}, got {layer!r}")
    states = parse_states(data.get("states", {}), names)
    return View(parse_camera(cam.get("c2w")), int(size[0]), int(size[1]), fov, states, layer)


class LatestWins:
    """One job at a time. `latest(fn)`: dropped (None) when a newer `latest` job arrives while it waits;
    `always(fn)` (a sweep's frames, a save) waits its turn and runs."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._busy = False
        self._latest = 0
        self.dropped = 0

    def latest(self, fn: Callable[[], T]) -> T | None:
        return self._run(fn, droppable=True)

    def always(self, fn: Callable[[], T]) -> T:
        return self._run(fn, droppable=False)  # type: ignore[return-value] - never dropped

    def _run(self, fn: Callable[[], T], droppable: bool) -> T | None:
        with self._cond:
            ticket = 0
            if droppable:
                self._latest += 1
                ticket = self._latest
                self._cond.notify_all()
            while self._busy and (not droppable or ticket == self._latest):
                self._cond.wait()
            if droppable and ticket != self._latest:
                self.dropped += 1
                return None
            self._busy = True
        try:
            return fn()
        finally:
            with self._cond:
                self._busy = False
                self._cond.notify_all()


@dataclass
class Rendered:
    """An encoded image and where its time went (milliseconds), for the page and the timing headers."""

    png: bytes
    w: int
    h: int
    render_ms: float
    encode_ms: float
    wait_ms: float
    unseen: dict[str, float]

    def timing(self) -> dict[str, float]:
        return {"render_ms": round(self.render_ms, 1), "encode_ms": round(self.encode_ms, 1),
                "wait_ms": round(self.wait_ms, 1)}


def encode_png(rgb8: np.ndarray, level: int = 1) -> bytes:
    """PNG at a low compression level: at 160x120 zlib's default level costs as much as a fast render."""
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb8[..., ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, level])
    if not ok:
        raise LiveSceneError("could not encode the rendered image as PNG")
    return buf.tobytes()


@dataclass
class Sweep:
    """A sweep video being written in the background; the page polls `status()`."""

    state: str = "idle"  # idle | running | done | failed
    done: int = 0
    total: int = 0
    path: str = ""
    message: str = ""
    warnings: list[str] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def status(self) -> dict[str, Any]:
        with self._lock:
            return {"state": self.state, "done": self.done, "total": self.total, "path": self.path,
                    "message": self.message, "warnings": list(self.warnings)}

    def begin(self, path: Path, total: int) -> bool:
        """Claim the sweep slot (False when a sweep is already running: one at a time)."""
        with self._lock:
            if self.state == "running":
                return False
            self.state, self.done, self.total, self.path, self.message, self.warnings = \
                "running", 0, total, str(path), "rendering", []
            return True

    def advance(self) -> None:
        with self._lock:
            self.done += 1

    def end(self, state: str, message: str, warnings: list[str] | None = None) -> None:
        with self._lock:
            self.state, self.message, self.warnings = state, message, list(warnings or [])


def size_for(aspect: float, side: int) -> tuple[int, int]:
    """(w, h) with the longer side `side` at the dataset's aspect ratio (4:3 -> 160x120, 320x240)."""
    if aspect >= 1:
        return side, max(8, round(side / aspect))
    return max(8, round(side * aspect)), side


class ViewerSession:
    """A loaded run and what the viewer does with it: describe, render, save, sweep, read a command."""

    def __init__(self, run: Any, low: int = 160, sharp: int = 320):
        self.run = run
        self.names: list[str] = list(run.names)
        self.views_dir = Path(run.run_dir) / "views"
        self.scheduler = LatestWins()
        self.learned = learned_frame_states(run)  # (N, M): the states of every frame, for sliders and warnings
        intr = run.views.intrinsics[0]
        self.aspect = intr.w / intr.h
        self.low, self.sharp = size_for(self.aspect, low), size_for(self.aspect, sharp)
        self.sweep = Sweep()
        self._save_lock = threading.Lock()

    # ---------------------------------------------------------------------------------------------- description
    def info(self) -> dict[str, Any]:
        """Objects, training cameras, sizes and the scene's frame for the page."""
        views = self.run.views
        cameras = []
        for i, frame in enumerate(views.dataset.frames):
            intr = views.intrinsics[i]
            cameras.append({"index": i, "name": frame.fid, "held_out": i in views.held_out,
                            "c2w": np.asarray(views.c2w_gl[i], dtype=float).reshape(-1).round(6).tolist(),
                            "fov_y": round(math.degrees(2 * math.atan(0.5 * intr.h / intr.fl_y)), 4),
                            "states": {n: round(float(v), 4) for n, v in zip(self.names, self.learned[i])}})
        up = np.asarray(views.c2w_gl)[:, :3, 1].mean(0)
        lo, hi = np.asarray(views.box_lo, float), np.asarray(views.box_hi, float)
        start = start_camera(np.asarray(views.c2w_gl), list(views.train), (lo + hi) / 2)
        return {"run": str(self.run.run_dir), "name": Path(self.run.run_dir).name, "objects": self.names,
                "cameras": cameras, "start": start, "up": (up / max(np.linalg.norm(up), 1e-9)).tolist(),
                "target": ((lo + hi) / 2).tolist(), "extent": float((hi - lo).max()),
                "sizes": {"low": self.low, "sharp": self.sharp, "save": self.save_size()},
                "layers": list(LAYERS), "views_dir": str(self.views_dir)}

    def save_size(self) -> list[int]:
        """Saved views: the dataset's working size, or the sharp size when that is larger."""
        intr = self.run.views.intrinsics[0]
        return [intr.w, intr.h] if intr.w * intr.h >= self.sharp[0] * self.sharp[1] else list(self.sharp)

    # ------------------------------------------------------------------------------------------------- rendering
    def image(self, view: View) -> np.ndarray:
        """(H, W, 3) uint8 of the view's layer (the render itself, no scheduling). The low size the page asks for
        while something moves is rendered at `DRAG_SCALE` of it and scaled up: a drag wants frames, not detail."""
        intr = view.intrinsics()
        drag = (view.w, view.h) == tuple(self.low)
        if drag:
            intr = intr.scaled(max(8, round(view.w * DRAG_SCALE)), max(8, round(view.h * DRAG_SCALE)))
        out = render_view(self.run, view.c2w, intr, view.states or None,
                          tolerance=DRAG_TOLERANCE if drag else None)
        if view.layer == "objects":
            rgb8 = colorize_probs(out["probs"])
        elif view.layer == "depth":
            rgb8 = colorize_depth(out["depth"])
        else:
            rgb8 = (out["rgb"] * 255).round().astype(np.uint8)
        if rgb8.shape[:2] != (view.h, view.w):
            rgb8 = cv2.resize(rgb8, (view.w, view.h), interpolation=cv2.INTER_LINEAR)
        return rgb8

    def render(self, view: View) -> Rendered | None:
        """The view as PNG, or None when a newer request came in while this one waited."""
        t0 = time.perf_counter()

        def job() -> Rendered:
            t1 = time.perf_counter()
            rgb8 = self.image(view)
            t2 = time.perf_counter()
            png = encode_png(rgb8)
            t3 = time.perf_counter()
            return Rendered(png, view.w, view.h, (t2 - t1) * 1e3, (t3 - t2) * 1e3, (t1 - t0) * 1e3, self.unseen(view))

        return self.scheduler.latest(job)

    def warm_up(self) -> float:
        """One small render before the page opens: what the renderer builds on first use (the fast renderer's
        occupancy grid, when the checkpoint has none) is then not paid on the first slider move. Seconds."""
        t0 = time.perf_counter()
        info = self.info()
        cam = info["cameras"][info["start"]]
        self.image(View(np.asarray(cam["c2w"]).reshape(4, 4), *self.low, cam["fov_y"], {}))
        return time.perf_counter() - t0

    def unseen(self, view: View) -> dict[str, float]:
        """Objects at a state no training view near this camera showed -> the nearest state those views show."""
        return unseen_states(self.run, self.learned, view.c2w, view.states)

    # ------------------------------------------------------------------------------------------------ save, sweep
    def save(self, view: View) -> dict[str, str]:
        """RUN/views/view_NNN.png and view_NNN.json (a camera file `livescene render --cameras` reads back)."""
        rgb8 = self.scheduler.always(lambda: self.image(view))
        with self._save_lock:
            stem = self.views_dir / f"view_{_next_number(self.views_dir, 'view'):03d}"
            atomic.write_image(stem.with_suffix(".png"), rgb8)
            atomic.write_json(stem.with_suffix(".json"), camera_file(view))
        return {"png": str(stem.with_suffix(".png")), "json": str(stem.with_suffix(".json"))}

    def start_sweep(self, view: View, name: str, count: int = 30, fps: int = 15) -> dict[str, Any]:
        """Render `name` from 0 to 1 in `count` frames at this view (the other states held) into an MP4 in the
        background: the `livescene render --sweep` frames, at the viewer's camera."""
        if name not in self.names:
            raise ViewError(f"unknown object {name!r}; this run has {self.names}")
        if not isinstance(count, int) or isinstance(count, bool) or not 2 <= count <= MAX_SWEEP:
            raise ViewError(f"sweep count must be a whole number in [2, {MAX_SWEEP}], got {count!r}")
        if not isinstance(fps, int) or isinstance(fps, bool) or not 1 <= fps <= 60:
            raise ViewError(f"fps must be a whole number in [1, 60], got {fps!r}")
        stem = f"sweep_{_safe(name)}"
        path = self.views_dir / f"{stem}_{_next_number(self.views_dir, stem):03d}.mp4"
        if not self.sweep.begin(path, count):
            return {"started": False, **self.sweep.status()}
        threading.Thread(target=self._sweep, args=(view, name, count, fps, path), name="sweep", daemon=True).start()
        return {"started": True, "state": "running", "path": str(path)}

    def _sweep(self, view: View, name: str, count: int, fps: int, path: Path) -> None:
        try:
            views = [View(view.c2w, view.w, view.h, view.fov_y, {**view.states, name: float(v)}, view.layer)
                     for v in np.linspace(0.0, 1.0, count)]
            warnings = warn_unseen(self.run, [{"c2w": v.c2w, "states": v.states} for v in views], {})
            frames = []
            for v in views:
                frames.append(self.scheduler.always(lambda v=v: self.image(v)))
                self.sweep.advance()
            write_video(path, frames, fps=fps)
            self.sweep.end("done", f"{count} frames -> {path}", warnings)
        except Exception as exc:  # noqa: BLE001 - the page shows the message; the server keeps serving
            self.sweep.end("failed", f"{type(exc).__name__}: {exc}")

    # ---------------------------------------------------------------------------------------------------- command
    def command(self, text: Any) -> dict[str, Any]:
        """"open the fridge" -> {"states": {"fridge door": 1.0}} via livescene.language (needs its extra)."""
        if not isinstance(text, str) or not text.strip() or len(text) > 300:
            raise ViewError("command must be a non-empty text of at most 300 characters, e.g. \"open the fridge\"")
        cmd = parse_command(text)  # InputError for an unreadable command, before loading the text model
        states = apply_command(self.run, text)
        return {"states": states, "verb": cmd.verb, "query": cmd.query}


def start_camera(c2ws: np.ndarray, train: list[int], centre: np.ndarray, cos_min: float = 0.95) -> int:
    """The training camera to open on: the farthest of those looking at the scene centre (within ~18 degrees),
    for an overview rather than a capture's first close-up; the first training camera when none does."""
    if not train:
        return 0
    tr = np.asarray(train)
    to_centre = centre[None] - c2ws[tr, :3, 3]
    dist = np.linalg.norm(to_centre, axis=1)
    cos = np.einsum("ij,ij->i", to_centre, -c2ws[tr, :3, 2]) / np.maximum(dist, 1e-9)
    facing = cos >= cos_min
    return int(tr[np.argmax(np.where(facing, dist, -1.0))]) if facing.any() else int(tr[0])


def camera_file(view: View) -> dict[str, Any]:
    """The view as a `livescene render --cameras FILE` camera file."""
    return {"intrinsics": view.intrinsics().to_json(),
            "frames": [{"transform_matrix": view.c2w.tolist(), "states": dict(view.states)}]}


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]+", "_", name).strip("_") or "object"


def _next_number(folder: Path, prefix: str) -> int:
    """1 + the highest NNN of folder/prefix_NNN.* (1 when there is none)."""
    pattern = re.compile(rf"^{re.escape(prefix)}_(\d+)\.")
    found = [int(m.group(1)) for p in folder.glob(f"{prefix}_*") if (m := pattern.match(p.name))] \
        if folder.is_dir() else []
    return max(found, default=0) + 1



def measure(session: ViewerSession, drags: int = 8) -> dict[str, Any]:
    """The viewer's speed on this run and machine, through the same path as the page's requests (render, PNG,
    scheduler): the first low image after a slider move, frames/s while a slider is dragged, the sharp image when
    the slider rests (the page showed this camera's sharp image before the drag, so pixels no moving part reaches
    are reused), and the sharp image when an orbit rests (nothing to reuse: `sharp_s`)."""
    info = session.info()
    cam = info["cameras"][info["start"]]
    c2w = np.asarray(cam["c2w"]).reshape(4, 4)
    name = session.names[0]

    def timed(size: tuple[int, int], value: float, pose: np.ndarray = c2w) -> float:
        t0 = time.perf_counter()
        session.render(View(pose, *size, cam["fov_y"], {name: value}))
        return time.perf_counter() - t0

    warm = timed(session.low, 0.0)  # what the renderer builds on first use
    sharp = timed(session.sharp, 0.0)  # the page's image before the slider moves, as the camera rested
    first = timed(session.low, 0.05)
    drag = [timed(session.low, v) for v in np.linspace(0.1, 1.0, drags)]
    sharp_slider = timed(session.sharp, 1.0)
    poses = [_orbit(c2w, np.asarray(info["target"]), np.asarray(info["up"]), a) for a in np.linspace(1.0, 8.0, drags)]
    orbit = [timed(session.low, 1.0, pose) for pose in poses]  # the camera dragged: nothing to reuse
    return {"device": str(session.run.device), "threads": torch.get_num_threads(), "object": name,
            "load_avg": round(os.getloadavg()[0], 2),
            "low": list(session.low), "sharp": list(session.sharp), "warm_up_s": round(warm, 3),
            "first_low_s": round(first, 3), "drag_s_per_frame": round(float(np.mean(drag)), 5),
            "drag_fps": round(len(drag) / sum(drag), 2), "orbit_fps": round(len(orbit) / sum(orbit), 2),
            "sharp_s": round(sharp, 3), "sharp_after_slider_s": round(sharp_slider, 3)}


def _orbit(c2w: np.ndarray, target: np.ndarray, up: np.ndarray, degrees: float) -> np.ndarray:
    """The camera turned about `up` through `target` by `degrees` (an orbit drag)."""
    r = Rotation.from_rotvec(np.radians(degrees) * up / max(np.linalg.norm(up), 1e-9)).as_matrix()
    out = c2w.copy()
    out[:3, :3] = r @ c2w[:3, :3]
    out[:3, 3] = target + r @ (c2w[:3, 3] - target)
    return out
