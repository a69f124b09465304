"""Shared fixtures: a tiny hand-made LiveScene dataset (no simulator needed) and helpers."""

from __future__ import annotations

import os
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from interreal.conventions import fid_of_index, opencv_to_opengl
from interreal.synth.camera import look_at

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
os.environ.setdefault("OMP_NUM_THREADS", "2")


def _has_cuda() -> bool:
    try:
        import torch

        return torch.cuda.is_available()
    except Exception:  # noqa: BLE001
        return False


def pytest_collection_modifyitems(config, items):
    if _has_cuda():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


def make_tiny_dataset(root: Path, n_frames: int = 4, size: tuple[int, int] = (32, 24), n_objects: int = 2,
                      seed: int = 0) -> Path:
    """A valid dataset: random images, a box mask per object, poses on a circle, two labels."""
    from interreal import dataset as D
    from interreal.atomic import write_image
    from interreal.conventions import frame_name, fid_of_index, index_to_onehot, opencv_to_opengl

    rng = np.random.default_rng(seed)
    w, h = size
    root.mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(n_frames):
        idx = i * 10
        write_image(root / "images" / f"{frame_name(idx)}.png", rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
        index = np.zeros((h, w), np.uint8)
        for k in range(n_objects):
            index[2 + 5 * k: 6 + 5 * k, 3 + i: 9 + i] = k + 1
        D.write_mask(root, fid_of_index(idx), index_to_onehot(index, n_objects))
        a = 2 * np.pi * i / n_frames
        # OpenCV camera on a circle looking at the origin
        c = np.array([3 * np.cos(a), 3 * np.sin(a), 0.5])
        z = -c / np.linalg.norm(c)
        x = np.cross(z, [0, 0, 1.0]); x /= np.linalg.norm(x)
        y = np.cross(z, x)
        c2w = np.eye(4); c2w[:3, :3] = np.stack([x, y, z], 1); c2w[:3, 3] = c
        frames.append(D.Frame(file_path=f"images/{frame_name(idx)}.png", c2w=opencv_to_opengl(c2w)))
    intr = D.Intrinsics(w=w, h=h, fl_x=30.0, fl_y=30.0, cx=w / 2, cy=h / 2, k1=-0.01)
    D.write_transforms(root, intr, frames)
    names = ["door", "drawer", "lid", "tap", "fan", "box"][:n_objects]
    D.write_mapping(root, dict(enumerate(names)))
    D.write_labels(root, {frame_name(0): {names[0]: 0.0}, frame_name(10 * (n_frames - 1)): {names[0]: 1.0}})
    return root


@pytest.fixture(scope="module")
def one_thread():
    """One torch thread for a module's trainings: on a shared 2-core machine, OpenMP workers waiting on each other
    cost 10x."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture
def tiny_dataset(tmp_path: Path) -> Path:
    return make_tiny_dataset(tmp_path / "ds")


class FakeClock:
    """A monotonic clock a test moves itself: each read adds `tick` seconds, `advance` adds a piece of work's cost.
    Injected where code plans from measured durations, so a busy machine cannot change what the test checks."""

    def __init__(self, tick: float = 0.0):
        self.t, self.tick = 1000.0, tick

    def __call__(self) -> float:
        self.t += self.tick
        return self.t

    def advance(self, seconds: float) -> None:
        self.t += seconds


CHROMIUM = "/usr/bin/chromium"  # Debian's: Playwright cannot download its own browser here
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--no-first-run"]


@pytest.fixture(scope="module")
def browser():
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: the browser tests need Debian's Chromium: apt-get install chromium "
                    "(bash .ci/setup installs it when run as root)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=ARGS)
        yield b
        b.close()


def arc_camera(az_deg: float, radius: float, elevation: float, aim=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Camera-to-world (4, 4), OpenCV axes: on a circle `radius` around `aim`'s axis (z up), `elevation` rad above
    it, looking at `aim` (the motion routes' arcs of views)."""
    az = np.radians(az_deg)
    centre = radius * np.array([np.sin(az) * np.cos(elevation), -np.cos(az) * np.cos(elevation), np.sin(elevation)])
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = look_at(centre, np.asarray(aim, float)), centre
    return c2w


def moved_front(front: np.ndarray, kind: str, s: float, slide: float, turn_deg: float) -> np.ndarray:
    """A flat front (4, 3), z up, facing -y, at state s: 'slide' -> the prism it sweeps pulled out `slide` units
    along -y (8, 3); a hinge -> turned `turn_deg` * s about its first edge (z)."""
    if kind == "slide":
        return np.concatenate([front, front + [0.0, -slide * s, 0.0]])
    rot = Rotation.from_rotvec([0.0, 0.0, -np.radians(turn_deg) * s]).as_matrix()
    return (front - front[0]) @ rot.T + front[0]


def silhouette(pts: np.ndarray, c2w: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(mask (H, W) uint8, the points' pixels (N, 2)): the convex hull of `pts` (N, 3) seen by a pinhole camera
    (`size` = (W, H))."""
    w2c = np.linalg.inv(c2w)
    p = (K @ (w2c[:3, :3] @ pts.T + w2c[:3, 3:])).T
    uv = p[:, :2] / p[:, 2:]
    m = np.zeros(size[::-1], np.uint8)
    cv2.fillConvexPoly(m, cv2.convexHull(np.round(uv * 16).astype(np.int32)), 1, shift=4)
    return m, uv


def views_dataset(c2ws: list[np.ndarray], masks: list[np.ndarray], K: np.ndarray, dist: np.ndarray | None = None,
                  root: Path = Path("no-such-dataset")):
    """A duck-typed dataset of one object (`masks` (H, W) bool each) under cameras `c2ws` (OpenCV axes): what the
    pose-free motion routes read (frames' c2w / index / fid, load_mask, intrinsics, root for the transient layer)."""
    frames = [SimpleNamespace(c2w=opencv_to_opengl(c), index=i, fid=fid_of_index(i)) for i, c in enumerate(c2ws)]
    stacked = [m[..., None] > 0 for m in masks]
    return SimpleNamespace(frames=frames, load_mask=lambda f: stacked[f.index], root=root,
                           intrinsics=SimpleNamespace(K=lambda: K, dist=lambda: np.zeros(5) if dist is None else dist))
