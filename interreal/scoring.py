"""Score a dataset against the truth of a simulated capture (`interreal synth`): masks, poses.

The demo, the stress suite and the benchmarks all measure stages this way, so the figures agree.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def mask_ious(ds: Path, capture: Path) -> dict[str, float]:
    """Mean IoU per object of the dataset's masks against the simulator's instance truth, on non-keyframes."""
    import cv2

    from .conventions import mask_file
    from .dataset import load_dataset
    from .synth import Capture

    d = load_dataset(ds)
    cap = Capture.open(capture)
    keyframes = {int(p.stem) for p in (capture / "annotations" / "keyframes").glob("*.png") if p.stem.isdigit()}
    ious: dict[str, list[float]] = {n: [] for n in d.object_names}
    for f in d.frames:
        if f.index in keyframes:
            continue
        m = np.load(mask_file(ds, f.fid))
        gt = cv2.resize(cap.instance(f.index), (m.shape[1], m.shape[0]), interpolation=cv2.INTER_NEAREST)
        for k, name in enumerate(d.object_names):
            t = gt == cap.names.index(name) + 1
            p = m[..., k]
            union = (t | p).sum()
            if union:
                ious[name].append(float((t & p).sum() / union))
    return {n: float(np.mean(v)) for n, v in ious.items() if v}


def pose_errors(ds: Path, capture: Path) -> dict[str, float]:
    """Pose error of the dataset's cameras against the simulator's truth (similarity-aligned)."""
    from .dataset import load_dataset
    from .synth import Capture

    d = load_dataset(ds)
    cap = Capture.open(capture)
    est = np.stack([f.c2w for f in d.frames])
    return compare_poses(est, cap.poses[[f.index for f in d.frames]])


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising ||dst - (s R src + t)||^2 over point pairs (N, 3)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    var = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var) if var > 0 else 1.0
    return s, R, mu_d - s * R @ mu_s


def compare_poses(est_c2w: np.ndarray, ref_c2w: np.ndarray) -> dict[str, float]:
    """Rotation error (deg) and centre error (% of the reference path's bounding-box diagonal) after a similarity
    alignment of camera centres. Both inputs: (N, 4, 4) camera-to-world with the same camera axes, same order."""
    s, R, t = umeyama(est_c2w[:, :3, 3], ref_c2w[:, :3, 3])
    c = (s * (R @ est_c2w[:, :3, 3].T)).T + t
    extent = float(np.linalg.norm(ref_c2w[:, :3, 3].max(0) - ref_c2w[:, :3, 3].min(0)))
    cerr = np.linalg.norm(c - ref_c2w[:, :3, 3], axis=1) / max(extent, 1e-12) * 100
    Ra = R @ est_c2w[:, :3, :3]
    cosang = (np.einsum("nij,nij->n", Ra, ref_c2w[:, :3, :3]) - 1) / 2
    rerr = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
    return {"rot_err_deg_median": float(np.median(rerr)), "rot_err_deg_max": float(rerr.max()),
            "center_err_pct_median": float(np.median(cerr)), "center_err_pct_max": float(cerr.max()),
            "scale": s}
