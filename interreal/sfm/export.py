"""Export of the kept model: transforms.json (OpenGL camera-to-world, oriented) and the point cloud `sparse_pc.ply`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .. import atomic
from ..conventions import opencv_to_opengl
from ..dataset import Frame, write_transforms
from ..errors import StageError
from ..layout import IMAGES_DIR, PLY_FILE
from .config import SfMConfig
from .geometry import apply_similarity, camera_intrinsics, orientation_transform, rec_poses


def write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Binary little-endian PLY (x, y, z float, red, green, blue uchar), as nerfstudio reads sparse_pc.ply."""
    n = len(xyz)
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n").encode()
    rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    if n:
        rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        rec["r"], rec["g"], rec["b"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    atomic.write_bytes(path, header + rec.tobytes())


def export(ds: Path, rec, cfg: SfMConfig, extra: dict | None = None) -> dict[str, Any]:
    """transforms.json (OpenGL c2w, oriented) and sparse_pc.ply; returns what was applied."""
    names, c2w_cv, ids = rec_poses(rec)
    if not names:
        raise StageError("the reconstruction has no registered images")
    cams = {rec.images[i].camera_id for i in ids}
    if len(cams) != 1:
        raise StageError(f"expected one shared camera, the model has {len(cams)}")
    intr = camera_intrinsics(rec.cameras[cams.pop()])
    T = orientation_transform(c2w_cv, cfg.orientation, cfg.center_scale)
    c2w_gl = opencv_to_opengl(apply_similarity(T, c2w_cv))
    frames = [Frame(file_path=f"{IMAGES_DIR}/{n}", c2w=m, extra={"colmap_im_id": int(i)})
              for n, m, i in zip(names, c2w_gl, ids)]
    pts = [(p.xyz, p.color) for p in rec.points3D.values()]
    xyz = np.asarray([p[0] for p in pts], dtype=np.float64).reshape(-1, 3)
    rgb = np.asarray([p[1] for p in pts], dtype=np.uint8).reshape(-1, 3)
    xyz_t = (T[:3, :3] @ xyz.T).T + T[:3, 3] if len(xyz) else xyz
    write_ply(ds / PLY_FILE, xyz_t, rgb)
    meta = {"applied_transform": T[:3, :].tolist(), "ply_file_path": PLY_FILE,
            "orientation_method": cfg.orientation, **(extra or {})}
    write_transforms(ds, intr, frames, extra=meta)  # written last, atomically
    return {"applied_transform_4x4": T.tolist(), "intrinsics": intr.to_json(), "frames": len(frames)}
