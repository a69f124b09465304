"""Is the truth self-consistent? Reproject static pixels between frames with gt depth, poses and distorted intrinsics.

Independent of the renderer's internals: it uses only OpenCV's camera model (`undistortPoints` / `projectPoints`)
and the rendered depth, so a wrong pose convention, intrinsics or distortion shows up as a colour error.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..conventions import opengl_to_opencv
from ..dataset import Intrinsics

_CRIT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 60, 1e-12)


def unproject(c2w_gl: np.ndarray, depth: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """World points (H, W, 3) of every pixel centre (u + 0.5, v + 0.5) at its z-depth."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    n = cv2.undistortPoints(np.stack([u, v], -1).reshape(-1, 1, 2), intr.K(), intr.dist(), None, None,
                            criteria=_CRIT).reshape(h, w, 2)
    d = depth.astype(np.float64)[..., None]
    cam = np.concatenate([n * d, d], axis=-1)
    c2w = opengl_to_opencv(c2w_gl)
    return cam @ c2w[:3, :3].T + c2w[:3, 3]


def project(c2w_gl: np.ndarray, points: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) array-index pixel coordinates (pixel (0, 0) centre at 0, 0) and (N,) z-depth of world points."""
    w2c = np.linalg.inv(opengl_to_opencv(c2w_gl))
    cam = points.reshape(-1, 3) @ w2c[:3, :3].T + w2c[:3, 3]
    px, _ = cv2.projectPoints(cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), intr.K(), intr.dist())
    return px.reshape(-1, 2) - 0.5, cam[:, 2]


def reprojection_error(scene, i: int, j: int, intr: Intrinsics | None = None,
                       assumed: Intrinsics | None = None) -> dict[str, float]:
    """Clean renders of frames i and j: static pixels of i warped into j.

    `assumed`: the camera model used for the warp (default: the true one); a wrong one shows as a larger error.

    Returns colour_mae (8-bit levels, mean over static pixels visible in both), depth_rel (median relative
    difference between the projected depth and j's own depth) and overlap (fraction of i's pixels compared).
    """
    intr = intr or scene.intrinsics
    poses, states = scene.camera_path(), scene.states()
    a = scene.render(poses[i], states[i], intrinsics=intr)
    b = scene.render(poses[j], states[j], intrinsics=intr)
    h, w = a.depth.shape
    model = assumed or intr
    px, z = project(poses[j], unproject(poses[i], a.depth, model), model)
    mx = px[:, 0].reshape(h, w).astype(np.float32)
    my = px[:, 1].reshape(h, w).astype(np.float32)
    z = z.reshape(h, w)
    inside = (mx > 1) & (mx < w - 2) & (my > 1) & (my < h - 2)
    zb = cv2.remap(b.depth, mx, my, cv2.INTER_NEAREST)
    inst_b = cv2.remap(b.instance, mx, my, cv2.INTER_NEAREST)
    sel = inside & (np.abs(zb - z) < 0.01 * z) & (a.instance == 0) & (inst_b == 0)
    if not sel.any():
        return {"colour_mae": float("nan"), "depth_rel": float("nan"), "overlap": 0.0}
    warped = cv2.remap(b.rgb.astype(np.float32), mx, my, cv2.INTER_LINEAR)
    zb_lin = cv2.remap(b.depth, mx, my, cv2.INTER_LINEAR)
    return {
        "colour_mae": float(np.abs(warped[sel] - a.rgb[sel].astype(np.float32)).mean()),
        "depth_rel": float(np.median(np.abs(zb_lin[sel] - z[sel]) / z[sel])),
        "overlap": float(sel.mean()),
    }


def reprojection_summary(scene, pairs: list[tuple[int, int]], intr: Intrinsics | None = None) -> dict[str, float]:
    """Mean colour error, median depth error and mean overlap over frame pairs."""
    res = [reprojection_error(scene, i, j, intr) for i, j in pairs]
    return {
        "colour_mae": float(np.nanmean([r["colour_mae"] for r in res])),
        "colour_mae_max": float(np.nanmax([r["colour_mae"] for r in res])),
        "depth_rel": float(np.nanmedian([r["depth_rel"] for r in res])),
        "overlap": float(np.mean([r["overlap"] for r in res])),
        "pairs": len(res),
    }
