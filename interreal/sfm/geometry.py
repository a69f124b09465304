"""Camera geometry of a reconstruction: poses out of a pycolmap model, COLMAP cameras as nerfstudio intrinsics, and
the orientation (gravity-like up -> +Z, centred, max |t| = 1) applied before export."""

from __future__ import annotations

import numpy as np

from ..dataset import Intrinsics
from ..errors import StageError


def _rot_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation taking unit vector a onto unit vector b."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(np.dot(a, b))
    if c < -1 + 1e-10:
        axis = np.cross(a, [1.0, 0, 0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


PAN = 0.17  # the x axes' second singular value over sqrt(n) under which they span one direction: a pure pan


def estimate_up(c2w_cv: np.ndarray, method: str = "vertical") -> np.ndarray:
    """World 'up' from OpenCV camera-to-world poses.

    "vertical": a handheld camera's x axis stays roughly horizontal, so up is the direction most orthogonal to all
    x axes (smallest singular vector), signed by the mean camera up (-y). Falls back to the mean up when the x axes
    span a single direction (a pure pan). "up": the mean camera up (nerfstudio's default, biased when cameras pitch).
    """
    mean_up = -c2w_cv[:, :3, 1].mean(axis=0)
    mean_up /= np.linalg.norm(mean_up)
    if method == "up":
        return mean_up
    x = c2w_cv[:, :3, 0]
    _, s, vt = np.linalg.svd(x, full_matrices=False)
    if s[1] > PAN * np.sqrt(len(x)):
        up = vt[2]
        return up if np.dot(up, mean_up) > 0 else -up
    up = mean_up - vt[0] * np.dot(mean_up, vt[0])
    return up / np.linalg.norm(up)


def level_up(c2w_cv: np.ndarray, max_roll_deg: float = 10.0) -> np.ndarray | None:
    """World up as `estimate_up`'s "vertical" finds it, or None where it is not to be trusted as gravity: the
    cameras' x axes span one direction (a pure pan: up is then their mean up, tilted by their pitch) or stray from
    one plane by more than `max_roll_deg` (rms: a camera rolled about freely, or a video turned on its side)."""
    x = c2w_cv[:, :3, 0]
    s = np.linalg.svd(x, compute_uv=False)
    n = np.sqrt(len(x))
    if len(x) < 3 or s[1] <= PAN * n or s[2] > np.sin(np.radians(max_roll_deg)) * n:
        return None
    return estimate_up(c2w_cv, "vertical")


def orientation_transform(c2w_cv: np.ndarray, method: str, center_scale: bool) -> np.ndarray:
    """4x4 similarity applied to world points: up -> +Z, cameras centred, max |t| = 1."""
    T = np.eye(4)
    if method != "none":
        T[:3, :3] = _rot_between(estimate_up(c2w_cv, method), np.array([0.0, 0.0, 1.0]))
    if center_scale:
        c = (T[:3, :3] @ c2w_cv[:, :3, 3].T).T
        mean = c.mean(axis=0)
        ext = float(np.abs(c - mean).max())
        s = 1.0 / ext if ext > 1e-9 else 1.0
        T[:3, :3] *= s
        T[:3, 3] = -s * mean
    return T


def apply_similarity(T: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """Similarity on world coordinates applied to camera-to-world poses (rotation kept orthonormal)."""
    s = np.cbrt(np.linalg.det(T[:3, :3]))
    R = T[:3, :3] / s
    out = np.array(c2w, dtype=np.float64, copy=True)
    out[..., :3, :3] = R @ c2w[..., :3, :3]
    out[..., :3, 3] = (T[:3, :3] @ c2w[..., :3, 3][..., None])[..., 0] + T[:3, 3]
    return out


def camera_intrinsics(cam) -> Intrinsics:
    """nerfstudio keys for a COLMAP camera; every perspective model is written as OPENCV (as colmap_to_json does)."""
    p = np.asarray(cam.params, dtype=np.float64)
    name = cam.model.name if hasattr(cam.model, "name") else str(cam.model_name)
    w, h = int(cam.width), int(cam.height)
    if name in ("SIMPLE_PINHOLE",):
        return Intrinsics(w, h, p[0], p[0], p[1], p[2], camera_model="OPENCV")
    if name == "PINHOLE":
        return Intrinsics(w, h, p[0], p[1], p[2], p[3], camera_model="OPENCV")
    if name == "SIMPLE_RADIAL":
        return Intrinsics(w, h, p[0], p[0], p[1], p[2], k1=p[3], camera_model="OPENCV")
    if name == "RADIAL":
        return Intrinsics(w, h, p[0], p[0], p[1], p[2], k1=p[3], k2=p[4], camera_model="OPENCV")
    if name == "OPENCV":
        return Intrinsics(w, h, p[0], p[1], p[2], p[3], k1=p[4], k2=p[5], p1=p[6], p2=p[7], camera_model="OPENCV")
    raise StageError(f"camera model {name} cannot be written to transforms.json; use RADIAL, SIMPLE_RADIAL or OPENCV")


def rec_poses(rec) -> tuple[list[str], np.ndarray, list[int]]:
    """(image names, OpenCV camera-to-world (N, 4, 4), image ids) of the registered images, in name order."""
    items = sorted(((im.name, iid) for iid, im in rec.images.items() if im.has_pose), key=lambda t: t[0])
    c2w = []
    for _, iid in items:
        w2c = np.eye(4)
        w2c[:3, :4] = rec.images[iid].cam_from_world().matrix()
        c2w.append(np.linalg.inv(w2c))
    return [n for n, _ in items], np.asarray(c2w).reshape(-1, 4, 4), [i for _, i in items]
