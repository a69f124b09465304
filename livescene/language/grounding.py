"""From a chosen object to its mask in any view: the trained probability field, thresholded.

The grounding mask of object k in a view is `probs[..., k] > mask_threshold`, where probs is the softmax of the
rendered object logits (`livescene.render.render_view`). Views are dataset frames (rendered at the run's state for
that frame) or any camera the caller gives. `mask_iou` scores a mask against a truth mask.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np

from interreal import atomic
from interreal.conventions import frame_id, mask_file
from interreal.errors import InputError
from ..errors import LiveSceneError
from ..render import render_view

DEFAULT_VIEWS = 4
OVERLAY_COLOR = np.array([255, 40, 40], dtype=np.float32)


@dataclass
class View:
    """A camera to ground in: a name for files, camera-to-world (OpenGL), intrinsics, and the object states:
    explicit {name: value} overrides (None = none) on top of the run's learned states at `time`."""

    name: str
    c2w_gl: np.ndarray
    intrinsics: Any
    states: dict[str, float] | None = None
    time: float = 0.0


@dataclass
class ViewMask:
    view: View
    rgb: np.ndarray  # (H, W, 3) uint8 render
    prob: np.ndarray  # (H, W) float32 probability of the chosen object
    mask: np.ndarray  # (H, W) bool
    probs: np.ndarray  # (H, W, M + 1) every object's probability (background last)

    @property
    def area(self) -> float:
        return float(self.mask.mean())


def mask_iou(pred: np.ndarray, truth: np.ndarray) -> float | None:
    """Intersection over union of two bool masks; None when both are empty (the view says nothing)."""
    pred, truth = np.asarray(pred, bool), np.asarray(truth, bool)
    if pred.shape != truth.shape:
        raise ValueError(f"mask shapes differ: {pred.shape} vs {truth.shape}")
    union = np.logical_or(pred, truth).sum()
    if union == 0:
        return None
    return float(np.logical_and(pred, truth).sum() / union)


def overlay(rgb: np.ndarray, mask: np.ndarray, alpha: float = 0.55) -> np.ndarray:
    """The render with the mask tinted red and its outline drawn, for a person to check at a glance."""
    out = rgb.astype(np.float32).copy()
    out[mask] = (1 - alpha) * out[mask] + alpha * OVERLAY_COLOR
    out = out.clip(0, 255).astype(np.uint8)
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(out, contours, -1, (255, 255, 0), 1)
    return out


def check_run_has_masks(run: Any) -> None:
    """A run trained without object masks has an untrained probability field: refuse to ground with it."""
    if not run.names:
        raise LiveSceneError("the run has no objects (empty mapping.yaml): there is nothing to ground")
    loss = getattr(run.config, "loss", None)
    if loss is not None and not (getattr(loss, "focal", 0) or getattr(loss, "repulsion", 0)):
        raise LiveSceneError("this run was trained with the mask losses off (loss.focal = loss.repulsion = 0): its "
                             "probability field cannot ground objects; retrain with the default mask losses")
    ds = run.dataset
    if not any(mask_file(ds.root, f.fid).exists() for f in ds.frames):
        raise LiveSceneError(f"this run was trained without object masks (its dataset {ds.root} has no masks/): its "
                             f"probability field is untrained, so it cannot ground objects; make masks with "
                             f"`interreal masks DS --keyframes DIR` and train again")


def frame_views(run: Any, spec: str | Sequence[str] | None = None) -> list[View]:
    """Views at dataset frames: spec = None (a few spread frames), "all", "held-out", or frame ids ("00042,00120").

    Each is rendered at the run's learned states for that frame (what the scene looked like then)."""
    frames = list(run.dataset.frames)
    views = run.views
    if not frames:
        raise LiveSceneError("the run's dataset has no frames to render")
    if spec is None or spec == "" or spec == []:
        picks = sorted(set(np.linspace(0, len(frames) - 1, min(DEFAULT_VIEWS, len(frames))).round().astype(int)))
    elif spec in ("all", ["all"]):
        picks = list(range(len(frames)))
    elif spec in ("held-out", ["held-out"]):
        picks = list(views.held_out) or list(range(len(frames)))
    else:
        tokens = spec.split(",") if isinstance(spec, str) else [t for s in spec for t in str(s).split(",")]
        by_id = {f.fid: i for i, f in enumerate(frames)}
        by_index = {f.index: i for i, f in enumerate(frames)}
        picks = []
        for tok in (t.strip() for t in tokens if t.strip()):
            i = by_id.get(frame_id(tok))
            if i is None and tok.isdigit():
                i = by_index.get(int(tok))
            if i is None:
                raise InputError(f"view {tok!r} is not a frame of the run's dataset (frames "
                                 f"{frames[0].fid}..{frames[-1].fid}, {len(frames)} in all); use frame ids, "
                                 f"'held-out' or 'all'")
            picks.append(i)
    return [View(frames[i].fid, np.asarray(views.c2w_gl[i], dtype=np.float64), views.intrinsics[i], None,
                 float(views.times[i])) for i in picks]


def render_mask(run: Any, view: View, obj: int, mask_threshold: float = 0.5) -> ViewMask:
    """Render one view and threshold the chosen object's probability."""
    out = render_view(run, view.c2w_gl, view.intrinsics, view.states or None, time=view.time)
    probs = _numpy(out["probs"])
    if probs.ndim != 3 or obj >= probs.shape[-1] - 1:
        raise LiveSceneError(f"render_view returned probs of shape {probs.shape}: expected (H, W, objects + 1) "
                             f"with object {obj} among them")
    rgb = _numpy(out["rgb"])
    if rgb.dtype != np.uint8:
        rgb = (rgb.clip(0, 1) * 255 + 0.5).astype(np.uint8)
    prob = probs[..., obj].astype(np.float32)
    return ViewMask(view, rgb, prob, prob > mask_threshold, probs)


def _numpy(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().float().cpu().numpy()
    return np.asarray(x)


def write_view(out_dir: Path, vm: ViewMask) -> dict[str, str]:
    """mask_<view>.png (0/255), prob_<view>.png (0..255), overlay_<view>.png; returns the file names."""
    files = {"mask": f"mask_{vm.view.name}.png", "prob": f"prob_{vm.view.name}.png",
             "overlay": f"overlay_{vm.view.name}.png"}
    atomic.write_image(out_dir / files["mask"], vm.mask.astype(np.uint8) * 255)
    atomic.write_image(out_dir / files["prob"], (vm.prob.clip(0, 1) * 255 + 0.5).astype(np.uint8))
    atomic.write_image(out_dir / files["overlay"], overlay(vm.rgb, vm.mask))
    return files
