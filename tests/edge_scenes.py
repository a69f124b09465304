"""The tall plain door (and the drawer front) the motion-route tests film: cameras on an arc, exact masks, sparse
labels, and painted frames for the routes that read colour. Shared by `test_motion_edge*.py`, `test_motion_colour.py`
and `test_motion_prism.py`."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from conftest import arc_camera, moved_front, silhouette, views_dataset

from interreal.conventions import fid_of_index
from interreal.dataset import known_states
from interreal.transients import write_transient

W, H = 480, 360
K = np.array([[420.0, 0, W / 2], [0, 420.0, H / 2], [0, 0, 1]])
# a door 0.5 wide and 2.0 tall seen from 1.3 away: its top and bottom are always outside the image
TALL = np.array([[-0.25, 0.0, 1.0], [0.25, 0.0, 1.0], [0.25, 0.0, -1.0], [-0.25, 0.0, -1.0]])  # z up, facing -y
N = 50
KEYS = [0, 27, 49]


def truth_states(n: int, start: int = 12) -> np.ndarray:
    """Rests closed, opens from frame `start` over 10 frames, rests open, half closes, rests."""
    s = np.zeros(n)
    s[start:start + 10] = np.linspace(0, 1, 10)
    s[start + 10:start + 20] = 1.0
    s[start + 20:start + 30] = np.linspace(1, 0.4, 10)
    s[start + 30:] = 0.4
    return s


def capture(kind: str, n: int = N, moves: bool = True, root: Path = Path("no-such-dataset"), arm: bool = False,
            thick: float = 0.0, arc_from: float = -25.0):
    """A duck-typed dataset: cameras on a 50 deg arc 1.3 units away looking at the part's middle, and its masks:
    the tall door turned up to 80 deg about its left edge, or a drawer front (the prism it sweeps, 0.2 units).
    `arm`: while the part moves, an arm reaches up from the image's bottom to its far edge, cut from its masks and
    written to the transient layer under `root`, as the masks stage does. `thick`: the door a slab this thick behind
    its front (hinged on the front's edge, as a fridge door is); `arc_from`: where the 50 deg arc starts (deg)."""
    part = np.concatenate([TALL, TALL + [0.0, thick, 0.0]]) if thick else TALL
    states = truth_states(n) if moves else np.zeros(n)
    c2ws, masks = [], []
    for i, s in enumerate(states):
        c2ws.append(arc_camera(arc_from + 50 * i / (n - 1), 1.3, 0.15))
        m, uv = silhouette(moved_front(part, kind, s, 0.2, 80.0), c2ws[-1], K, (W, H))
        if arm and 8 <= i < 46:
            grip = 0.5 * (uv[1] + uv[2])  # the middle of the far edge
            band = np.zeros((H, W), np.uint8)
            cv2.fillConvexPoly(band, np.round([[grip[0] - 30, grip[1]], [grip[0] + 30, grip[1]], [grip[0] + 60, H],
                                               [grip[0] - 10, H]]).astype(np.int32), 1)
            m[band > 0] = 0
            write_transient(root, fid_of_index(i), band > 0)
        masks.append(m)
    ds = views_dataset(c2ws, masks, K, root=root)
    masks = [m[..., None] > 0 for m in masks]
    labelled = np.zeros(n, bool)
    labelled[[0, 6, 11, 22, 27, 31, 42, 49]] = True
    st, kn = known_states(np.arange(n, dtype=float), np.where(labelled, states, 0)[:, None], labelled[:, None])
    return ds, states, st[:, 0], kn[:, 0], labelled, masks


def off_deg(axis: np.ndarray, truth: list[float]) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(axis @ truth)))))


def painted(masks: list[np.ndarray], seed: int = 0) -> list[np.ndarray]:
    """RGB frames of the capture: a plain blue door (its masks) on a beige wall shaded left to right, both noisy."""
    rng = np.random.default_rng(seed)
    shade = np.broadcast_to(np.linspace(150, 210, W), (H, W))
    wall = np.dstack([shade, np.full((H, W), 180.0), np.full((H, W), 150.0)])
    out = []
    for m in masks:
        img = np.where(m.reshape(H, W, 1) > 0, [40.0, 90.0, 200.0], wall) + rng.normal(0, 6, (H, W, 3))
        out.append(np.clip(img, 0, 255).astype(np.uint8))
    return out
