"""Shared fixtures: a tiny hand-made LiveScene dataset (no simulator needed) and helpers."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

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
