"""The dataset's types: cameras (`Intrinsics`), images with poses (`Frame`), part motions (`Articulation`) and a
loaded dataset (`LiveSceneDataset`), as `interreal.conventions` and DESIGN.md define them."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..conventions import frame_id, frame_index, mask_file
from ..errors import DatasetError
from ..layout import MASKS_DIR
from ..images import read_image_rgb

CAMERA_MODELS = ("OPENCV", "SIMPLE_RADIAL", "RADIAL", "PINHOLE", "SIMPLE_PINHOLE", "OPENCV_FISHEYE")
INTRINSIC_KEYS = ("w", "h", "fl_x", "fl_y", "cx", "cy")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole + OpenCV distortion (k1, k2, p1, p2 [, k3]) as nerfstudio stores them."""

    w: int
    h: int
    fl_x: float
    fl_y: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    camera_model: str = "OPENCV"

    def K(self) -> np.ndarray:
        return np.array([[self.fl_x, 0, self.cx], [0, self.fl_y, self.cy], [0, 0, 1]], dtype=np.float64)

    def dist(self) -> np.ndarray:
        """OpenCV distortion vector (k1, k2, p1, p2, k3)."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3], dtype=np.float64)

    def has_distortion(self) -> bool:
        return bool(np.any(self.dist() != 0))

    def scaled(self, w: int, h: int) -> "Intrinsics":
        """The same camera at another image size (distortion is resolution-independent)."""
        sx, sy = w / self.w, h / self.h
        return replace(self, w=w, h=h, fl_x=self.fl_x * sx, fl_y=self.fl_y * sy, cx=self.cx * sx, cy=self.cy * sy)

    def to_json(self) -> dict[str, Any]:
        d = {k: getattr(self, k) for k in INTRINSIC_KEYS}
        d.update({"k1": self.k1, "k2": self.k2, "p1": self.p1, "p2": self.p2, "camera_model": self.camera_model})
        if self.k3:
            d["k3"] = self.k3
        return {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in d.items()}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "Intrinsics":
        return cls(
            w=int(d["w"]), h=int(d["h"]), fl_x=float(d["fl_x"]), fl_y=float(d.get("fl_y", d["fl_x"])),
            cx=float(d["cx"]), cy=float(d["cy"]),
            k1=float(d.get("k1", 0.0)), k2=float(d.get("k2", 0.0)),
            p1=float(d.get("p1", 0.0)), p2=float(d.get("p2", 0.0)), k3=float(d.get("k3", 0.0)),
            camera_model=str(d.get("camera_model", "OPENCV")),
        )


@dataclass
class Frame:
    """One image of the dataset. `c2w` is camera-to-world with OpenGL axes, as stored in transforms.json."""

    file_path: str  # relative to the dataset root, e.g. "images/frame_00042.png"
    c2w: np.ndarray | None = None
    intrinsics: Intrinsics | None = None  # per-frame override (nerfstudio allows it)
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def fid(self) -> str:
        return frame_id(self.file_path)

    @property
    def index(self) -> int:
        return frame_index(self.file_path)

    @property
    def key(self) -> str:
        """The label key this frame has in key_frame_value.yaml (the image stem)."""
        return Path(self.file_path).stem


MOTION_KINDS = ("hinge", "slide")


@dataclass
class Articulation:
    """How one object moves with its state (conventions: `articulation.json`): a hinge turns by s * range radians
    about `axis` through `origin` (right-hand rule), a slide moves s * range world units along `axis`; state 0 is
    the rest pose. `extra` keeps what the estimate measured (residuals, support) for reports."""

    kind: str
    axis: np.ndarray  # (3,) unit
    origin: np.ndarray  # (3,) a point on a hinge's axis (unused by a slide)
    range: float
    extra: dict[str, Any] = field(default_factory=dict)

    def pose(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) taking a rest-pose point p to R @ p + t at state s."""
        if self.kind == "slide":
            return np.eye(3), self.axis * (s * self.range)
        from scipy.spatial.transform import Rotation

        rot = Rotation.from_rotvec(np.asarray(self.axis, float) * (s * self.range)).as_matrix()
        return rot, self.origin - rot @ self.origin

    def measured_states(self, fids: list[str]) -> np.ndarray:
        """(N,) each frame's state as `interreal motions` measured it from the part's displacement (`frame_states`:
        {frame id: state}), NaN where it measured none (not registered, or a motion written by hand)."""
        found = self.extra.get("frame_states")
        out = np.full(len(fids), np.nan)
        if not isinstance(found, dict):
            return out
        for i, fid in enumerate(fids):
            v = found.get(fid)
            if isinstance(v, (int, float)) and math.isfinite(v):
                out[i] = float(v)
        return out

    def to_json(self) -> dict[str, Any]:
        return {"type": self.kind, "axis": [float(v) for v in self.axis],
                "origin": [float(v) for v in self.origin], "range": float(self.range), **self.extra}

    @classmethod
    def from_json(cls, d: dict[str, Any], where: str = "articulation") -> "Articulation":
        try:
            kind = str(d["type"])
            axis = np.asarray(d["axis"], dtype=np.float64).reshape(3)
            origin = np.asarray(d.get("origin", [0.0, 0.0, 0.0]), dtype=np.float64).reshape(3)
            rng = float(d["range"])
        except (KeyError, TypeError, ValueError) as exc:
            raise DatasetError(f"{where}: needs type, axis (3 numbers), origin (3 numbers) and range ({exc})") from exc
        norm = float(np.linalg.norm(axis))
        if kind not in MOTION_KINDS:
            raise DatasetError(f"{where}: type {kind!r} is not one of {MOTION_KINDS}")
        if not (np.isfinite(axis).all() and np.isfinite(origin).all() and math.isfinite(rng)) or norm < 1e-9:
            raise DatasetError(f"{where}: axis, origin and range must be finite and the axis non-zero")
        extra = {k: v for k, v in d.items() if k not in ("type", "axis", "origin", "range")}
        return cls(kind, axis / norm, origin, rng, extra)


@dataclass
class LiveSceneDataset:
    root: Path
    frames: list[Frame]
    intrinsics: Intrinsics | None
    mapping: dict[int, str]
    labels: dict[str, dict[str, float]]
    prompts: dict[str, str] = field(default_factory=dict)
    layout: str = "nerfstudio"  # or "blender"
    extra: dict[str, Any] = field(default_factory=dict)  # other top-level transforms.json keys
    articulation: dict[str, Articulation] = field(default_factory=dict)  # object name -> motion (optional file)

    @property
    def object_names(self) -> list[str]:
        return [self.mapping[i] for i in sorted(self.mapping)]

    @property
    def n_objects(self) -> int:
        return len(self.mapping)

    def frame_intrinsics(self, frame: Frame) -> Intrinsics:
        intr = frame.intrinsics or self.intrinsics
        if intr is None:
            raise DatasetError(f"{self.root}: no intrinsics for {frame.file_path}")
        return intr

    def image_path(self, frame: Frame) -> Path:
        return self.root / frame.file_path

    def load_image(self, frame: Frame) -> np.ndarray:
        """RGB uint8 (H, W, 3); RGBA is blended on white as the official reader does."""
        return read_image_rgb(self.image_path(frame))

    def has_masks(self) -> bool:
        return (self.root / MASKS_DIR).is_dir() and all(mask_file(self.root, f.fid).exists() for f in self.frames)

    def load_mask(self, frame: Frame) -> np.ndarray:
        """(H, W, objects + 1) bool, background last; DatasetError naming the file when it is not one (a float
        0.5 cast to bool would be true in every channel)."""
        path = mask_file(self.root, frame.fid)
        try:
            m = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            raise DatasetError(f"{path}: unreadable mask ({exc}); re-run `interreal masks`") from None
        if m.ndim != 3 or m.dtype != bool:
            raise DatasetError(f"{path}: a {m.ndim}-D {m.dtype} array of shape {m.shape}, expected bool (H, W, "
                               f"objects + 1) with the background last; re-run `interreal masks`")
        return m

    def label_matrix(self) -> tuple[np.ndarray, np.ndarray]:
        """(values, given): (N, M) float and bool arrays over frames x objects; unlabelled entries are 0 / False."""
        names = self.object_names
        values = np.zeros((len(self.frames), len(names)), dtype=np.float32)
        given = np.zeros_like(values, dtype=bool)
        by_index = {}
        for key, entry in self.labels.items():
            by_index[frame_index(key)] = entry
        for i, frame in enumerate(self.frames):
            entry = by_index.get(frame.index)
            if not entry:
                continue
            for j, name in enumerate(names):
                if name in entry:
                    values[i, j] = float(entry[name])
                    given[i, j] = True
        return values, given
