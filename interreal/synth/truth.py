"""A LiveScene dataset made from a capture's truth: what the trainer uses until the real pipeline exists,
and the reference the real pipeline (frames -> masks -> poses -> labels) is scored against.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from .. import dataset as D
from ..atomic import write_image
from ..conventions import fid_of_index, frame_index, frame_name, index_to_onehot, opengl_to_opencv
from ..errors import InputError
from ..posefit import umeyama
from ..report import StageReport, report_path
from .capture import Capture


def surface_box(cap: Capture, every: int = 10) -> list[float]:
    """World box [x0, y0, z0, x1, y1, z1] of the surfaces the capture saw (depth back-projected, 0.5-99.5
    percentiles, 5 % pad): the `aabb` a radiance field should cover."""
    intr = cap.intrinsics
    pts = []
    for i in range(0, len(cap), every):
        d = cap.depth(i)
        h, w = d.shape
        it = intr.scaled(w, h)
        ys, xs = np.mgrid[0:h:4, 0:w:4]
        z = d[ys, xs]
        ok = z > 0
        x = (xs[ok] + 0.5 - it.cx) / it.fl_x * z[ok]
        y = (ys[ok] + 0.5 - it.cy) / it.fl_y * z[ok]
        c2w = opengl_to_opencv(cap.poses[i])
        pts.append(np.stack([x, y, z[ok]], -1) @ c2w[:3, :3].T + c2w[:3, 3])
    p = np.concatenate(pts)
    lo, hi = np.percentile(p, 0.5, 0), np.percentile(p, 99.5, 0)
    pad = 0.05 * (hi - lo)
    return [float(v) for v in np.concatenate([lo - pad, hi + pad])]


def truth_articulation(capture_dir: str | Path, ds_dir: str | Path) -> dict[str, D.Articulation]:
    """The capture's true part motions in the dataset's world frame (a similarity fitted to the camera centres,
    so an SfM dataset of the capture gets them in its own units): the reference `interreal motions` is scored
    against, and an oracle for the trainer."""
    cap = Capture.open(capture_dir)
    ds = D.load_dataset(ds_dir)
    est = np.stack([f.c2w[:3, 3] for f in ds.frames])
    s, R, t = umeyama(est, cap.poses[[f.index for f in ds.frames]][:, :3, 3])  # capture = s R dataset + t
    parts = {p.name: p for p in cap.scene().parts}
    out = {}
    for name in ds.object_names:
        p = parts[name]
        out[name] = D.Articulation(p.kind, R.T @ p.axis, R.T @ (p.pivot - t) / s,
                                   p.max_motion if p.kind == "hinge" else p.max_motion / s, {"source": "truth"})
    return out


def truth_dataset(capture_dir: str | Path, ds_dir: str | Path, size: tuple[int, int] = (320, 240),
                  every: int = 1, progress: bool = False) -> Path:
    """Write a valid LiveScene dataset from `capture_dir`'s truth into `ds_dir` (replaced if it exists).

    Images are decoded from the video (what the phone recorded) and resized to `size` = (w, h); masks come from the
    gt instance maps (the occluding person is background); poses and intrinsics (scaled) from gt/cameras.json;
    labels from annotations/states.yaml. Frames: every `every`-th frame plus every annotated one.
    """
    cap = Capture.open(capture_dir)
    ds = Path(ds_dir)
    w, h = int(size[0]), int(size[1])
    if w < 8 or h < 8 or every < 1:
        raise InputError(f"truth_dataset: size must be >= 8x8 and every >= 1 (got {w}x{h}, every={every})")
    if ds.exists():
        if any(ds.iterdir()) and not report_path(ds, "synth_truth").exists():
            raise InputError(f"{ds} exists and was not made by truth_dataset: choose an empty folder")
        shutil.rmtree(ds)
    ds.mkdir(parents=True)
    labels = cap.labels()
    labelled = {frame_index(k) for k in labels}
    n = len(cap)
    keep = sorted(set(range(0, n, every)) | labelled)
    keep_set = set(keep)
    intr = cap.intrinsics.scaled(w, h)
    names = cap.names
    with StageReport(ds, "synth_truth", inputs={"capture": str(Path(capture_dir).resolve())},
                     settings={"size": [w, h], "every": every}) as rep:
        with rep.step("frames"):
            frames = []
            for i, rgb in tqdm(cap.frames(), total=n, desc="truth dataset", disable=not progress, leave=False):
                if i not in keep_set:
                    continue
                img = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA) if rgb.shape[:2] != (h, w) else rgb
                write_image(ds / "images" / f"{frame_name(i)}.png", img)
                inst = cap.instance(i)
                if inst.shape != (h, w):
                    inst = cv2.resize(inst, (w, h), interpolation=cv2.INTER_NEAREST_EXACT)
                inst = np.where(inst == 255, 0, inst)
                D.write_mask(ds, fid_of_index(i), index_to_onehot(inst, len(names)))
                frames.append(D.Frame(file_path=f"images/{frame_name(i)}.png", c2w=cap.poses[i]))
        if len(frames) != len(keep):
            raise InputError(f"{cap.video_path} has fewer decodable frames ({len(frames)} of {len(keep)} wanted): "
                             f"re-run `interreal synth`")
        D.write_transforms(ds, intr, frames, extra={"synth_capture": str(Path(capture_dir).resolve()),
                                                   "aabb": surface_box(cap)})
        D.write_mapping(ds, dict(enumerate(names)))
        D.write_labels(ds, {k: v for k, v in labels.items() if frame_index(k) in keep_set})
        D.write_prompts(ds, cap.descriptions)
        rep.figures.update(frames=len(frames), objects=len(names), labelled_frames=len(labelled & keep_set))
    return ds
