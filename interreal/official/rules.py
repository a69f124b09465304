"""The official LiveScene reader's rules (dataparser + `atrb_utils.read_attributes`), re-implemented to check a folder.

Frame order and split as nerfstudio / the Blender parser make them, labels zero-filled and min-max normalised per
object over each split, one mask per frame at the image size, exactly one-hot (see the package doc).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from PIL import Image

from ..conventions import LABELS_FILE, MAPPING_FILE, MASKS_DIR, TRANSFORMS_FILE, frame_id
from ..dataset import npy_header
from ..dataset.official import is_blender, label_columns, label_key_index
from ..errors import DatasetError

TRAIN_FRACTION = 0.9  # nerfstudio's default train_split_fraction (real data)
EVAL_INTERVAL = 2  # the Blender parser's eval_interval (synthetic data): eval = even positions
MAX_AUTO_RESOLUTION = 1600  # nerfstudio looks for images_<2^k>/ above this many pixels per side
SPLIT_KEYS = ("train_filenames", "val_filenames", "test_filenames")
TOL = 1e-6




def official_frames(meta: dict[str, Any]) -> list[dict[str, Any]]:
    """transforms.json frames in the order the official parser indexes them: sorted by file path (nerfstudio),
    as listed (Blender)."""
    frames = [f for f in meta.get("frames", []) if isinstance(f, dict) and "file_path" in f]
    return frames if is_blender(meta) else sorted(frames, key=lambda f: str(f["file_path"]))


def fraction_split(n: int, fraction: float = TRAIN_FRACTION) -> tuple[list[int], list[int]]:
    """nerfstudio's `get_train_eval_split_fraction`: (train, eval) positions."""
    n_train = math.ceil(n * fraction)
    train = np.linspace(0, n - 1, n_train, dtype=int) if n else np.zeros(0, int)
    return sorted(set(train.tolist())), sorted(set(range(n)) - set(train.tolist()))


def interval_split(n: int, interval: int = EVAL_INTERVAL) -> tuple[list[int], list[int]]:
    """The Blender parser's interval split: eval = positions divisible by `interval`, train = the others."""
    held = [i for i in range(n) if i % interval == 0]
    return [i for i in range(n) if i % interval], held


def _norm_path(p: str) -> str:
    return p[2:] if p.startswith("./") else p


def official_split(meta: dict[str, Any]) -> tuple[list[int], list[int], str]:
    """(train, eval, how) positions in `official_frames(meta)` order. Eval is the `test` split (`ns-eval`); with
    explicit lists, `test_filenames` (else `val_filenames`)."""
    frames = official_frames(meta)
    n = len(frames)
    if is_blender(meta):
        tr, ev = interval_split(n)
        return tr, ev, "interval (synthetic): eval = even positions, train = odd"
    if any(k in meta for k in SPLIT_KEYS):
        paths = [_norm_path(str(f["file_path"])) for f in frames]
        def pick(key: str) -> list[int]:
            names = {_norm_path(str(x)) for x in meta.get(key) or []}
            unknown = names - set(paths)
            if unknown:
                raise DatasetError(f"{TRANSFORMS_FILE} {key} names {len(unknown)} file(s) that are not frames, e.g. "
                                   f"{sorted(unknown)[0]} (nerfstudio stops on it)")
            return [i for i, p in enumerate(paths) if p in names]
        ev_key = "test_filenames" if "test_filenames" in meta else "val_filenames"
        return pick("train_filenames"), pick(ev_key), f"explicit train_filenames / {ev_key}"
    tr, ev = fraction_split(n)
    return tr, ev, f"fraction {TRAIN_FRACTION} of the frames sorted by file path"






def minmax_columns(values: np.ndarray) -> np.ndarray:
    """Per-column min-max over all rows, zeros included, as the official reader normalises a split (NaN where a
    column is constant: 0 / 0)."""
    lo, hi = values.min(axis=0), values.max(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (values - lo) / (hi - lo)


@dataclass
class OfficialCheck:
    """What the official reader would make of a folder: problems (any one breaks or silently changes training)."""

    root: Path
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    split: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.problems


def _read_yaml(path: Path, what: str) -> Any:
    if not path.exists():
        raise DatasetError(f"{path} is missing: the official reader needs {what}")
    try:
        return yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path} is not valid YAML ({' '.join(str(exc).split())[:120]})") from None


def read_meta(root: Path) -> dict[str, Any]:
    path = root / TRANSFORMS_FILE
    try:
        meta = json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(f"{path} is missing: not a dataset folder") from None
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path} is not valid JSON ({exc})") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise DatasetError(f"{path} has no 'frames' list")
    return meta


def _image_size(path: Path) -> tuple[int, int] | None:
    try:
        with Image.open(path) as im:
            return im.size
    except Exception:  # noqa: BLE001 - reported as a problem by the caller
        return None


def _image_path(root: Path, meta: dict[str, Any], entry: dict[str, Any]) -> Path:
    rel = _norm_path(str(entry["file_path"]))
    return root / (rel + ".png" if is_blender(meta) and not Path(rel).suffix else rel)


def check_official(root: str | Path) -> OfficialCheck:
    """Run the official reader's rules (module doc) on a folder; DatasetError only when it has no readable
    transforms.json / mapping.yaml / key_frame_value.yaml."""
    root = Path(root)
    res = OfficialCheck(root)
    meta = read_meta(root)
    mapping = _read_yaml(root / MAPPING_FILE, "{object id: name}") or {}
    labels = _read_yaml(root / LABELS_FILE, "{frame key: {object name: value}}") or {}
    if not isinstance(mapping, dict) or not mapping:
        raise DatasetError(f"{root / MAPPING_FILE}: expected a non-empty mapping {{0: name, ...}}")
    if not isinstance(labels, dict):
        raise DatasetError(f"{root / LABELS_FILE}: expected {{frame key: {{object name: value}}}}")
    ids = sorted(mapping)
    if ids != list(range(len(ids))):
        res.problems.append(f"mapping.yaml ids {ids} are not 0..{len(ids) - 1}: the id is the mask channel")
    names = [str(mapping[i]) for i in ids]
    frames = official_frames(meta)
    fids = [frame_id(str(f["file_path"])) for f in frames]
    bad = [f for f in fids if not f.isdigit()]
    if bad:
        res.problems.append(f"frame id '{bad[0]}' (last '_' token of the image name) is not a number")
        return res
    if max(int(f) for f in fids) == 0:
        res.problems.append("every frame id is 0: the official time id = fid / max fid divides by 0")
    _check_label_keys(labels, names, res)
    try:
        train, ev, how = official_split(meta)
    except DatasetError as exc:
        res.problems.append(str(exc))
        return res
    res.split = {"how": how, "train": len(train), "eval": len(ev)}
    _check_masks(root, meta, frames, fids, len(names), res)
    for split, pos in (("train", train), ("eval", ev)):
        if not pos:
            res.problems.append(f"the {split} split is empty ({len(frames)} frames, {how})")
            continue
        _check_split_labels(split, [fids[i] for i in pos], labels, names, res)
    for folder in sorted(root.glob("images_*")):
        res.problems.append(f"{folder.name}/ exists: nerfstudio may load those downscaled images while the masks "
                            f"stay at full size; remove it")
    return res


def _check_label_keys(labels: dict, names: list[str], res: OfficialCheck) -> None:
    for key, entry in labels.items():
        try:
            label_key_index(key)
        except ValueError:
            res.problems.append(f"key_frame_value.yaml key {key!r} does not end in a frame number")
            continue
        for name, value in (entry or {}).items():
            if name not in names:
                res.problems.append(f"key_frame_value.yaml[{key}] names {name!r}, not in mapping.yaml (KeyError)")
            elif isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
                res.problems.append(f"key_frame_value.yaml[{key}][{name}] = {value!r} is not a finite number")


def _check_split_labels(split: str, fids: list[str], labels: dict, names: list[str], res: OfficialCheck) -> None:
    try:
        values, given = label_columns(fids, labels, names)
    except (TypeError, ValueError):
        return  # named by _check_label_keys
    norm = minmax_columns(values)
    for j, name in enumerate(names):
        col = norm[:, j]
        if not np.isfinite(col).all():
            res.problems.append(f"{split} split: '{name}' reads {values[0, j]:g} on all its {len(fids)} frames "
                                f"(unlabelled ones count as 0), so the official normalisation gives NaN (0 / 0): "
                                f"it needs a non-zero label there")
            continue
        changed = given[:, j] & (np.abs(col - values[:, j]) > TOL)
        if changed.any():
            i = int(np.argmax(changed))
            res.problems.append(f"{split} split: '{name}' labels span [{values[:, j].min():g}, "
                                f"{values[:, j].max():g}] (unlabelled frames count as 0), so the official "
                                f"normalisation rescales them: {values[i, j]:g} on frame {fids[i]} reads as "
                                f"{col[i]:.4g} ({int(changed.sum())} label(s) changed)")


def _check_masks(root: Path, meta: dict, frames: list[dict], fids: list[str], n_objects: int,
                 res: OfficialCheck) -> None:

    problems: list[str] = []
    for entry, fid in zip(frames, fids):
        path = root / MASKS_DIR / f"{fid}.npy"
        size = _image_size(_image_path(root, meta, entry))
        if size is None:
            problems.append(f"{entry['file_path']}: image missing or unreadable")
            continue
        if max(size) > MAX_AUTO_RESOLUTION:
            res.notes.append(f"images are {size[0]}x{size[1]} (> {MAX_AUTO_RESOLUTION} px): load them at full size "
                             f"(no images_<n>/ folder), so the masks match")
        if not path.exists():
            problems.append(f"{path.relative_to(root)} is missing (np.load fails for frame {fid})")
            continue
        try:
            shape, _ = npy_header(path)
        except (OSError, ValueError) as exc:
            problems.append(f"{path.relative_to(root)}: unreadable ({exc})")
            continue
        want = (size[1], size[0], n_objects + 1)
        if tuple(shape) != want:
            problems.append(f"{path.relative_to(root)} has shape {tuple(shape)}, the image needs {want} "
                            f"(H, W, objects + background)")
            continue
        m = np.load(path, allow_pickle=False)
        count = (m != 0).sum(axis=2)
        if (count != 1).any():
            problems.append(f"{path.relative_to(root)}: {int((count != 1).sum())} pixels do not have exactly one "
                            f"channel set (the official mask loss indexes one channel per pixel)")
    res.problems += problems[:10] + ([f"... and {len(problems) - 10} more mask problems"] if len(problems) > 10 else [])
    res.notes[:] = sorted(set(res.notes))


def official_positions(layout: str, extra: dict[str, Any], file_paths: list[str]) -> tuple[list[int], list[int]]:
    """(train, eval) positions, in the loaded order of `file_paths`, of the official split (`official_split`) of a
    dataset with this layout and these other transforms.json keys (explicit split lists)."""
    meta: dict[str, Any] = {**extra, "frames": [{"file_path": p} for p in file_paths]}
    if layout == "blender":
        meta["camera_angle_x"] = 1.0
    tr, ev, _ = official_split(meta)
    loaded = {_norm_path(p): i for i, p in enumerate(file_paths)}
    order = [loaded[_norm_path(str(f["file_path"]))] for f in official_frames(meta)]
    return sorted(order[i] for i in tr), sorted(order[i] for i in ev)
