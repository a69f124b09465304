"""Rigid part motions inside the fields: a part's samples are read in the part's rest frame (its pose at state 0).

A k-axis alone (the paper's model) gives each state its own features, so a surface seen at one state from one
side is not the same surface at another state from another side: on the benchmark, a fridge door that every
training view near one camera showed open rendered at 12.9 dB there when asked half closed. With a rigid motion
per part (a hinge turning about an axis, a slide moving along one: `interreal.dataset.Articulation`, estimated by
`interreal motions`), every view of the part at any state trains the same rest-frame surface, and the space a
part leaves when it moves is the static scene's by construction (benchmark, 15 min: novel-state PSNR 22.2 -> 23.7
dB; that camera's black close-up door face was then drawn by a floater near the cameras, outside the door's hull,
until the near plane came from the SfM points (`SamplerConfig.near_auto`): 26.4 dB, that camera 20.1).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from scipy.ndimage import binary_dilation
from torch import nn

from interreal.conventions import opengl_to_opencv
from interreal.dataset import known_states

KIND_CODES = {"hinge": 1, "slide": 2}  # 0: the object has no rigid motion (the k-axis alone moves it)
HULL_RES = 64  # cells along each axis of a part's rest-frame hull box


def rotate(v: torch.Tensor, axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues: v (..., 3) turned by `angle` (...) about unit `axis` (..., 3), right-hand rule."""
    c, s = torch.cos(angle)[..., None], torch.sin(angle)[..., None]
    dot = (axis * v).sum(-1, keepdim=True)
    return v * c + torch.cross(axis, v, dim=-1) * s + axis * dot * (1 - c)


class PartMotions(nn.Module):
    """Per object slot: motion kind (0 = none), unit axis, a point on a hinge's axis and the motion at state 1.

    Buffers, not parameters: a run's checkpoint carries the motions it was trained with, so rendering needs no
    dataset file, and the optimiser never moves them."""

    def __init__(self, max_objects: int):
        super().__init__()
        self.register_buffer("kind", torch.zeros(max_objects, dtype=torch.long))
        self.register_buffer("axis", torch.zeros(max_objects, 3))
        self.register_buffer("origin", torch.zeros(max_objects, 3))
        self.register_buffer("range", torch.zeros(max_objects))
        # where each part can be in its rest frame (`carve_hull`); a slot without one is not gated
        self.register_buffer("hull", torch.zeros(max_objects, HULL_RES, HULL_RES, HULL_RES, dtype=torch.bool))
        self.register_buffer("hull_lo", torch.zeros(max_objects, 3))
        self.register_buffer("hull_hi", torch.ones(max_objects, 3))
        self.register_buffer("hull_set", torch.zeros(max_objects, dtype=torch.bool))

    def load(self, motions: list) -> None:
        """Fill the slots from `interreal.dataset.Articulation`s (None: that object has no rigid motion)."""
        self.kind.zero_()
        for i, m in enumerate(motions):
            if m is None:
                continue
            self.kind[i] = KIND_CODES[m.kind]
            self.axis[i] = torch.as_tensor(m.axis, dtype=torch.float32)
            self.origin[i] = torch.as_tensor(m.origin, dtype=torch.float32)
            self.range[i] = float(m.range)

    def set_hull(self, obj: int, hull: tuple[np.ndarray, np.ndarray, np.ndarray] | None) -> None:
        """Gate object `obj` to a carved hull (lo, hi, occupied), or lift its gate (None)."""
        self.hull_set[obj] = hull is not None
        if hull is not None:
            lo, hi, occ = hull
            self.hull_lo[obj] = torch.as_tensor(lo, dtype=torch.float32)
            self.hull_hi[obj] = torch.as_tensor(hi, dtype=torch.float32)
            self.hull[obj] = torch.as_tensor(occ, dtype=torch.bool)

    def padded_hull(self, obj: int) -> torch.Tensor | None:
        """Object `obj`'s hull with a border of empty cells, flattened: a point's cell is then one clamped index
        (`inside_one`), no bounds test. None when it has no hull (it may own any point)."""
        if not bool(self.hull_set[obj]):
            return None
        return F.pad(self.hull[obj].to(torch.uint8), (1, 1, 1, 1, 1, 1)).bool().reshape(-1)

    def inside_one(self, obj: int, rest: torch.Tensor, padded: torch.Tensor | None = None) -> torch.Tensor:
        """rest (N, 3): object `obj`'s rest-frame points -> (N,) bool, True where it may own the point (inside its
        hull, or everywhere when it has none). padded: its `padded_hull`, when the caller keeps it."""
        padded = self.padded_hull(obj) if padded is None else padded
        if padded is None:
            return torch.ones(rest.shape[0], dtype=torch.bool, device=rest.device)
        res = self.hull.shape[1]
        cell = ((rest.detach() - self.hull_lo[obj]) / (self.hull_hi[obj] - self.hull_lo[obj]) * res).floor_()
        c = cell.add_(1).clamp_(0, res + 1).long()  # outside the hull's box: a border cell (empty)
        return padded[(c[:, 0] * (res + 2) + c[:, 1]) * (res + 2) + c[:, 2]]

    def inside(self, objects: list[int], rest: torch.Tensor) -> torch.Tensor:
        """rest (K, N, 3): each listed object's rest-frame points -> (K, N) bool (`inside_one`)."""
        return torch.stack([self.inside_one(o, rest[j]) for j, o in enumerate(objects)])

    def rigid(self, n_objects: int) -> list[int]:
        """The object slots (< n_objects) that move rigidly."""
        return [i for i in range(n_objects) if int(self.kind[i]) > 0]

    def to_rest(self, pts: torch.Tensor, dirs: torch.Tensor, values: torch.Tensor,
                objects: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        """World samples pts, dirs (N, 3) at per-sample states values (N, max_objects) -> where they sit in each
        listed object's rest frame: points and directions (len(objects), N, 3)."""
        idx = torch.as_tensor(objects, device=pts.device, dtype=torch.long)
        kind, axis, origin = self.kind[idx], self.axis[idx], self.origin[idx]
        amount = values[:, idx] * self.range[idx]  # (N, K)
        angle = -amount * (kind == KIND_CODES["hinge"])  # turn back to state 0
        shift = (amount * (kind == KIND_CODES["slide"]))[..., None] * axis  # (N, K, 3)
        a = axis.expand(pts.shape[0], -1, -1)
        p = rotate(pts[:, None, :] - origin, a, angle) + origin - shift
        d = rotate(dirs[:, None, :].expand_as(a), a, angle)
        return p.transpose(0, 1), d.transpose(0, 1)


# ----------------------------------------------------------------------------------------------------------------
# Where a rigid part can be: its masks carved into its rest frame
# ----------------------------------------------------------------------------------------------------------------
HULL_COARSE = 32  # cells along each axis of the first pass over the scene box
HULL_MIN_VIEWS = 0.3  # a cell needs this share of the views that show the part to show the part or the
# background where it projects (cells near the cameras, in few views' frustums, are otherwise kept on little evidence)
HULL_IN = 0.9  # ... and the part in this share of them (a visual hull with room for wrong mask pixels; at 0.6 a
# point 30 cm in front of the benchmark's door was kept, most views looking through it at the door)
HULL_COARSE_GROW = 0.03  # the first pass reads the part's masks grown by this share of the image width: its
# cells are larger than a thin part, whose centres may miss the part's pixels
HULL_MIN_PIXELS = 50  # views that show fewer of the part's pixels are not used
HULL_MAX_VIEWS = 80  # views carved with (evenly spread over those whose state is known)
HULL_DILATE = 2  # cells added around the carved hull: a gate must not clip the part's own surface


def _hull_votes(cells: np.ndarray, motion, frames: list[int], states: np.ndarray, masks: np.ndarray,
                cams: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]], obj: int, background: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """Per rest-frame point (P, 3): views showing the part there, views showing the part or the background there.
    Other objects are no evidence (they may stand in front of the part)."""
    inside = np.zeros(len(cells), np.int32)
    seen = np.zeros(len(cells), np.int32)
    h, w = masks.shape[1:]
    for f in frames:
        rot, trans = motion.pose(float(states[f]))
        rvec, tvec, k, dist = cams[f]
        world = cells @ rot.T + trans
        cam = world @ cv2.Rodrigues(rvec)[0].T + tvec.ravel()
        front = cam[:, 2] > 1e-6
        px, _ = cv2.projectPoints(world[front], rvec, tvec, k, dist)
        uv = np.full((len(cells), 2), -1, np.int64)
        uv[front] = np.floor(np.nan_to_num(px.reshape(-1, 2), nan=-1.0).clip(-1, 1e6)).astype(np.int64)
        u, v = uv[:, 0], uv[:, 1]
        ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        lab = np.full(len(cells), 255, np.int64)
        lab[ok] = masks[f, v[ok], u[ok]]
        inside += lab == obj
        seen += (lab == obj) | (lab == background)
    return inside, seen


def _grown(masks: np.ndarray, frames: list[int], obj: int, share: float) -> np.ndarray:
    """The label maps with object `obj`'s pixels grown by `share` of the width (only `frames` are filled)."""
    r = max(1, int(round(share * masks.shape[2])))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    out = np.full_like(masks, 255)
    for f in frames:
        grown = cv2.dilate((masks[f] == obj).astype(np.uint8), kernel) > 0
        out[f] = np.where(grown, obj, masks[f])
    return out


def _grid(lo: np.ndarray, hi: np.ndarray, res: int) -> np.ndarray:
    axes = [lo[d] + (np.arange(res) + 0.5) * (hi[d] - lo[d]) / res for d in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def carve_hull(motion, obj: int, n_objects: int, frames: list[int], states: np.ndarray, masks: np.ndarray,
               cams: list, box: tuple[np.ndarray, np.ndarray], res: int = HULL_RES
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(lo, hi, occupied (res, res, res) bool) of object `obj`'s rest-frame hull, or None when no view shows it.

    A cell is the part's when most views that see the part or the background where the cell projects (at each
    view's own state) see the part: a visual hull that tolerates a few wrong mask pixels. Coarse over the scene
    box first, then at `res` over the box of what the coarse pass kept."""
    lo, hi = np.asarray(box[0], float), np.asarray(box[1], float)
    frames = [f for f in frames if (masks[f] == obj).sum() >= HULL_MIN_PIXELS]
    if len(frames) > HULL_MAX_VIEWS:
        frames = [frames[i] for i in np.linspace(0, len(frames) - 1, HULL_MAX_VIEWS).round().astype(int)]
    occ = None
    for level, n in enumerate((HULL_COARSE, res)):
        cells = _grid(lo, hi, n)
        labels = _grown(masks, frames, obj, HULL_COARSE_GROW) if level == 0 else masks
        inside, seen = _hull_votes(cells, motion, frames, states, labels, cams, obj, n_objects)
        occ = ((seen >= max(3, HULL_MIN_VIEWS * len(frames))) & (inside >= HULL_IN * seen)).reshape(n, n, n)
        if not occ.any():
            return None
        occ = binary_dilation(occ, iterations=1 if level == 0 else HULL_DILATE)
        if level == 0:  # the fine pass covers what the coarse one kept
            idx = np.argwhere(occ)
            cell = (hi - lo) / n
            lo, hi = lo + idx.min(0) * cell, lo + (idx.max(0) + 1) * cell
    return lo, hi, occ


def fit_hulls(motions: PartMotions, articulation: list, views, masks: np.ndarray) -> dict[str, dict]:
    """Carve every rigid part's hull from the training frames whose state is known before training
    (`known_states`) and gate the part to it. masks (N, H, W) class ids (objects 0..M-1, background M, 255
    unknown) at the views' working size. Returns per object name: cells kept and views used (None: no hull)."""
    n = len(views.names)
    states, known = known_states(views.times, views.labels, views.given)  # held-out labels left out
    cams = []
    for c2w_gl, intr in zip(views.c2w_gl, views.intrinsics):
        w2c = np.linalg.inv(opengl_to_opencv(c2w_gl))
        cams.append((cv2.Rodrigues(w2c[:3, :3])[0], w2c[:3, 3].copy(), intr.K(), intr.dist()))
    report: dict[str, dict] = {}
    for o in motions.rigid(n):
        frames = [f for f in views.train if known[f, o]]
        hull = carve_hull(articulation[o], o, n, frames, states[:, o], masks, cams, (views.box_lo, views.box_hi))
        motions.set_hull(o, hull)
        report[views.names[o]] = None if hull is None else {"views": len(frames), "cells": int(hull[2].sum())}
    return report
