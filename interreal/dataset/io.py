"""Readers and writers of the dataset files (transforms.json in our / InterReal / OmniSim layouts, mapping, labels,
prompts, articulation, masks). Writes are atomic."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import yaml

from .. import atomic
from ..conventions import frame_index, mask_file
from ..errors import DatasetError
from ..layout import ARTICULATION_FILE, LABELS_FILE, MAPPING_FILE, PLY_FILE, PROMPTS_FILE, TRANSFORMS_FILE
from ..images import IMAGE_SUFFIXES, read_image_rgb
from .official import is_official_data, normalise_raw_labels, raw_value_ok
from .types import DISTORTION_KEYS, INTRINSIC_KEYS, Articulation, Frame, Intrinsics, LiveSceneDataset


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

    official = is_official_data(root)  # raw values outside [0, 1]: load_dataset normalises them the official way
    for key, entry in read_labels_raw(root).items():
        if not isinstance(entry, dict):
            raise DatasetError(f"{path}: entry {key}: expected {{object name: value}}, got {entry!r}; fix it with "
                               f"`interreal label {Path(root)} --set OBJECT {key} VALUE` or by hand")
        for name, value in entry.items():
            why = label_value_problem(value)
            if why is not None and not (official and raw_value_ok(value)):
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


SAME_STATE = 0.02  # two labels this close name one state: the part rests between them


def known_states(times: np.ndarray, labels: np.ndarray, given: np.ndarray, tol: float = SAME_STATE
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


def pose_matrix(value: Any) -> np.ndarray:
    m = np.asarray(value, dtype=np.float64)
    if m.shape == (3, 4):
        m = np.vstack([m, [0, 0, 0, 1]])
    if m.shape != (4, 4):
        raise ValueError(f"transform_matrix has shape {m.shape}, expected 4x4")
    return m


def resolve_blender_path(root: Path, file_path: str) -> str:
    rel = file_path[2:] if file_path.startswith("./") else file_path
    if Path(rel).suffix.lower() in IMAGE_SUFFIXES:
        return rel
    for suf in (".png", ".jpg", ".jpeg"):
        if (root / (rel + suf)).exists():
            return rel + suf
    return rel + ".png"


def transforms_layout(meta: dict[str, Any]) -> str:
    """"blender" (OmniSim: `camera_angle_x`, file paths without extension) or "nerfstudio"."""
    return "blender" if "camera_angle_x" in meta and "fl_x" not in meta else "nerfstudio"


def camera_angle_intrinsics(angle_x: float, w: int, h: int, camera_model: str = "PINHOLE") -> Intrinsics:
    """The centred pinhole camera a Blender-style `camera_angle_x` describes at image size w x h."""
    f = 0.5 * w / math.tan(0.5 * float(angle_x))
    return Intrinsics(w=w, h=h, fl_x=f, fl_y=f, cx=w / 2, cy=h / 2, camera_model=camera_model)


def parse_transforms(meta: dict[str, Any], root: Path | None = None
                     ) -> tuple[Intrinsics | None, list[Frame], str, dict[str, Any]]:
    """The one transforms.json parser (a dataset's own, or a nerfstudio / Polycam file to import): (shared
    intrinsics, frames, layout, other top-level keys). A frame without `transform_matrix` gets c2w None; per-frame
    intrinsics where the entry has its own camera keys. Blender layout: shared intrinsics None (they need the image
    size, `camera_angle_intrinsics`), and with `root` the extension-less file paths resolved against it."""
    layout = transforms_layout(meta)
    intr = Intrinsics.from_json(meta) if layout == "nerfstudio" and all(
        k in meta for k in ("fl_x", "cx", "cy", "w", "h")) else None
    frames: list[Frame] = []
    for entry in meta["frames"]:
        fp = str(entry["file_path"])
        if layout == "blender" and root is not None:
            fp = resolve_blender_path(root, fp)
        elif fp.startswith("./"):
            fp = fp[2:]
        merged = {**meta, **entry}
        own = any(k in entry for k in INTRINSIC_KEYS) and all(k in merged for k in ("fl_x", "cx", "cy", "w", "h"))
        fr_intr = Intrinsics.from_json(merged) if own else None
        c2w = pose_matrix(entry["transform_matrix"]) if "transform_matrix" in entry else None
        extra = {k: v for k, v in entry.items() if k not in ("file_path", "transform_matrix")}
        frames.append(Frame(file_path=fp, c2w=c2w, intrinsics=fr_intr, extra=extra))
    keys = set(INTRINSIC_KEYS + DISTORTION_KEYS + ("frames", "camera_model", "camera_angle_x"))
    return intr, frames, layout, {k: v for k, v in meta.items() if k not in keys}


def read_transforms_file(path: Path, name: str, error: type[Exception], json_hint: str = "",
                         frames_hint: str = "") -> dict[str, Any]:
    """The JSON object of a transforms.json file with its 'frames' list; `error` naming the file as `name` (and the
    hint) when it is not valid JSON or has no such list."""
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise error(f"{name} is not valid JSON ({exc}){json_hint}") from exc
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise error(f"{name} has no 'frames' list{frames_hint}")
    return meta


def load_transforms(root: str | Path) -> tuple[Intrinsics | None, list[Frame], str, dict[str, Any]]:
    """Parse a dataset's transforms.json in either layout; returns (shared intrinsics, frames, layout, other keys)."""
    root = Path(root)
    path = root / TRANSFORMS_FILE
    if not path.exists():
        raise DatasetError(f"{path} is missing: run `interreal poses {root}` (or `interreal process`) first")
    meta = read_transforms_file(path, str(path), DatasetError, json_hint="; re-run `interreal poses`")
    intr, frames, layout, extra = parse_transforms(meta, root)
    unposed = [f.file_path for f in frames if f.c2w is None]
    if unposed:
        raise DatasetError(f"{path}: {len(unposed)} frames have no transform_matrix (e.g. {unposed[0]}); "
                           "re-run `interreal poses`")
    if layout == "blender":
        if not frames:
            raise DatasetError(f"{path} has no frames")
        h, w = read_image_rgb(root / frames[0].file_path).shape[:2]
        intr = camera_angle_intrinsics(meta["camera_angle_x"], w, h)
    return intr, frames, layout, extra


def point_cloud_path(root: str | Path, extra: dict[str, Any] | None = None) -> Path:
    """The SfM point cloud of a dataset: transforms.json's `ply_file_path` (nerfstudio's key) when it names a file
    inside the dataset, else `sparse_pc.ply`. `extra`: the top-level keys `load_transforms` returns."""
    root = Path(root)
    rel = (extra or {}).get("ply_file_path")
    if isinstance(rel, str) and rel.strip():
        norm = os.path.normpath(rel.removeprefix("./"))
        if not os.path.isabs(norm) and norm != ".." and not norm.startswith(".." + os.sep):
            return root / norm
    return root / PLY_FILE


def read_point_cloud(root: str | Path, extra: dict[str, Any] | None = None) -> np.ndarray | None:
    """(P, 3) finite points of the dataset's point cloud (`point_cloud_path`); None when it is missing or not a
    readable PLY (a point cloud is optional: it only improves the scene box)."""
    path = point_cloud_path(root, extra)
    if not path.is_file():
        return None
    import trimesh  # 1.2 s to import: only when a point cloud is read

    try:
        pc = trimesh.load(str(path), file_type="ply")
        pts = np.asarray(getattr(pc, "vertices", []), dtype=np.float64).reshape(-1, 3)
    except Exception:  # noqa: BLE001 - any parser failure means "no usable point cloud"
        return None
    return pts[np.isfinite(pts).all(axis=1)]  # a NaN point would make a box NaN


def load_dataset(root: str | Path) -> LiveSceneDataset:
    """Load a dataset folder (our layout, InterReal or OmniSim). Frames are sorted by file path, as nerfstudio does."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root} is not a folder")
    intr, frames, layout, extra = load_transforms(root)
    if layout == "nerfstudio":
        frames.sort(key=lambda f: f.file_path)
    mapping, labels = read_mapping(root), read_labels(root)

    if is_official_data(root):  # raw values outside [0, 1] -> the official normalisation, with a note
        labels = normalise_raw_labels(root, labels, [f.file_path for f in frames], [mapping[i] for i in sorted(mapping)])
    return LiveSceneDataset(
        root=root, frames=frames, intrinsics=intr, mapping=mapping, labels=labels,
        prompts=read_prompts(root), layout=layout, extra=extra, articulation=read_articulation(root),
    )


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
