"""Rays from a LiveScene dataset, read only through `interreal.dataset.load_dataset`.

- Cameras: transforms.json stores OpenGL camera-to-world; rays are built with OpenCV axes
  (`interreal.conventions.opengl_to_opencv`), pixel centres undistorted with the dataset's k1, k2, p1, p2, k3.
- Scene box: transforms.json `aabb`/`scene_box` when given, else the SfM point cloud (`sparse_pc.ply`),
  else a box around the cameras and the point they look at. Fields see coordinates normalised to [-1, 1].
- Split: every `holdout_every`-th frame (by position, from `holdout_offset`) is held out and never trained on,
  labels included.
- Frame time: source frame index / largest index, the coordinate of the per-frame variable.
- Transients (`DS/transients/<fid>.png`, `interreal.transients`: people, hands): their pixels are never drawn as
  training rays, so no loss (colour, probability field, proposal) sees them and the static scene is not fitted to
  a hand; their class is unknown (255) in the masks the trainer reads.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import yaml
from tqdm import tqdm

from interreal.conventions import UNANNOTATED, mask_file, onehot_to_index, opengl_to_opencv
from interreal.dataset import (Intrinsics, LiveSceneDataset, format_problems, load_dataset, read_point_cloud,
                               validate)
from interreal.official import official_positions
from interreal.transients import read_transient

from .config import SceneInfo, TrainConfig
from .errors import InvalidDatasetError, LiveSceneError

UNKNOWN = 255


# ----------------------------------------------------------------------------------------------------------------
# Cameras
# ----------------------------------------------------------------------------------------------------------------
def pixel_directions(intr: Intrinsics) -> np.ndarray:
    """Unit-z camera-frame directions (H, W, 3) (OpenCV axes) of pixel centres, distortion removed."""
    if intr.camera_model == "OPENCV_FISHEYE":
        raise LiveSceneError("OPENCV_FISHEYE cameras are not supported: undistort the images first")
    u, v = np.meshgrid(np.arange(intr.w, dtype=np.float64) + 0.5, np.arange(intr.h, dtype=np.float64) + 0.5)
    if intr.has_distortion():
        pts = np.stack([u.ravel(), v.ravel()], -1).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-9)
        und = cv2.undistortPoints(pts, intr.K(), intr.dist(), R=np.eye(3), P=np.eye(3), criteria=crit).reshape(intr.h, intr.w, 2)
        x, y = und[..., 0], und[..., 1]
    else:
        x, y = (u - intr.cx) / intr.fl_x, (v - intr.cy) / intr.fl_y
    return np.stack([x, y, np.ones_like(x)], -1)


def camera_rays(c2w_gl: np.ndarray, intr: Intrinsics, dirs_cam: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World rays (origins, unit dirs, z_scale) of every pixel, each (H*W, 3|3|1); z-depth = distance * z_scale."""
    c2w = opengl_to_opencv(np.asarray(c2w_gl, dtype=np.float64))
    d = (pixel_directions(intr) if dirs_cam is None else dirs_cam).reshape(-1, 3)
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    world = (d / norm) @ c2w[:3, :3].T
    origins = np.broadcast_to(c2w[:3, 3], world.shape)
    return origins.astype(np.float32), world.astype(np.float32), (1.0 / norm[:, 0]).astype(np.float32)


def check_pose(value, where: str) -> np.ndarray:
    """A camera-to-world matrix from user input (4x4, or 3x4 with the last row implied; 16 numbers), finite, with a
    rotation part that is a rotation; else LiveSceneError naming `where`. A NaN camera renders a black image."""
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise LiveSceneError(f"{where}: a camera matrix must be numbers (4x4), got {value!r:.80}") from None
    if m.shape == (16,):
        m = m.reshape(4, 4)
    if m.shape == (3, 4):
        m = np.vstack([m, [0, 0, 0, 1]])
    if m.shape != (4, 4):
        raise LiveSceneError(f"{where}: camera matrix has shape {'x'.join(map(str, m.shape)) or 'scalar'}, "
                             f"expected 4x4 (or 3x4) camera-to-world")
    if not np.isfinite(m).all():
        raise LiveSceneError(f"{where}: camera matrix has non-finite values (NaN or inf)")
    r = m[:3, :3]
    if np.abs(r.T @ r - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(r) - 1) > 1e-3:
        raise LiveSceneError(f"{where}: the camera matrix's 3x3 rotation is not a rotation (orthonormal, det +1)")
    if not np.allclose(m[3], [0, 0, 0, 1]):
        raise LiveSceneError(f"{where}: the camera matrix's last row is {m[3].tolist()}, expected [0, 0, 0, 1]")
    return m


def check_intrinsics(intr: Intrinsics, where: str, max_pixels: int = 64_000_000) -> Intrinsics:
    """Finite, positive focal lengths and a sane image size (LiveSceneError naming `where`)."""
    vals = [intr.fl_x, intr.fl_y, intr.cx, intr.cy]
    if not (np.isfinite(vals).all() and intr.fl_x > 0 and intr.fl_y > 0):
        raise LiveSceneError(f"{where}: intrinsics fl_x, fl_y, cx, cy = {vals} must be finite with positive focal lengths")
    if intr.w < 1 or intr.h < 1 or intr.w * intr.h > max_pixels:
        raise LiveSceneError(f"{where}: image size {intr.w}x{intr.h} is not between 1x1 and {max_pixels:,} pixels")
    return intr


# ----------------------------------------------------------------------------------------------------------------
# Scene box
# ----------------------------------------------------------------------------------------------------------------
def sparse_points(ds: LiveSceneDataset) -> np.ndarray | None:
    """(P, 3) the SfM point cloud (transforms.json's `ply_file_path`, else `sparse_pc.ply`); None when it is missing,
    broken or nearly empty."""
    pts = read_point_cloud(ds.root, ds.extra)
    return pts if pts is not None and len(pts) >= 10 else None


def scene_box(ds: LiveSceneDataset) -> tuple[np.ndarray, np.ndarray, str]:
    """(lo, hi, source) world-space box the fields cover."""
    for key in ("aabb", "scene_box"):
        if key in ds.extra:
            box = _box_of(ds.extra[key], f"{ds.root / 'transforms.json'} '{key}'")
            return box[0], box[1], f"transforms.json:{key}"
    poses = np.stack([opengl_to_opencv(f.c2w) for f in ds.frames])
    centres = poses[:, :3, 3]
    pts = sparse_points(ds)
    if pts is not None:
        lo, hi = np.percentile(pts, 1, axis=0), np.percentile(pts, 99, axis=0)
        lo, hi = np.minimum(lo, centres.min(0)), np.maximum(hi, centres.max(0))
        pad = 0.1 * (hi - lo).max()
        return lo - pad, hi + pad, "sparse_pc.ply"
    # the point the optical axes pass closest to (least squares), else the camera centroid
    axes = poses[:, :3, 2]
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for c, z in zip(centres, axes):
        p = np.eye(3) - np.outer(z, z)
        a += p
        b += p @ c
    focus = centres.mean(0)
    if np.linalg.cond(a) < 1e6:
        cand = np.linalg.solve(a, b)
        if np.mean(((cand - centres) * axes).sum(-1) > 0) > 0.8:
            focus = cand
    dist = np.linalg.norm(centres - focus, axis=-1)
    radius = max(float(np.median(dist)) * 1.5, float(dist.max()) * 1.1, 1e-3)
    lo = np.minimum(focus - radius, centres.min(0))
    hi = np.maximum(focus + radius, centres.max(0))
    return lo, hi, "cameras"


def _box_of(value, where: str) -> np.ndarray:
    """(2, 3) finite box with lo < hi from 6 numbers, else LiveSceneError naming `where`."""
    try:
        box = np.asarray(value, dtype=np.float64).reshape(2, 3)
    except (TypeError, ValueError):
        raise LiveSceneError(f"{where}: expected 6 numbers [[x0, y0, z0], [x1, y1, z1]], got {value!r}") from None
    if not np.isfinite(box).all() or not (box[0] < box[1]).all():
        raise LiveSceneError(f"{where}: {box.tolist()} is not a finite box with x0 < x1, y0 < y1, z0 < z1")
    return box


# ----------------------------------------------------------------------------------------------------------------
# Checks: what the trainer reads must be right before it trains (else the optimiser gets the blame)
# ----------------------------------------------------------------------------------------------------------------
def require_valid(path: str | Path, check_masks: bool = True) -> None:
    """The dataset passes `interreal validate` (the same checks, one code path), else InvalidDatasetError with
    every problem listed. There is no override: a broken dataset trains or renders garbage. `check_masks=False`
    reads only each mask's header (dtype, shape): what a trained run's readers need, in a 30th of the time.

    One exception: a dataset with no masks at all is accepted (the colour field trains; grounding and mask figures
    then say the run has no masks); some frames without a mask is an error."""
    result = validate(path, check_masks=check_masks)
    problems = result.problems
    missing = [p for p in problems if p.kind == "missing-mask"]
    if missing and len(missing) == result.summary.get("frames", -1):
        problems = [p for p in problems if p.kind != "missing-mask"]
    if problems:
        listed = format_problems(dataclasses.replace(result, problems=problems), per_kind=5)
        raise InvalidDatasetError(f"the dataset {path} is not valid, so livescene will not read it (fix it, then "
                                  f"check with `interreal validate {path}`):\n{listed}")


def require_valid_run_dataset(run_dir: str | Path, command: str) -> Path | None:
    """Validate the dataset a run folder names (RUN/config.yaml 'dataset') before a command reads the run; the
    path, or None when the run names none. A dataset that is gone only warns: what the command can do without it
    (grounding by object name) still works, what needs it (rendering) says so when it loads the run."""
    cfg_path = Path(run_dir) / "config.yaml"
    if not cfg_path.exists():
        return None
    try:
        meta = yaml.safe_load(cfg_path.read_text(encoding="utf-8")) or {}
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise LiveSceneError(f"{cfg_path} is not readable YAML ({' '.join(str(exc).split())[:200]}): "
                             f"the run folder is damaged") from exc
    ds = meta.get("dataset") if isinstance(meta, dict) else None
    if not ds:
        return None
    path = Path(str(ds))
    if not path.exists():
        print(f"livescene {command}: warning: the run's dataset {path} is gone (moved or deleted); commands that "
              f"render need it (--dataset NEW_PATH where offered)", file=sys.stderr)
        return None
    require_valid(path)
    return path


def check_views(views: "Views") -> None:
    """Numbers the model reads are finite and in range: poses, intrinsics, labels, the box (LiveSceneError naming
    the frame) - a NaN here would only show up as a diverged loss."""
    names = [f.fid for f in views.dataset.frames]
    bad = [names[i] for i in range(len(names)) if not np.isfinite(views.c2w_gl[i]).all()]
    if bad:
        raise InvalidDatasetError(f"non-finite camera pose (transform_matrix) in frame(s) {', '.join(bad[:5])} of "
                                  f"{views.dataset.root}: re-run `interreal poses`")
    for i, it in enumerate(views.intrinsics):
        vals = [it.fl_x, it.fl_y, it.cx, it.cy]
        if not (np.isfinite(vals).all() and it.fl_x > 0 and it.fl_y > 0 and it.w > 0 and it.h > 0):
            raise InvalidDatasetError(f"frame {names[i]} of {views.dataset.root}: intrinsics {vals} are not finite "
                                      f"and positive")
    ok = np.isfinite(views.labels) & (views.labels >= 0) & (views.labels <= 1)
    if not ok[views.given].all():
        i, k = np.argwhere(views.given & ~ok)[0]
        raise InvalidDatasetError(f"label of '{views.names[k]}' on frame {names[i]} is {views.labels[i, k]!r}, "
                                  f"not a value in [0, 1]: fix it with `interreal label`")
    _box_of([views.box_lo.tolist(), views.box_hi.tolist()], f"scene box (from {views.box_source})")


# ----------------------------------------------------------------------------------------------------------------
# Dataset -> tensors
# ----------------------------------------------------------------------------------------------------------------
def closest_point_depth(ds: LiveSceneDataset, c2w_gl: np.ndarray, intrinsics: list[Intrinsics],
                        share: float = 1.0) -> float | None:
    """The smallest depth at which any camera sees the SfM point cloud: per camera the `share` percentile of the
    depths of the points that project into its image (a stray point or two must not set it), then the minimum.
    None without `sparse_pc.ply`. Nothing the capture filmed lies much nearer than this to a camera."""
    pts = sparse_points(ds)
    if pts is None:
        return None
    best = np.inf
    for c2w, intr in zip(c2w_gl, intrinsics):
        cv = opengl_to_opencv(c2w)
        cam = (pts - cv[:3, 3]) @ cv[:3, :3]
        z = cam[:, 2]
        front = z > 1e-9
        u = intr.fl_x * cam[front, 0] / z[front] + intr.cx
        v = intr.fl_y * cam[front, 1] / z[front] + intr.cy
        seen = z[front][(u >= 0) & (u < intr.w) & (v >= 0) & (v < intr.h)]
        if len(seen) >= 10:
            best = min(best, float(np.percentile(seen, share)))
    return best if np.isfinite(best) else None


def split_indices(n: int, every: int, offset: int) -> tuple[list[int], list[int]]:
    """(train, held_out) frame positions: every `every`-th frame from `offset` is held out."""
    if every <= 1 or n < 2:
        return list(range(n)), []
    held = [i for i in range(n) if i % every == offset % every]
    if len(held) == n:
        held = held[1:]
    hs = set(held)
    return [i for i in range(n) if i not in hs], held


def frame_times(ds: LiveSceneDataset) -> np.ndarray:
    idx = np.array([f.index for f in ds.frames], dtype=np.float64)
    top = idx.max() if len(idx) and idx.max() > 0 else 1.0
    return (idx / top).astype(np.float32)


def _resize(img: np.ndarray, w: int, h: int, nearest: bool) -> np.ndarray:
    if img.shape[1] == w and img.shape[0] == h:
        return img
    return cv2.resize(img, (w, h), interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)


@dataclass
class Views:
    """Per-frame cameras and metadata (no pixels): what rendering and evaluation need."""

    dataset: LiveSceneDataset
    c2w_gl: np.ndarray  # (N, 4, 4)
    intrinsics: list[Intrinsics]  # per frame, at the working image size
    times: np.ndarray  # (N,)
    labels: np.ndarray  # (N, M) Lvar's targets: the labels, or the measured states (`measured_targets`)
    given: np.ndarray  # (N, M) bool, False on held-out frames
    train: list[int]
    held_out: list[int]
    box_lo: np.ndarray
    box_hi: np.ndarray
    box_source: str
    measured_states: bool = False  # `labels` hold the measured states where there are any (`measured_targets`)

    @property
    def names(self) -> list[str]:
        return self.dataset.object_names

    @property
    def n_objects(self) -> int:
        return self.dataset.n_objects

    def closest_depth(self) -> float | None:
        """`closest_point_depth` of these cameras (what `config.resolve` sets the near plane from)."""
        return closest_point_depth(self.dataset, self.c2w_gl, self.intrinsics)

    def scene_info(self) -> SceneInfo:
        intr = self.intrinsics[0]
        centre = 0.5 * (self.box_lo + self.box_hi)
        dist = np.linalg.norm(self.c2w_gl[:, :3, 3] - centre, axis=-1)
        return SceneInfo(width=intr.w, height=intr.h, focal=0.5 * (intr.fl_x + intr.fl_y),
                         extent=float((self.box_hi - self.box_lo).max()),
                         distance=float(max(np.median(dist), 0.05 * (self.box_hi - self.box_lo).max())),
                         n_frames=len(self.times))


def nearest_views(centres: np.ndarray, train: list[int], centre: np.ndarray, near: int = 0) -> np.ndarray:
    """Positions of the `near` training frames (default: a tenth of them, at least 8) whose cameras stand closest
    to `centre`: the views that can have shown a part from where a camera there looks at it. centres (N, 3)."""
    tr = np.asarray(train)
    near = near or max(8, len(tr) // 10)
    return tr[np.argsort(np.linalg.norm(centres[tr] - centre, axis=1))[:near]]


def working_size(intr: Intrinsics, image_hw: tuple[int, int], max_side: int) -> tuple[int, int]:
    h, w = image_hw
    if max_side and max(w, h) > max_side:
        s = max_side / max(w, h)
        w, h = max(1, int(round(w * s))), max(1, int(round(h * s)))
    return w, h


def load_views(path: str | Path, cfg: TrainConfig, check_masks: bool = True) -> Views:
    """The dataset's cameras and labels, after `require_valid` (an invalid dataset is refused, never read)."""
    require_valid(path, check_masks)
    ds = load_dataset(path)
    if not ds.frames:
        raise LiveSceneError(f"{path}: transforms.json lists no frames")
    first = ds.load_image(ds.frames[0])
    intrs = []
    for f in ds.frames:
        base = ds.frame_intrinsics(f)
        if (base.w, base.h) != (first.shape[1], first.shape[0]):
            base = base.scaled(first.shape[1], first.shape[0])
        w, h = working_size(base, first.shape[:2], cfg.max_side)
        intrs.append(base.scaled(w, h) if (w, h) != (base.w, base.h) else base)
    labels, given = ds.label_matrix()
    if cfg.split == "official":  # the paper's split, so figures compare with its (interreal.official)
        train, held = official_positions(ds.layout, ds.extra, [f.file_path for f in ds.frames])
    else:
        train, held = split_indices(len(ds.frames), cfg.holdout_every, cfg.holdout_offset)
    targets, given = measured_targets(ds, labels, given) if cfg.measured_states else (labels, given.copy())
    given[held] = False
    if cfg.scene_box:
        if len(cfg.scene_box) != 6:
            raise LiveSceneError(f"scene_box needs 6 numbers (x0 y0 z0 x1 y1 z1), got {cfg.scene_box}")
        lo, hi, src = np.asarray(cfg.scene_box[:3], float), np.asarray(cfg.scene_box[3:], float), "config"
    else:
        lo, hi, src = scene_box(ds)
    views = Views(dataset=ds, c2w_gl=np.stack([f.c2w for f in ds.frames]), intrinsics=intrs, times=frame_times(ds),
                  labels=targets, given=given, train=train, held_out=held,
                  box_lo=lo.astype(np.float32), box_hi=hi.astype(np.float32), box_source=src,
                  measured_states=cfg.measured_states)
    check_views(views)
    return views


def measured_matrix(ds: LiveSceneDataset) -> np.ndarray:
    """(N, M) each frame's state as `interreal motions` measured it (`Articulation.measured_states`), clipped to the
    state range; NaN where none was measured (no motion, or the frame not registered)."""
    fids = [f.fid for f in ds.frames]
    out = np.full((len(fids), ds.n_objects), np.nan)
    for o, name in enumerate(ds.object_names):
        motion = ds.articulation.get(name)
        if motion is not None:
            out[:, o] = np.clip(motion.measured_states(fids), 0.0, 1.0)
    return out


def measured_targets(ds: LiveSceneDataset, labels: np.ndarray, given: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lvar's targets (N, M) and where they are given: the labels, with each frame's measured state
    (`measured_matrix`) in their place where `interreal motions` measured one. The labels then only fix a motion's
    ends and direction (the measurement is calibrated on them) and cover the frames it missed."""
    measured = measured_matrix(ds)
    ok = np.isfinite(measured)
    return np.where(ok, measured, labels), given | ok


def measured_counts(views: Views) -> dict[str, int]:
    """{object: training frames whose Lvar target is a measured state} (only objects with any)."""
    counts = np.isfinite(measured_matrix(views.dataset))[views.train].sum(0)
    return {name: int(n) for name, n in zip(views.names, counts) if n}


def load_transient(views: Views, i: int) -> np.ndarray | None:
    """(H, W) bool transient pixels (a person, a hand) at the working size, or None when the frame has none."""
    ds = views.dataset
    m = read_transient(ds.root, ds.frames[i].fid)
    if m is None:
        return None
    intr = views.intrinsics[i]
    return _resize(m.astype(np.uint8), intr.w, intr.h, nearest=True) > 0


def transient_at(views: Views, i: int, w: int, h: int) -> np.ndarray | None:
    """Frame i's transient pixels at (w, h), None when it has none: pixels evaluation leaves unscored (the field
    renders what is behind a hand, not the hand)."""
    tr = load_transient(views, i)
    if tr is None or not tr.any():
        return None
    return _resize(tr.astype(np.uint8), w, h, nearest=True) > 0


def scored_mse(pred: np.ndarray, gt: np.ndarray, transient: np.ndarray | None = None) -> float:
    """Mean squared error over the pixels that belong to the scene: a person or hand (`transient`, (H, W)) is not
    drawn by the field and not held against it."""
    err = (np.asarray(pred, np.float32) - np.asarray(gt, np.float32)) ** 2
    if transient is None or not transient.any() or transient.all():
        return float(err.mean())
    return float(err[~transient].mean())


def load_frame(views: Views, i: int) -> tuple[np.ndarray, np.ndarray | None]:
    """(rgb uint8 (H, W, 3), mask index map uint8 (H, W) or None) at the working size."""
    ds = views.dataset
    intr = views.intrinsics[i]
    frame = ds.frames[i]
    rgb = _resize(ds.load_image(frame), intr.w, intr.h, nearest=False)
    mask = None
    if mask_file(ds.root, frame.fid).exists():
        onehot = ds.load_mask(frame)
        if onehot.shape[-1] != ds.n_objects + 1:
            raise LiveSceneError(f"mask {frame.fid} has {onehot.shape[-1]} channels, expected {ds.n_objects + 1}")
        mask = _resize(onehot_to_index(onehot), intr.w, intr.h, nearest=True)
    return rgb, mask


class ErrorMap:
    """Where the colour error is, per tile of each training frame, so a share of every batch goes there (instant-ngp's
    error map). Uniform rays spend most of a batch on walls the field already draws; on the real laptop video (10
    minutes on 2 cores, two runs each) half of each batch drawn here gave held-out 26.12 / 26.42 dB against 25.72 /
    26.00 uniform. A tile holds a running mean of its rays' squared error; it starts above any error, so every tile is
    visited before its own error decides. Saved with the checkpoint (`Trainer._state`), so a resume draws as an
    uninterrupted run."""

    START = 0.05  # a tile's value before its first ray: above the squared error of all but the worst pixels
    KEEP = 0.7  # running mean: the old value's share at each new ray
    MAX_TILES = 1 << 22  # torch.multinomial's categories stay far below its 2^24 limit

    def __init__(self, n_frames: int, h: int, w: int, train: torch.Tensor, tile: int = 16):
        while len(train) * math.ceil(h / tile) * math.ceil(w / tile) > self.MAX_TILES:
            tile *= 2
        self.tile, self.h, self.w, self.train = tile, h, w, train
        self.err = torch.full((n_frames, math.ceil(h / tile), math.ceil(w / tile)), self.START)

    def draw(self, n: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(frames, ys, xs) (n,): tiles of the training frames drawn by their error, a pixel uniform in each."""
        sub = self.err[self.train]
        th, tw = sub.shape[1:]
        idx = torch.multinomial(sub.reshape(-1), n, replacement=True, generator=gen)
        t = self.tile
        ys = ((idx // tw) % th * t + torch.randint(t, (n,), generator=gen)).clamp(max=self.h - 1)
        xs = (idx % tw * t + torch.randint(t, (n,), generator=gen)).clamp(max=self.w - 1)
        return self.train[idx // (th * tw)], ys, xs

    def record(self, f: torch.Tensor, ys: torch.Tensor, xs: torch.Tensor, err: torch.Tensor) -> None:
        """Rays' squared colour errors (n,) into their tiles' running means (rays sharing a tile: one of them). A
        ray of a diverged step (not finite) is left out: the map must stay a distribution to draw from."""
        ok = torch.isfinite(err)
        f, ys, xs, err = f[ok], ys[ok], xs[ok], err[ok].float().clamp(min=1e-8)
        cell = (f, ys // self.tile, xs // self.tile)
        self.err[cell] = self.KEEP * self.err[cell] + (1 - self.KEEP) * err


class RayData:
    """All training pixels in memory (uint8) with per-intrinsics direction grids; draws random ray batches."""

    def __init__(self, views: Views, device: torch.device):
        self.views = views
        self.device = device
        n = len(views.dataset.frames)
        h, w = views.intrinsics[0].h, views.intrinsics[0].w
        if any((it.w, it.h) != (w, h) for it in views.intrinsics):
            raise LiveSceneError("frames of different sizes are not supported: resize the images to one size")
        self.h, self.w = h, w
        self.rgb = torch.empty((n, h, w, 3), dtype=torch.uint8)
        self.mask = torch.full((n, h, w), UNKNOWN, dtype=torch.uint8)
        self.transient: torch.Tensor | None = None  # (N, H, W) bool once any frame has transient pixels
        for i in tqdm(range(n), desc="loading frames", leave=False, disable=n < 50):
            rgb, mask = load_frame(views, i)
            self.rgb[i] = torch.from_numpy(rgb)
            if mask is not None:
                m = mask.astype(np.int64)
                m = np.where(m == 0, views.dataset.n_objects, m - 1)  # class ids: objects 0..M-1, background M
                m[mask == UNANNOTATED] = UNKNOWN  # a pixel with no channel set (official data): no mask loss
                self.mask[i] = torch.from_numpy(m.astype(np.uint8))
            self._add_transient(i, load_transient(views, i), n)
        self.has_masks = bool((self.mask != UNKNOWN).any())
        keys = {}
        self.dir_id = torch.zeros(n, dtype=torch.long)
        grids = []
        for i, it in enumerate(views.intrinsics):
            if it not in keys:
                keys[it] = len(grids)
                d = pixel_directions(it)
                grids.append(torch.from_numpy(d.astype(np.float32)))
            self.dir_id[i] = keys[it]
        self.dirs_cam = torch.stack(grids)  # (G, H, W, 3)
        c2w = np.stack([opengl_to_opencv(m) for m in views.c2w_gl]).astype(np.float32)
        self.rot = torch.from_numpy(c2w[:, :3, :3])
        self.trans = torch.from_numpy(c2w[:, :3, 3])
        self.times = torch.from_numpy(views.times)
        self.labels = torch.from_numpy(views.labels.astype(np.float32))
        self.given = torch.from_numpy(views.given)
        self.train = torch.tensor(views.train, dtype=torch.long)
        key = [i for i in views.train if views.given[i].any()]
        self.keyframes = torch.tensor(key, dtype=torch.long)
        self.errors = ErrorMap(n, h, w, self.train)

    def sample(self, n: int, gen: torch.Generator, keyframe_fraction: float,
               error_share: float = 0.0) -> dict[str, torch.Tensor]:
        """A batch of n rays: `keyframe_fraction` from frames with state labels, of the others `error_share` drawn
        by the error map (`ErrorMap`, fed by `record`), the rest uniform over the training pixels."""
        n_key = int(round(n * keyframe_fraction)) if len(self.keyframes) else 0
        f_all = self.train[torch.randint(len(self.train), (n - n_key,), generator=gen)]
        if n_key:
            f_key = self.keyframes[torch.randint(len(self.keyframes), (n_key,), generator=gen)]
            f_all = torch.cat([f_all, f_key])
        ys = torch.randint(self.h, (n,), generator=gen)
        xs = torch.randint(self.w, (n,), generator=gen)
        n_err = int(round((n - n_key) * error_share))
        if n_err:
            f_all[:n_err], ys[:n_err], xs[:n_err] = self.errors.draw(n_err, gen)
        if self.transient is not None:
            f_all, ys, xs = self.avoid_transients(f_all, ys, xs, n - n_key, gen)
        out = self.gather(f_all, ys, xs)
        out["pixel"] = torch.stack([f_all, ys, xs], -1).to(self.device)
        return out

    def record(self, batch: dict[str, torch.Tensor], err: torch.Tensor) -> None:
        """The batch's squared colour errors (n,) into the error map."""
        f, ys, xs = batch["pixel"].cpu().unbind(-1)
        self.errors.record(f, ys, xs, err.detach().cpu())

    def _add_transient(self, i: int, tr: np.ndarray | None, n: int) -> None:
        """Record frame i's transient pixels; their class becomes unknown (no probability-field loss there)."""
        if tr is None or not tr.any():
            return
        if self.transient is None:
            self.transient = torch.zeros((n, self.h, self.w), dtype=torch.bool)
        self.transient[i] = torch.from_numpy(tr)
        self.mask[i][self.transient[i]] = UNKNOWN

    def avoid_transients(self, f: torch.Tensor, ys: torch.Tensor, xs: torch.Tensor, n_free: int,
                         gen: torch.Generator, rounds: int = 32) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Rays that landed on a transient pixel are drawn again (frame and pixel, from the same pool: training
        frames for the first `n_free`, keyframes after), so rays stay uniform over the static pixels and no loss ever
        sees a person or a hand. Rays still on one after `rounds` (frames nearly all transient) are dropped."""
        f, ys, xs = f.clone(), ys.clone(), xs.clone()
        for _ in range(rounds):
            idx = torch.nonzero(self.transient[f, ys, xs])[:, 0]
            if not len(idx):
                return f, ys, xs
            free = idx < n_free
            new = torch.empty(len(idx), dtype=torch.long)
            n_f = int(free.sum())
            new[free] = self.train[torch.randint(len(self.train), (n_f,), generator=gen)]
            if n_f < len(idx):
                new[~free] = self.keyframes[torch.randint(len(self.keyframes), (len(idx) - n_f,), generator=gen)]
            f[idx] = new
            ys[idx] = torch.randint(self.h, (len(idx),), generator=gen)
            xs[idx] = torch.randint(self.w, (len(idx),), generator=gen)
        keep = ~self.transient[f, ys, xs]
        return f[keep], ys[keep], xs[keep]

    def gather(self, f: torch.Tensor, ys: torch.Tensor, xs: torch.Tensor) -> dict[str, torch.Tensor]:
        d = self.dirs_cam[self.dir_id[f], ys, xs]
        z_scale = 1.0 / d.norm(dim=-1)
        d = d * z_scale[:, None]
        dirs = torch.einsum("nij,nj->ni", self.rot[f], d)
        out = {
            "origins": self.trans[f], "dirs": dirs, "z_scale": z_scale,
            "rgb": self.rgb[f, ys, xs].float() / 255.0,
            "mask": self.mask[f, ys, xs].long().masked_fill(self.mask[f, ys, xs] == UNKNOWN, -1),
            "t": self.times[f], "labels": self.labels[f], "given": self.given[f], "frame": f,
        }
        return {k: v.to(self.device, non_blocking=True) for k, v in out.items()}
