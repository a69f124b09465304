"""Read, write and validate the LiveScene dataset layout (see DESIGN.md and `interreal.conventions`).

This is the public dataset API: `livescene` reads datasets through `load_dataset` only.
It reads our datasets, the official InterReal (nerfstudio `transforms.json`) layout and the official
OmniSim (Blender-style `camera_angle_x`, `file_path` without extension) layout.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import yaml

from . import atomic
from .conventions import (
    ARTICULATION_FILE,
    IMAGES_DIR,
    LABELS_FILE,
    MAPPING_FILE,
    MASKS_DIR,
    PROMPTS_FILE,
    REPORTS_DIR,
    TRANSFORMS_FILE,
    frame_id,
    frame_index,
    mask_file,
)
from .errors import DatasetError

CAMERA_MODELS = ("OPENCV", "SIMPLE_RADIAL", "RADIAL", "PINHOLE", "SIMPLE_PINHOLE", "OPENCV_FISHEYE")
INTRINSIC_KEYS = ("w", "h", "fl_x", "fl_y", "cx", "cy")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")


# ----------------------------------------------------------------------------------------------------------------
# Data classes
# ----------------------------------------------------------------------------------------------------------------
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


# ----------------------------------------------------------------------------------------------------------------
# Readers
# ----------------------------------------------------------------------------------------------------------------
def read_image_rgb(path: str | Path) -> np.ndarray:
    import cv2

    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise DatasetError(f"cannot decode image {path}: the file is not an image or is truncated")
    if img.dtype == np.uint16:
        img = (img / 257.0).round().astype(np.uint8)
    if img.ndim == 2:
        return np.repeat(img[..., None], 3, axis=2)
    if img.shape[2] == 4:
        rgb = img[..., 2::-1].astype(np.float32)
        a = img[..., 3:4].astype(np.float32) / 255.0
        return (rgb * a + 255.0 * (1 - a)).round().astype(np.uint8)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)  # 10x faster than copying a reversed-stride view


def read_yaml(path: Path) -> Any:
    with open(path, "r", encoding="utf-8") as fh:
        return yaml.safe_load(fh)


def read_mapping(root: str | Path) -> dict[int, str]:
    path = Path(root) / MAPPING_FILE
    if not path.exists():
        return {}
    raw = _read_yaml_or_error(path, "name the objects 0, 1, ... (e.g. {0: fridge door})") or {}
    if not isinstance(raw, dict):
        raise DatasetError(f"{path}: expected a mapping of object id -> name, got {type(raw).__name__}")
    out: dict[int, str] = {}
    for k, v in raw.items():
        try:
            out[int(k)] = str(v)
        except (TypeError, ValueError):
            raise DatasetError(f"{path}: object id {k!r} is not an integer; fix the file (ids 0, 1, ...)") from None
    return out


def _read_yaml_or_error(path: Path, hint: str) -> Any:
    try:
        return read_yaml(path)
    except (OSError, yaml.YAMLError, UnicodeDecodeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DatasetError(f"{path} is not valid YAML ({first}); {hint}") from None


def read_labels_raw(root: str | Path) -> dict[str, Any]:
    """key_frame_value.yaml as written, bad entries included ({} when absent): what the label tools edit, so a
    hand-made mistake can be listed and overwritten with our tools instead of breaking them."""
    path = Path(root) / LABELS_FILE
    if not path.exists():
        return {}
    raw = _read_yaml_or_error(path, "fix it by hand, or move it away and set the labels again") or {}
    if not isinstance(raw, dict):
        raise DatasetError(f"{path}: expected {{frame_00042: {{object: value}}}}, got a {type(raw).__name__}; "
                           "fix it by hand, or move it away and set the labels again")
    return {str(k): ({str(n): v for n, v in entry.items()} if isinstance(entry, dict) else ({} if entry is None else entry))
            for k, entry in raw.items()}


def label_value_problem(value: Any) -> str | None:
    """Why a stored label cannot be a state (None when it is a finite number in [0, 1])."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        try:
            v = float(str(value).strip())
        except ValueError:
            return f"{value!r} is not a number"
        if isinstance(value, bool):
            return f"{value!r} is not a number"
    else:
        v = float(value)
    if not math.isfinite(v):
        return f"{value!r} is not a finite number"
    if not 0.0 <= v <= 1.0:
        return f"{value!r} is outside [0, 1]"
    return None


def read_labels(root: str | Path) -> dict[str, dict[str, float]]:
    """Frame key -> {object: state}; DatasetError naming the file and entry on anything that is not a state in
    [0, 1] (never clipped: a 5.0 is a mistake, not a fully open door)."""
    path = Path(root) / LABELS_FILE
    out: dict[str, dict[str, float]] = {}
    for key, entry in read_labels_raw(root).items():
        if not isinstance(entry, dict):
            raise DatasetError(f"{path}: entry {key}: expected {{object name: value}}, got {entry!r}; fix it with "
                               f"`interreal label {Path(root)} --set OBJECT {key} VALUE` or by hand")
        for name, value in entry.items():
            why = label_value_problem(value)
            if why is not None:
                raise DatasetError(f"{path}: entry {key} / {name}: {why}; fix it with "
                                   f"`interreal label {Path(root)} --set {name!r} {key} VALUE` (or --unset)")
            out.setdefault(key, {})[name] = float(value)
        out.setdefault(key, {})
    return out


def read_prompts(root: str | Path) -> dict[str, str]:
    path = Path(root) / PROMPTS_FILE
    if not path.exists():
        return {}
    raw = read_yaml(path) or {}
    return {str(k): str(v) for k, v in raw.items()} if isinstance(raw, dict) else {}


def known_states(times: np.ndarray, labels: np.ndarray, given: np.ndarray, tol: float = 0.02
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(states, known) (N, M) from the labels alone: labelled frames, and frames between two labelled frames (in
    `times` order) whose labels agree within `tol` (the object was held still between them). labels, given (N, M)
    as `label_matrix` gives them."""
    states = np.where(given, labels, 0.0).astype(np.float64)
    known = given.copy()
    order = np.argsort(times, kind="stable")
    for o in range(labels.shape[1]):
        marked = [p for p, i in enumerate(order) if given[i, o]]
        for a, b in zip(marked[:-1], marked[1:]):
            la, lb = labels[order[a], o], labels[order[b], o]
            if abs(la - lb) <= tol:
                between = order[a + 1: b]
                states[between, o] = 0.5 * (la + lb)
                known[between, o] = True
    return states, known


def read_articulation(root: str | Path) -> dict[str, Articulation]:
    """Object name -> motion from `articulation.json` ({} when the file is absent)."""
    path = Path(root) / ARTICULATION_FILE
    if not path.exists():
        return {}
    try:
        raw = json.loads(path.read_text())
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path} is not valid JSON ({exc}); re-run `interreal motions`") from exc
    objects = raw.get("objects") if isinstance(raw, dict) else None
    if not isinstance(objects, dict):
        raise DatasetError(f"{path}: expected {{\"objects\": {{name: {{type, axis, origin, range}}}}}}")
    return {str(n): Articulation.from_json(d if isinstance(d, dict) else {}, f"{path.name}[{n}]")
            for n, d in objects.items()}


def _matrix(value: Any) -> np.ndarray:
    m = np.asarray(value, dtype=np.float64)
    if m.shape == (3, 4):
        m = np.vstack([m, [0, 0, 0, 1]])
    if m.shape != (4, 4):
        raise ValueError(f"transform_matrix has shape {m.shape}, expected 4x4")
    return m


def _resolve_blender_path(root: Path, file_path: str) -> str:
    rel = file_path[2:] if file_path.startswith("./") else file_path
    if Path(rel).suffix.lower() in IMAGE_SUFFIXES:
        return rel
    for suf in (".png", ".jpg", ".jpeg"):
        if (root / (rel + suf)).exists():
            return rel + suf
    return rel + ".png"


def load_transforms(root: str | Path) -> tuple[Intrinsics | None, list[Frame], str, dict[str, Any]]:
    """Parse transforms.json in either layout; returns (shared intrinsics, frames, layout, other keys)."""
    root = Path(root)
    path = root / TRANSFORMS_FILE
    if not path.exists():
        raise DatasetError(f"{path} is missing: run `interreal poses {root}` (or `interreal process`) first")
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path} is not valid JSON ({exc}); re-run `interreal poses`") from exc
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise DatasetError(f"{path} has no 'frames' list")
    layout = "blender" if "camera_angle_x" in meta and "fl_x" not in meta else "nerfstudio"
    frames: list[Frame] = []
    intr: Intrinsics | None = None
    if layout == "nerfstudio" and all(k in meta for k in ("fl_x", "cx", "cy", "w", "h")):
        intr = Intrinsics.from_json(meta)
    for entry in meta["frames"]:
        fp = str(entry["file_path"])
        if layout == "blender":
            fp = _resolve_blender_path(root, fp)
        elif fp.startswith("./"):
            fp = fp[2:]
        fr_intr = Intrinsics.from_json({**meta, **entry}) if "fl_x" in entry else None
        extra = {k: v for k, v in entry.items() if k not in ("file_path", "transform_matrix")}
        frames.append(Frame(file_path=fp, c2w=_matrix(entry["transform_matrix"]), intrinsics=fr_intr, extra=extra))
    if layout == "blender":
        if not frames:
            raise DatasetError(f"{path} has no frames")
        h, w = read_image_rgb(root / frames[0].file_path).shape[:2]
        f = 0.5 * w / math.tan(0.5 * float(meta["camera_angle_x"]))
        intr = Intrinsics(w=w, h=h, fl_x=f, fl_y=f, cx=w / 2, cy=h / 2, camera_model="PINHOLE")
    keys = set(INTRINSIC_KEYS + DISTORTION_KEYS + ("frames", "camera_model", "camera_angle_x"))
    extra = {k: v for k, v in meta.items() if k not in keys}
    return intr, frames, layout, extra


def load_dataset(root: str | Path) -> LiveSceneDataset:
    """Load a dataset folder (our layout, InterReal or OmniSim). Frames are sorted by file path, as nerfstudio does."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root} is not a folder")
    intr, frames, layout, extra = load_transforms(root)
    if layout == "nerfstudio":
        frames.sort(key=lambda f: f.file_path)
    return LiveSceneDataset(
        root=root, frames=frames, intrinsics=intr, mapping=read_mapping(root), labels=read_labels(root),
        prompts=read_prompts(root), layout=layout, extra=extra, articulation=read_articulation(root),
    )


def list_images(folder: str | Path) -> list[Path]:
    """Frame images in a dataset's images/ folder, in name order."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


# ----------------------------------------------------------------------------------------------------------------
# Writers (all atomic)
# ----------------------------------------------------------------------------------------------------------------
def write_transforms(root: str | Path, intrinsics: Intrinsics, frames: Iterable[Frame], extra: dict | None = None) -> Path:
    """Write nerfstudio transforms.json: shared intrinsics at the top, OpenGL camera-to-world per frame."""
    out: dict[str, Any] = intrinsics.to_json()
    out.update(extra or {})
    out["frames"] = []
    for fr in frames:
        if fr.c2w is None:
            continue
        entry = {"file_path": fr.file_path, "transform_matrix": np.asarray(fr.c2w, dtype=np.float64).tolist()}
        if fr.intrinsics is not None:
            entry.update(fr.intrinsics.to_json())
        entry.update(fr.extra)
        out["frames"].append(entry)
    path = Path(root) / TRANSFORMS_FILE
    atomic.write_json(path, out)
    return path


def write_mapping(root: str | Path, mapping: dict[int, str]) -> None:
    atomic.write_yaml(Path(root) / MAPPING_FILE, {int(k): str(v) for k, v in sorted(mapping.items())})


def write_labels(root: str | Path, labels: dict[str, dict[str, float]]) -> None:
    ordered = {k: (_label_out(labels[k]) if isinstance(labels[k], dict) else labels[k])
               for k in sorted(labels, key=_label_sort_key)}
    atomic.write_yaml(Path(root) / LABELS_FILE, ordered)


def _label_out(entry: dict[str, Any]) -> dict[str, Any]:
    """Numbers as floats; a bad entry the user has not repaired yet is written back as it was, not lost."""
    return {n: (float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else v) for n, v in entry.items()}


def write_prompts(root: str | Path, prompts: dict[str, str]) -> None:
    atomic.write_yaml(Path(root) / PROMPTS_FILE, dict(prompts))


def write_articulation(root: str | Path, motions: dict[str, Articulation], extra: dict | None = None) -> Path:
    """Write `articulation.json` (objects in the order given; `extra`: top-level provenance keys)."""
    path = Path(root) / ARTICULATION_FILE
    atomic.write_json(path, {**(extra or {}), "objects": {n: m.to_json() for n, m in motions.items()}})
    return path


def write_mask(root: str | Path, fid: str, onehot: np.ndarray) -> None:
    if onehot.ndim != 3 or onehot.dtype != bool:
        raise ValueError(f"mask must be bool (H, W, objects + 1), got {onehot.dtype} {onehot.shape}")
    atomic.write_npy(mask_file(Path(root), fid), onehot)


def _label_sort_key(key: str) -> tuple[int, str]:
    try:
        return (frame_index(key), key)
    except ValueError:
        return (1 << 30, key)


# ----------------------------------------------------------------------------------------------------------------
# Validation
# ----------------------------------------------------------------------------------------------------------------
@dataclass
class Problem:
    kind: str  # a stable class name, e.g. "mask-not-onehot"; tests and tools match on it
    where: str
    message: str

    def __str__(self) -> str:
        return f"[{self.kind}] {self.where}: {self.message}"


@dataclass
class ValidationResult:
    root: Path
    problems: list[Problem]
    summary: dict[str, Any]
    warnings: list[str] = field(default_factory=list)  # usable, but training will suffer (e.g. too few labels)

    @property
    def ok(self) -> bool:
        return not self.problems

    def kinds(self) -> set[str]:
        return {p.kind for p in self.problems}


def validate(root: str | Path, check_masks: bool = True) -> ValidationResult:
    """Every problem that stops the official reader (or would make training wrong); never raises on garbage.

    Also names stages whose inputs changed since they ran (`interreal.provenance`: stale poses, masks, labels,
    motions). `check_masks=False` is the quick mode for tools that validate before they start (`livescene`): image
    and mask headers, end markers and staleness only, no per-pixel decoding (about 0.5 s for 300 frames instead of
    10+ s); everything else is checked the same way, by the same code."""
    root = Path(root)
    problems: list[Problem] = []
    summary: dict[str, Any] = {"root": str(root)}

    def add(kind: str, where: str | Path, message: str) -> None:
        problems.append(Problem(kind, str(where), message))

    if not root.is_dir():
        add("no-dataset", root, "not a folder")
        return ValidationResult(root, problems, summary)

    meta = _validate_transforms_json(root, add)
    frames = _validate_frames(root, meta, add) if meta is not None else []
    summary["frames"] = len(frames)
    mapping = _validate_mapping(root, add)
    summary["objects"] = [mapping[i] for i in sorted(mapping)] if mapping else []
    labels = _validate_labels(root, mapping, frames, add)
    summary["labels_per_object"] = _labels_per_object(labels, mapping)
    warnings = [m for _, m in label_shortage(summary["labels_per_object"], len(frames))] if frames else []
    sizes = _validate_images(root, frames, meta, add, decode=check_masks)
    summary["size"] = sorted({f"{w}x{h}" for (w, h) in sizes.values()})
    _validate_masks(root, frames, mapping, sizes, add, pixels=check_masks)
    summary["masks"] = bool(frames) and all(mask_file(root, fid).exists() for fid, _ in frames)
    summary["poses"] = sum(1 for _, e in frames if "transform_matrix" in e)
    summary["articulated"] = _validate_articulation(root, mapping, add)
    _validate_reports(root, add)
    _validate_provenance(root, add)
    return ValidationResult(root, problems, summary, warnings)


def _validate_transforms_json(root: Path, add) -> dict | None:
    path = root / TRANSFORMS_FILE
    if not path.exists():
        add("no-transforms", path, "missing: run `interreal poses DS` (or import poses with --poses FILE)")
        return None
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        add("bad-json", path, f"not valid JSON: {exc}")
        return None
    if not isinstance(meta, dict):
        add("bad-json", path, "top level is not an object")
        return None
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        add("no-frames", path, "'frames' is missing or empty")
        return None
    if "camera_angle_x" in meta and "fl_x" not in meta:
        angle = meta.get("camera_angle_x")
        if not isinstance(angle, (int, float)) or not (0 < float(angle) < math.pi):
            add("bad-intrinsics", path, f"camera_angle_x={angle!r} is not an angle in (0, pi) radians")
        return meta
    for i, entry in enumerate(frames):
        if not isinstance(entry, dict):
            continue
        merged = {**meta, **entry}
        where = f"{path.name} frames[{i}]" if any(k in entry for k in INTRINSIC_KEYS) else path.name
        missing = [k for k in INTRINSIC_KEYS if k not in merged]
        if missing:
            add("missing-intrinsics", where, f"missing keys {missing}")
            if where == path.name:
                break
            continue
        try:
            vals = {k: float(merged[k]) for k in INTRINSIC_KEYS + tuple(k for k in DISTORTION_KEYS if k in merged)}
        except (TypeError, ValueError):
            add("bad-intrinsics", where, "intrinsics must be numbers")
            continue
        if not all(math.isfinite(v) for v in vals.values()):
            add("bad-intrinsics", where, "intrinsics must be finite")
        elif vals["w"] <= 0 or vals["h"] <= 0 or vals["fl_x"] <= 0 or vals["fl_y"] <= 0:
            add("bad-intrinsics", where, "w, h, fl_x and fl_y must be positive")
        elif not (0 < vals["cx"] < vals["w"] and 0 < vals["cy"] < vals["h"]):
            add("bad-intrinsics", where, f"principal point ({vals['cx']}, {vals['cy']}) is outside the image")
        model = merged.get("camera_model", "OPENCV")
        if model not in CAMERA_MODELS:
            add("bad-intrinsics", where, f"camera_model {model!r} is not one of {CAMERA_MODELS}")
        if where == path.name:
            break
    return meta


def _validate_frames(root: Path, meta: dict, add) -> list[tuple[str, dict]]:
    """Checks each frame entry; returns (fid, entry) for entries whose image path and id are usable."""
    path = root / TRANSFORMS_FILE
    blender = "camera_angle_x" in meta and "fl_x" not in meta
    seen: dict[int, str] = {}
    out: list[tuple[str, dict]] = []
    for i, entry in enumerate(meta["frames"]):
        where = f"{path.name} frames[{i}]"
        if not isinstance(entry, dict) or "file_path" not in entry:
            add("bad-frame", where, "frame entry has no file_path")
            continue
        fp = str(entry["file_path"])
        fp = _resolve_blender_path(root, fp) if blender else (fp[2:] if fp.startswith("./") else fp)
        entry = {**entry, "file_path": fp}
        norm = os.path.normpath(fp)
        if Path(fp).is_absolute() or os.path.isabs(norm) or norm == ".." or norm.startswith(".." + os.sep):
            add("bad-file-path", where, f"file_path {fp!r} leaves the dataset folder: paths must be relative to it "
                f"(e.g. images/frame_00042.png)")
            continue
        fid = frame_id(fp)
        if not fid.isdigit():
            add("bad-frame-id", where, f"frame id '{fid}' of {fp} is not a number (name frames like frame_00042.png)")
            continue
        if int(fid) in seen:
            add("duplicate-frame-id", where, f"frame id {fid} of {fp} is also used by {seen[int(fid)]}")
            continue
        seen[int(fid)] = fp
        if "transform_matrix" not in entry:
            add("bad-pose", where, "no transform_matrix")
            continue
        try:
            m = _matrix(entry["transform_matrix"])
        except (TypeError, ValueError) as exc:
            add("bad-pose", where, f"transform_matrix unreadable: {exc}")
            continue
        if not np.all(np.isfinite(m)):
            add("bad-pose", where, "transform_matrix has non-finite values")
            continue
        r = m[:3, :3]
        orth = float(np.abs(r.T @ r - np.eye(3)).max())
        det = float(np.linalg.det(r))
        if orth > 1e-3 or abs(det - 1) > 1e-3:
            add("bad-rotation", where, f"rotation is not orthonormal with det +1 (max |RtR-I|={orth:.2e}, det={det:.4f})")
            continue
        if not np.allclose(m[3], [0, 0, 0, 1]):
            add("bad-pose", where, f"last row is {m[3].tolist()}, expected [0, 0, 0, 1]")
            continue
        out.append((fid, entry))
    return out


def _read_checked_yaml(path: Path, add, missing_code: str, missing_hint: str) -> tuple[bool, Any]:
    """(readable, content) of a dataset YAML file; a missing or unparsable file is reported through `add`."""
    if not path.exists():
        add(missing_code, path, f"missing: {missing_hint}")
        return False, None
    try:
        return True, read_yaml(path)
    except (OSError, yaml.YAMLError, UnicodeDecodeError) as exc:
        add("bad-yaml", path, f"not valid YAML: {exc}")
        return False, None


def _validate_mapping(root: Path, add) -> dict[int, str]:
    path = root / MAPPING_FILE
    ok, raw = _read_checked_yaml(path, add, "no-mapping",
                                 "name the objects with `interreal label DS --add-object NAME` or `interreal masks`")
    if not ok:
        return {}
    if not isinstance(raw, dict) or not raw:
        add("bad-mapping", path, "expected a non-empty mapping {0: 'name', 1: 'name', ...}")
        return {}
    mapping: dict[int, str] = {}
    for k, v in raw.items():
        if not isinstance(k, int) or isinstance(k, bool):
            add("bad-mapping", path, f"object id {k!r} is not an integer")
            continue
        if not isinstance(v, str) or not v.strip():
            add("bad-mapping", path, f"object {k} has no name")
            continue
        mapping[k] = v
    if mapping and sorted(mapping) != list(range(len(mapping))):
        add("bad-mapping", path, f"object ids {sorted(mapping)} are not contiguous from 0")
    names = list(mapping.values())
    dups = sorted({n for n in names if names.count(n) > 1})
    if dups:
        add("bad-mapping", path, f"names used twice: {dups}")
    return mapping


def _validate_labels(root: Path, mapping: dict[int, str], frames: list[tuple[str, dict]], add) -> dict:
    path = root / LABELS_FILE
    ok, raw = _read_checked_yaml(path, add, "no-labels", "set keyframe states with `interreal label DS --set NAME FRAME VALUE`")
    if not ok:
        return {}
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        add("bad-labels", path, "expected {frame_00042: {object name: value}}")
        return {}
    names = set(mapping.values())
    frame_numbers = {int(fid) for fid, _ in frames}
    good: dict[str, dict[str, float]] = {}
    for key, entry in raw.items():
        where = f"{path.name}[{key}]"
        try:
            idx = frame_index(str(key))
        except ValueError:
            add("bad-labels", where, "key does not end in a frame number (use frame_00042)")
            continue
        if frames and idx not in frame_numbers:
            add("label-unknown-frame", where, f"frame {idx} is not in transforms.json")
        if not isinstance(entry, dict):
            add("bad-labels", where, "expected {object name: value}")
            continue
        for name, value in entry.items():
            if mapping and name not in names:
                add("label-unknown-object", where, f"object {name!r} is not in mapping.yaml ({sorted(names)})")
                continue
            why = label_value_problem(value)
            if why is not None:
                add("label-bad-value", where, f"{name}: {why} (states are numbers in [0, 1]; fix it with "
                    f"`interreal label DS --set {name!r} {key} VALUE` or --unset)")
                continue
            good.setdefault(str(key), {})[str(name)] = float(value)
    return good


# fewer state labels than these leave a part's states unpinned (bench_train label sweep: state MAE 0.15 at 5 % labels
# vs 0.057 at 10 %); `validate` warns on all frames, `livescene train` on its training frames, with the same figures
MIN_LABELS = 3
MIN_LABEL_FRACTION = 0.08


def label_shortage(labelled: dict[str, int], n_frames: int) -> list[tuple[str, str]]:
    """(object, message) for each object whose labelled frames (of n_frames) are too few to pin its states down."""
    n = max(n_frames, 1)
    return [(name, f"'{name}' has state labels on only {k} of {n} frames ({k / n:.0%}): its states on the other "
                   f"frames may be wrong; label about 10 % of the frames (`interreal label DS --set '{name}' FRAME "
                   f"VALUE`)")
            for name, k in labelled.items() if k < MIN_LABELS or k / n < MIN_LABEL_FRACTION]


def _labels_per_object(labels: dict, mapping: dict[int, str]) -> dict[str, int]:
    counts = {mapping[i]: 0 for i in sorted(mapping)}
    for entry in labels.values():
        for name in entry:
            if name in counts:
                counts[name] += 1
    return counts


def _image_size(path: Path, decode: bool = True) -> tuple[int, int] | None:
    """(w, h), or None when the file is not a whole image. `decode`: decode every pixel (sure, ~15 ms a frame);
    else the header and the format's end marker (a truncated PNG / JPEG lacks it; ~0.3 ms a frame)."""
    try:
        from PIL import Image

        with Image.open(path) as im:
            if decode:
                im.load()
            size, fmt = im.size, im.format
    except Exception:  # noqa: BLE001 - any decoder failure is a listed problem, never a crash
        return None
    if not decode and fmt in ("PNG", "JPEG"):
        try:
            with open(path, "rb") as fh:
                fh.seek(max(0, path.stat().st_size - 64))
                tail = fh.read()
        except OSError:
            return None
        if (b"IEND" if fmt == "PNG" else b"\xff\xd9") not in tail:
            return None
    return size


def _validate_images(root: Path, frames: list[tuple[str, dict]], meta: dict | None, add,
                     decode: bool = True) -> dict[str, tuple[int, int]]:
    sizes: dict[str, tuple[int, int]] = {}
    for fid, entry in frames:
        path = root / entry["file_path"]
        if not path.exists():
            add("missing-image", path, "image listed in transforms.json does not exist")
            continue
        size = _image_size(path, decode)
        if size is None:
            add("bad-image", path, "not a readable image (truncated or not an image file)")
            continue
        sizes[fid] = size
        merged = {**(meta or {}), **entry}
        if "w" in merged and "h" in merged:
            try:
                if (int(merged["w"]), int(merged["h"])) != size:
                    add("image-size", path, f"image is {size[0]}x{size[1]} but transforms.json says {merged['w']}x{merged['h']}")
            except (TypeError, ValueError):
                pass
    if len(set(sizes.values())) > 1:
        add("mixed-sizes", root / IMAGES_DIR, f"images have different sizes: {sorted(set(sizes.values()))}")
    return sizes


def npy_header(path: Path) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) of a .npy file from its header alone (ValueError when it is not a .npy file)."""
    with open(path, "rb") as fh:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
        else:
            raise ValueError(f"unsupported .npy version {version}")
        need = int(np.prod(shape)) * dtype.itemsize
        have = os.fstat(fh.fileno()).st_size - fh.tell()
    if have < need:
        raise ValueError(f"truncated: {have} of {need} data bytes")
    return tuple(shape), dtype


def _validate_masks(root: Path, frames, mapping: dict[int, str], sizes: dict[str, tuple[int, int]], add,
                    pixels: bool = True) -> None:
    """Each mask's header (shape, dtype, channels: fast) and, with `pixels`, that every pixel has one channel."""
    if not frames:
        return
    n_channels = len(mapping) + 1 if mapping else None
    for fid, entry in frames:
        path = mask_file(root, fid)
        if not path.exists():
            add("missing-mask", path, f"no mask for {entry['file_path']} (run `interreal masks DS --keyframes DIR`)")
            continue
        try:
            shape, dtype = npy_header(path)
        except (OSError, ValueError) as exc:
            add("bad-mask", path, f"unreadable .npy: {exc}; re-run `interreal masks`")
            continue
        if len(shape) != 3:
            add("bad-mask", path, f"{len(shape)}-D array of shape {shape}: expected (H, W, objects + 1) with one "
                "channel per object and the background last; re-run `interreal masks`")
            continue
        if dtype != np.dtype(bool):
            add("bad-mask", path, f"stored as {dtype}, not bool: a mask is true/false per channel (a float 0.5 would "
                "read as true everywhere); re-run `interreal masks`")
            continue
        if fid in sizes and (shape[1], shape[0]) != sizes[fid]:
            add("mask-size", path, f"mask is {shape[1]}x{shape[0]}, image is {sizes[fid][0]}x{sizes[fid][1]}")
            continue
        if n_channels is not None and shape[2] != n_channels:
            add("mask-channels", path, f"{shape[2]} channels, expected {n_channels} ({len(mapping)} objects + "
                "background last): the object list changed after the masks were made; re-run `interreal masks`")
            continue
        if not pixels:
            continue
        try:
            m = np.load(path, allow_pickle=False)
        except Exception as exc:  # noqa: BLE001 - truncated/garbage .npy is a listed problem
            add("bad-mask", path, f"unreadable .npy: {exc}; re-run `interreal masks`")
            continue
        count = m.sum(axis=2)
        bad = int((count != 1).sum())
        if bad:
            ys, xs = np.nonzero(count != 1)
            add("mask-not-onehot", path, f"{bad} pixels do not have exactly one channel set (first at x={xs[0]}, y={ys[0]})")


def _validate_articulation(root: Path, mapping: dict[int, str], add) -> list[str]:
    """Objects with a motion in the optional `articulation.json` (each must name an object of mapping.yaml)."""
    if not (root / ARTICULATION_FILE).exists():
        return []
    try:
        motions = read_articulation(root)
    except DatasetError as exc:
        add("bad-articulation", root / ARTICULATION_FILE, str(exc))
        return []
    names = set(mapping.values())
    for name in motions:
        if mapping and name not in names:
            add("bad-articulation", root / ARTICULATION_FILE, f"object {name!r} is not in mapping.yaml ({sorted(names)})")
    return [n for n in motions if n in names]


def _validate_reports(root: Path, add) -> None:
    folder = root / REPORTS_DIR
    if not folder.is_dir():
        return
    for path in sorted(folder.glob("*.json")):
        try:
            rep = json.loads(path.read_text())
        except (OSError, ValueError, UnicodeDecodeError):
            add("bad-report", path, "not valid JSON")
            continue
        status = rep.get("status") if isinstance(rep, dict) else None
        if not isinstance(rep, dict) or status not in ("running", "failed", "ok"):
            add("bad-report", path, f"no valid status ({status!r}): the stage's report is damaged; re-run the stage")
            continue
        if status in ("running", "failed"):
            add("stage-incomplete", path, f"stage '{rep.get('stage', path.stem)}' is {status}: "
                f"{rep.get('error', 'it did not finish')}; re-run it")


def _validate_provenance(root: Path, add) -> None:
    """Stages whose inputs changed since they ran (frames from another video, masks propagated again, ...)."""
    from .provenance import stale_stages

    try:
        stale = stale_stages(root)
    except OSError as exc:
        add("stale", root / REPORTS_DIR, f"cannot compare the stages' inputs ({exc})")
        return
    for s in stale:
        add("stale", root / REPORTS_DIR / f"{s.stage}.json", s.message.removeprefix("stale: "))


def format_summary(result: ValidationResult) -> str:
    s = result.summary
    lines = [f"LiveScene dataset {s['root']}: OK",
             f"  frames   {s.get('frames', 0)}  (poses: {s.get('poses', 0)}, masks: {'yes' if s.get('masks') else 'no'})",
             f"  size     {', '.join(s.get('size', [])) or '?'}",
             f"  objects  {len(s.get('objects', []))}"]
    for name, n in s.get("labels_per_object", {}).items():
        lines.append(f"    - {name}: {n} labelled frames")
    return "\n".join(lines)


def format_problems(result: ValidationResult, per_kind: int = 0) -> str:
    """Every problem (or the first `per_kind` of each kind), after a count per kind."""
    counts: dict[str, int] = {}
    for p in result.problems:
        counts[p.kind] = counts.get(p.kind, 0) + 1
    lines = [f"{result.root}: {len(result.problems)} problem(s): "
             + ", ".join(f"{n} {k}" for k, n in counts.items())]
    shown: dict[str, int] = {}
    for p in result.problems:
        shown[p.kind] = shown.get(p.kind, 0) + 1
        if per_kind and shown[p.kind] > per_kind:
            if shown[p.kind] == per_kind + 1:
                lines.append(f"  ... and {counts[p.kind] - per_kind} more [{p.kind}] (without --brief: all of them)")
            continue
        lines.append(f"  {p}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------------------------
# CLI: interreal validate
# ----------------------------------------------------------------------------------------------------------------
def add_arguments(p) -> None:
    p.add_argument("dataset", type=Path, help="dataset folder")
    p.add_argument("--no-masks", action="store_true",
                   help="quick mode: image and mask headers only, no per-pixel decoding (what livescene runs)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--brief", action="store_true", help="list only the first 10 problems of each kind")
    p.epilog = ("examples:\n  interreal validate out/room\n  interreal validate out/room --brief\n"
                "  interreal validate out/room --json | jq .problems")


def main(args) -> int:
    result = validate(args.dataset, check_masks=not args.no_masks)
    if args.json:
        print(json.dumps({"ok": result.ok, "summary": result.summary, "warnings": result.warnings,
                          "problems": [p.__dict__ for p in result.problems]}, indent=2))
    else:
        print(format_summary(result) if result.ok else format_problems(result, per_kind=10 if args.brief else 0))
        for w in result.warnings:  # a warning, not a problem: the dataset is usable, its exit status stays 0
            print(f"  warning: {w}")
    return 0 if result.ok else 1
