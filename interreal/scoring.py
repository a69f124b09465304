"""Score a dataset against the truth of a simulated capture (`interreal synth`): masks, poses.

The demo, the stress suite and the benchmarks all measure stages this way, so the figures agree.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .conventions import mask_file
from .dataset import load_dataset, read_articulation
from .posefit import compare_poses, rotation_gauge, umeyama  # noqa: F401 - scored here, named here too
from .synth.capture import Capture
from .synth.truth import truth_articulation


def mask_ious(ds: Path, capture: Path) -> dict[str, float]:
    """Mean IoU per object of the dataset's masks against the simulator's instance truth, on non-keyframes."""
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
    d = load_dataset(ds)
    cap = Capture.open(capture)
    est = np.stack([f.c2w for f in d.frames])
    return compare_poses(est, cap.poses[[f.index for f in d.frames]])


def motion_errors(ds: Path, cap: Path) -> dict[str, dict]:
    """Per object: the estimated motion (articulation.json) against the simulator's: kind, axis angle (deg), the
    true hinge origin's distance from the estimated axis and the range error (share of the true range)."""
    est = read_articulation(ds)
    out: dict[str, dict] = {}
    for name, t in truth_articulation(cap, ds).items():
        e = est.get(name)
        if e is None:
            out[name] = {"measured": False}
            continue
        rec = {"kind": e.kind, "true_kind": t.kind,
               "axis_deg": round(float(np.degrees(np.arccos(np.clip(abs(e.axis @ t.axis), 0, 1)))), 2),
               "range_error": round(abs(e.range - t.range) / t.range, 4)}
        if t.kind == "hinge" and e.kind == "hinge":
            d = t.origin - e.origin
            rec["origin_error"] = round(float(np.linalg.norm(d - (d @ e.axis) * e.axis)), 4)
        out[name] = rec
    return out
