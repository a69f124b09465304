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
    from .sfm import compare_poses
    from .synth import Capture

    d = load_dataset(ds)
    cap = Capture.open(capture)
    est = np.stack([f.c2w for f in d.frames])
    return compare_poses(est, cap.poses[[f.index for f in d.frames]])
