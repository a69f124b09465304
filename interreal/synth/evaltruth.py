"""The simulator's truth as `livescene eval --gt CAPTURE` reads it: `CaptureTruth` has the `livescene.evaluate.Truth`
protocol (true states, depth, instances, and renders of any frame's camera at any states) for an `interreal synth`
capture, indexed by a run's dataset frames.

livescene imports no simulator: `open_truth` is registered under the entry-point group `livescene.truth`
(pyproject.toml), and `livescene.evaluate.open_truth` finds it there. Nothing here imports livescene; `views` is
duck-typed (`names`, `dataset.frames`, `intrinsics`, `c2w_gl`: `livescene.data.Views`).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..dataset import Intrinsics
from ..errors import InputError
from ..posefit import compare_poses, umeyama
from .capture import Capture
from .consistency import project, unproject


def open_truth(gt_dir: Path, views) -> "CaptureTruth":
    """The `livescene.truth` entry point: the capture in `gt_dir`, checked against the run's views."""
    return CaptureTruth(gt_dir, views)


class CaptureTruth:
    """Truth of an `interreal synth` capture, indexed by the dataset's frames (matched by source frame index)."""

    def __init__(self, gt_dir: str | Path, views):
        self.dir = Path(gt_dir)
        if not (self.dir / "gt" / "states.json").exists():
            raise InputError(f"{self.dir}/gt/states.json not found: --gt must be an `interreal synth` capture folder")
        self.cap = Capture.open(self.dir)
        check_same_capture(self.cap, views, self.dir)
        cols = []
        for n in views.names:
            if n not in self.cap.names:
                raise InputError(f"object {n!r} of the dataset is not in the capture's {self.cap.names}")
            cols.append(self.cap.names.index(n))
        self.frames = list(views.dataset.frames)
        self.names = list(views.names)
        self.states = self.cap.states[[f.index for f in self.frames]][:, cols]
        self._renders: dict = {}
        # the dataset's cameras may live in an SfM frame (centred, scaled): truth renders use the capture's own
        # camera for each frame, and depth compares in metres through a similarity fit of the camera centres
        est = np.asarray(views.c2w_gl)[:, :3, 3]
        ref = self.cap.poses[[f.index for f in self.frames]][:, :3, 3]
        self.metres_per_unit = float(umeyama(est, ref)[0]) if len(est) >= 3 else 1.0

    def render(self, i, states, intr):
        """Supersampled at the capture's resolution, then area-averaged: the way the dataset's images were made
        (one ray per pixel at a small size aliases, which alone costs about 30 dB)."""
        f = max(1, min(4, int(round(self.cap.intrinsics.w / intr.w))))
        rgb = self._scene_render(i, states, self.cap.intrinsics.scaled(intr.w * f, intr.h * f)).rgb
        return rgb if f == 1 else cv2.resize(rgb, (intr.w, intr.h), interpolation=cv2.INTER_AREA)

    def _scene_render(self, i: int, states, cap_intr: Intrinsics):
        """The simulator's render (rgb, z-depth, instance) of frame i's own camera at `states` with cap_intr."""
        values = {n: float(v) for n, v in zip(self.names, np.asarray(states).ravel())}
        return self.cap.scene().render(self.cap.poses[self.frames[i].index], values, cap_intr)

    def _clean(self, i: int, states, intr: Intrinsics, cache: bool = False):
        """The simulator's clean render (rgb, z-depth, instance) of frame i's camera at `states`, at the capture's
        own intrinsics scaled to intr's size; `cache` keeps it (part_support reads every training frame once per
        novel view)."""
        key = (i, intr.w, intr.h, tuple(np.round(np.asarray(states, float).ravel(), 6)))
        if cache and key in self._renders:
            return self._renders[key]
        out = self._scene_render(i, states, self.cap.intrinsics.scaled(intr.w, intr.h))
        if cache:
            self._renders[key] = out
        return out

    def part_support(self, i: int, states, intr: Intrinsics, train: list[int], comparable: float = 1.5) -> dict:
        """How training saw the moving parts that camera i shows at `states`.

        Each part pixel's surface point is taken into its part's own frame (so a training frame at any state
        can have seen it), carried to each training frame at that frame's states, and counted as seen where it
        lands unoccluded on the same part (2 cm + 1 % of depth). `seen`: share of the part pixels some training
        frame saw; `seen_comparable`: share seen from no more than `comparable` times this view's distance -
        a surface seen only from three times farther (or at a grazing angle: the footprint of a pixel on the
        surface, distance / cos(incidence), is compared) has a third of the detail this view asks for, and no
        model can render what it never saw. `part_share`: share of the image the parts cover."""
        parts = [next(p for p in self.cap.scene().parts if p.name == n) for n in self.names]
        states = np.asarray(states, float).ravel()
        cap_intr = self.cap.intrinsics.scaled(intr.w, intr.h)
        centre = self.cap.poses[self.frames[i].index][:3, 3]
        cam = self._clean(i, states, intr)
        world = unproject(self.cap.poses[self.frames[i].index], cam.depth, cap_intr)
        n_px = int(np.isin(cam.instance, np.arange(1, len(parts) + 1)).sum())
        if n_px == 0:
            return {"part_share": 0.0, "seen": None, "seen_comparable": None}
        normal = np.cross(np.gradient(world, axis=1), np.gradient(world, axis=0))
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True).clip(1e-12)
        seen_all, close_all = 0, 0
        for o, part in enumerate(parts):
            sel = cam.instance == o + 1
            if not sel.any():
                continue
            rot, trans = part.pose(float(states[o]))
            local = (world[sel] - trans) @ rot  # the part's rest frame
            n_local = normal[sel] @ rot
            here = _footprint(world[sel], normal[sel], centre)
            best = np.full(local.shape[0], np.inf)
            for f in train:
                ref = self._clean(f, self.states[f], intr, cache=True)
                rf, tf = part.pose(float(self.states[f][o]))
                pts = local @ rf.T + tf
                pose = self.cap.poses[self.frames[f].index]
                px, z = project(pose, pts, cap_intr)
                u, v = np.round(px[:, 0]).astype(int), np.round(px[:, 1]).astype(int)
                ok = (z > 0) & (u >= 0) & (u < intr.w) & (v >= 0) & (v < intr.h)
                idx = np.nonzero(ok)[0]
                zf = ref.depth[v[idx], u[idx]]
                hit = (np.abs(zf - z[idx]) < 0.02 + 0.01 * z[idx]) & (ref.instance[v[idx], u[idx]] == o + 1)
                idx = idx[hit]
                there = _footprint(pts[idx], n_local[idx] @ rf.T, pose[:3, 3])
                best[idx] = np.minimum(best[idx], there / here[idx])
            seen_all += int(np.isfinite(best).sum())
            close_all += int((best <= comparable).sum())
        return {"part_share": n_px / cam.depth.size, "seen": seen_all / n_px, "seen_comparable": close_all / n_px}

    def state_instance(self, i, states, intr):
        return self._clean(i, states, intr).instance

    @staticmethod
    def _fit(img: np.ndarray, intr: Intrinsics) -> np.ndarray:
        if img.shape[:2] == (intr.h, intr.w):
            return img
        return cv2.resize(img, (intr.w, intr.h), interpolation=cv2.INTER_NEAREST)

    def depth(self, i, intr):
        try:
            return self._fit(self.cap.depth(self.frames[i].index), intr)
        except Exception:  # noqa: BLE001 - no depth for this frame: no depth figure
            return None

    def instance(self, i, intr):
        try:
            return self._fit(self.cap.instance(self.frames[i].index), intr)
        except Exception:  # noqa: BLE001
            return None


MAX_CENTRE_ERR_PCT = 5.0  # SfM cameras of the capture itself agree within a fraction of this (0.1-1 %)
MAX_ROT_ERR_DEG = 5.0


def check_same_capture(cap, views, gt_dir: Path) -> None:
    """--gt must be the capture the run's dataset was made from, or every figure compares unrelated pictures:
    its frames hold the dataset's frame indices, its image has the dataset's aspect ratio, and its cameras match
    the dataset's up to a similarity (SfM's frame). LiveSceneError naming the mismatch otherwise."""
    idx = [f.index for f in views.dataset.frames]
    if max(idx) >= len(cap):
        raise InputError(f"--gt {gt_dir} has {len(cap)} frames but the run's dataset has frame index {max(idx)}: "
                             f"it is not the capture this dataset was made from")
    intr = views.intrinsics[0]
    ours, theirs = intr.w / intr.h, cap.intrinsics.w / cap.intrinsics.h
    if abs(ours / theirs - 1) > 0.02:
        raise InputError(f"--gt {gt_dir}: its images are {cap.intrinsics.w}x{cap.intrinsics.h}, the dataset's "
                             f"{intr.w}x{intr.h} (another aspect ratio): it is not the capture this dataset was made from")
    if len(idx) < 3:
        return
    est = np.asarray(views.c2w_gl, dtype=np.float64)
    ref = cap.poses[idx]
    err = compare_poses(est, ref)
    if not (err["center_err_pct_median"] <= MAX_CENTRE_ERR_PCT and err["rot_err_deg_median"] <= MAX_ROT_ERR_DEG):
        raise InputError(f"--gt {gt_dir}: its cameras do not match the run's dataset (median centre error "
                             f"{err['center_err_pct_median']:.1f} % of the path, rotation {err['rot_err_deg_median']:.1f} "
                             f"deg after the best similarity): it is not the capture this dataset was made from")


def _footprint(points: np.ndarray, normals: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Size of a pixel on the surface, up to the focal length: distance / cos(incidence) (N,)."""
    ray = points - centre
    dist = np.linalg.norm(ray, axis=-1)
    cos = np.abs((ray * normals).sum(-1)) / dist.clip(1e-12)
    return dist / cos.clip(0.05)
