"""The dataset-wide edit lock, the dataset's frames as label keys, and its objects (`mapping.yaml`): add, rename."""

from __future__ import annotations

import json
import os
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows: the thread lock is all we have
    fcntl = None  # type: ignore[assignment]

from .. import atomic, provenance
from ..conventions import ARTICULATION_FILE, IMAGES_DIR, MAPPING_FILE, frame_index, object_name_problem
from ..dataset import (list_images, load_transforms, read_labels_raw, read_mapping, read_prompts, write_labels,
                       write_mapping, write_prompts)
from ..errors import DatasetError, InputError
from ..layout import KEYFRAMES_DIR, LOCK_FILE
from ..provenance import MOTION_INPUTS



# ----------------------------------------------------------------------------------------------------------------
# Dataset state
# ----------------------------------------------------------------------------------------------------------------
_thread_lock = threading.RLock()
_held = threading.local()


@contextmanager
def edit_lock(ds: str | Path) -> Iterator[None]:
    """Serialise read-modify-write cycles on one dataset across threads and processes (CLI + web app).

    Re-entrant within a thread, so an edit may call other edits while holding it.
    """
    ds = Path(ds)
    with _thread_lock:
        depth = getattr(_held, "depth", 0)
        if depth:
            _held.depth = depth + 1
            try:
                yield
            finally:
                _held.depth = depth
            return
        ds.mkdir(parents=True, exist_ok=True)
        fd = os.open(ds / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            if fcntl is not None:
                fcntl.flock(fd, fcntl.LOCK_EX)
            _held.depth = 1
            yield
        finally:
            _held.depth = 0
            if fcntl is not None:
                fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)


def dataset_frames(ds: str | Path) -> dict[int, str]:
    """Frame number -> label key (image stem) for the frames of DS/images (else those in transforms.json)."""
    ds = Path(ds)
    paths = list_images(ds / IMAGES_DIR)
    if not paths and (ds / "transforms.json").exists():
        _, frames, _, _ = load_transforms(ds)
        paths = [Path(f.file_path) for f in frames]
    out: dict[int, str] = {}
    for p in paths:
        try:
            out[frame_index(p)] = p.stem
        except ValueError:
            continue
    if not out:
        raise InputError(f"{ds}: no frames in {ds / IMAGES_DIR}: run `interreal frames INPUT {ds}` first")
    return dict(sorted(out.items()))


def resolve_frame(frames: dict[int, str], frame: Any, where: str = "frame") -> str:
    """'42', 42, '00042', 'frame_00042' or 'frame_00042.png' -> the label key of a frame of the dataset."""
    text = str(frame).strip()
    try:
        idx = int(text) if text.lstrip("-").isdigit() else frame_index(text)
    except ValueError:
        raise InputError(f"{where}: {frame!r} is not a frame (use its number, e.g. 42, or frame_00042)") from None
    if idx not in frames:
        near = sorted(frames, key=lambda i: abs(i - idx))[:3]
        raise InputError(f"{where}: frame {idx} is not among the dataset's frames (nearest: "
                         f"{', '.join(frames[i] for i in sorted(near))}; list them with `ls DS/images`)")
    return frames[idx]


def read_objects(ds: str | Path) -> dict[int, str]:
    """The dataset's objects: mapping.yaml, else the keyframe folder's mapping.yaml, else none."""
    ds = Path(ds)
    mapping = read_mapping(ds)
    if not mapping and (ds / KEYFRAMES_DIR / MAPPING_FILE).exists():
        mapping = read_mapping(ds / KEYFRAMES_DIR)
    return mapping


def check_object_name(name: Any) -> str:
    problem = object_name_problem(name)
    if problem:
        raise InputError(problem)
    return str(name).strip()


def require_object(mapping: dict[int, str], name: str, where: str = "object") -> str:
    if name not in mapping.values():
        known = ", ".join(repr(n) for n in mapping.values()) or "none yet"
        raise InputError(f"{where}: unknown object {name!r} (objects: {known}); add it with --add-object {name!r}")
    return name


def write_objects(ds: Path, mapping: dict[int, str]) -> None:
    write_mapping(ds, mapping)
    if (ds / KEYFRAMES_DIR).is_dir():
        write_mapping(ds / KEYFRAMES_DIR, mapping)


# ----------------------------------------------------------------------------------------------------------------
# Public edits
# ----------------------------------------------------------------------------------------------------------------
def add_object(ds: str | Path, name: str, description: str | None = None) -> int:
    """Append an object to mapping.yaml (and keyframes/mapping.yaml); returns its id. Existing name: its id."""
    ds = Path(ds)
    name = check_object_name(name)
    with edit_lock(ds):
        mapping = read_objects(ds)
        for oid, existing in mapping.items():
            if existing == name:
                return oid
        oid = len(mapping)
        if sorted(mapping) != list(range(oid)):
            raise DatasetError(f"{ds / MAPPING_FILE}: object ids {sorted(mapping)} are not 0..{oid - 1}; fix the file first")
        mapping[oid] = name
        write_objects(ds, mapping)
        if description:
            prompts = read_prompts(ds)
            prompts[name] = str(description)
            write_prompts(ds, prompts)
        return oid


def rename_object(ds: str | Path, old: str, new: str) -> None:
    """Rename an object everywhere it is named: mapping.yaml, key_frame_value.yaml, keyframes/, prompts.yaml,
    articulation.json (a measured motion keeps its part, so it is not made stale by the new name).

    Idempotent, so a rename cut short by a crash is finished by running it again.
    """
    ds = Path(ds)
    new = check_object_name(new)
    with edit_lock(ds):
        mapping = read_objects(ds)
        if old == new:
            require_object(mapping, old)
            return
        if new in mapping.values():
            raise InputError(f"cannot rename {old!r} to {new!r}: an object called {new!r} exists already")
        require_object(mapping, old)
        masks_fresh = provenance.unchanged(ds, "masks", ["keyframes"])
        motions_fresh = provenance.unchanged(ds, "motions", MOTION_INPUTS)
        kf = ds / KEYFRAMES_DIR
        if kf.is_dir():
            for js in sorted(kf.glob("*.json")):
                _rename_in_labelme(js, old, new)
        if masks_fresh:  # a renamed object keeps its masks: the keyframes' new label text does not make them stale
            provenance.refresh(ds, "masks", ["keyframes"])
        labels = read_labels_raw(ds)
        if any(isinstance(entry, dict) and old in entry for entry in labels.values()):
            for entry in labels.values():
                if isinstance(entry, dict) and old in entry:
                    entry[new] = entry.pop(old)
            write_labels(ds, labels)
        prompts = read_prompts(ds)
        if old in prompts:
            write_prompts(ds, {(new if k == old else k): v for k, v in prompts.items()})
        write_objects(ds, {k: (new if v == old else v) for k, v in mapping.items()})
        _rename_in_articulation(ds, old, new)
        if motions_fresh:
            provenance.refresh(ds, "motions", MOTION_INPUTS)


def _rename_in_articulation(ds: Path, old: str, new: str) -> None:
    path = ds / ARTICULATION_FILE
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return  # absent, or damaged: `validate` names a damaged file
    objects = doc.get("objects") if isinstance(doc, dict) else None
    if isinstance(objects, dict) and old in objects:
        doc["objects"] = {(new if k == old else k): v for k, v in objects.items()}
        atomic.write_json(path, doc)


def _rename_in_labelme(path: Path, old: str, new: str) -> None:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return
    shapes = doc.get("shapes") if isinstance(doc, dict) else None
    if not isinstance(shapes, list):
        return
    changed = False
    for shape in shapes:
        if isinstance(shape, dict) and shape.get("label") == old:
            shape["label"] = new
            changed = True
    if changed:
        atomic.write_json(path, doc)
