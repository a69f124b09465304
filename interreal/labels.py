"""Keyframe state labels: `key_frame_value.yaml` and the object list `mapping.yaml`.

A label is an object's state on one frame, 0 = closed .. 1 = fully open. People measure states in physical
units ("the door is at 45 degrees", "the drawer is out 12 cm"), so values may be given with a unit and a range
(`--degrees 0:90`) and are normalised here. Every edit is validated first and written atomically under a
dataset-wide edit lock, so the CLI and the annotation app (`interreal.annotate`) can edit the same dataset
without losing each other's changes.
"""

from __future__ import annotations

import argparse
import csv
import difflib
import json
import math
import os
import sys
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator

import yaml

from . import atomic, provenance
from .conventions import ARTICULATION_FILE, IMAGES_DIR, LABELS_FILE, MAPPING_FILE, MASKS_DIR, frame_index
from .dataset import label_value_problem, list_images, load_transforms, read_labels_raw, read_mapping, read_prompts
from .dataset import npy_header, read_yaml, write_labels, write_mapping, write_prompts
from .errors import DatasetError, InputError
from .provenance import MOTION_INPUTS
from .report import StageReport, read_report

KEYFRAMES_DIR = "keyframes"  # where `interreal annotate` stores keyframe masks (the `--keyframes DIR` format)
LOCK_FILE = ".edit.lock"
FORBIDDEN_NAME_CHARS = ("=", "\n", "\r", "\t")
_TOL = 1e-9


# ----------------------------------------------------------------------------------------------------------------
# Units
# ----------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Unit:
    """A physical unit with the range that maps to states 0 .. 1 (lo may exceed hi: '90:0' = closed at 90)."""

    name: str  # "degrees" or "cm"
    lo: float
    hi: float

    def normalise(self, value: float) -> float:
        return (value - self.lo) / (self.hi - self.lo)

    def __str__(self) -> str:
        return f"{self.name} {self.lo:g}:{self.hi:g}"


UNIT_ALIASES = {
    "": None, "norm": None, "normalised": None, "normalized": None, "state": None, "0-1": None,
    "deg": "degrees", "degree": "degrees", "degrees": "degrees", "°": "degrees",
    "rad": "radians", "radian": "radians", "radians": "radians",
    "cm": "cm", "mm": "mm", "m": "m",
}
_TO_BASE = {"radians": ("degrees", 180.0 / math.pi), "mm": ("cm", 0.1), "m": ("cm", 100.0)}


def parse_range(text: str | tuple[float, float] | None, unit: str) -> Unit | None:
    """'0:90' (or a (lo, hi) pair) -> Unit; InputError naming the option when it does not parse."""
    if text is None:
        return None
    if isinstance(text, (tuple, list)):
        parts = [str(t) for t in text]
    else:
        parts = str(text).split(":")
    try:
        lo, hi = (float(p) for p in parts)
    except ValueError:
        raise InputError(f"--{unit} {text!r}: expected LO:HI, e.g. --{unit} 0:90") from None
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo == hi:
        raise InputError(f"--{unit} {text!r}: LO and HI must be finite and different")
    return Unit(unit, lo, hi)


def normalise_value(value: Any, unit: Unit | None = None, where: str = "value", row_unit: str | None = None,
                    units: dict[str, Unit] | None = None) -> float:
    """A state in [0, 1] from a raw value, optionally in a physical unit; InputError on NaN / out of range."""
    try:
        v = float(str(value).strip()) if not isinstance(value, (int, float)) else float(value)
    except ValueError:
        raise InputError(f"{where}: {value!r} is not a number") from None
    if not math.isfinite(v):
        raise InputError(f"{where}: {value!r} is not a finite number (NaN / inf cannot be a state)")
    if row_unit is not None:
        key = row_unit.strip().lower()
        if key not in UNIT_ALIASES:
            raise InputError(f"{where}: unknown unit {row_unit!r}; use one of deg, rad, cm, mm, m or leave it empty")
        base = UNIT_ALIASES[key]
        if base in _TO_BASE:
            base, factor = _TO_BASE[base]
            v *= factor
        if base is None:
            unit = None
        else:
            unit = (units or {}).get(base)
            if unit is None:
                raise InputError(f"{where}: the value is in {base}; give its range, e.g. --{base} 0:90")
    raw = v
    if unit is not None:
        v = unit.normalise(v)
    if -_TOL <= v <= 1 + _TOL:
        return min(max(v, 0.0), 1.0)
    shown = f"{raw:g} {unit.name} is outside the range {unit.lo:g}:{unit.hi:g}" if unit else f"{raw:g} is outside [0, 1]"
    hint = "" if unit else " (give physical values with --degrees LO:HI or --cm LO:HI)"
    raise InputError(f"{where}: {shown}{hint}")


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
        try:
            import fcntl
        except ImportError:  # pragma: no cover - Windows: the thread lock is all we have
            fcntl = None
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
    text = str(name).strip() if name is not None else ""
    if not text:
        raise InputError("an object needs a non-empty name")
    bad = [c for c in FORBIDDEN_NAME_CHARS if c in text]
    if bad:
        raise InputError(f"object name {text!r} contains {bad!r}; '=' separates name and value in --state NAME=VALUE")
    if len(text) > 100:
        raise InputError(f"object name {text[:20]!r}... is longer than 100 characters")
    return text


def require_object(mapping: dict[int, str], name: str, where: str = "object") -> str:
    if name not in mapping.values():
        known = ", ".join(repr(n) for n in mapping.values()) or "none yet"
        raise InputError(f"{where}: unknown object {name!r} (objects: {known}); add it with --add-object {name!r}")
    return name


def _write_objects(ds: Path, mapping: dict[int, str]) -> None:
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
        _write_objects(ds, mapping)
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
        _write_objects(ds, {k: (new if v == old else v) for k, v in mapping.items()})
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


def set_label(ds: str | Path, name: str, frame: Any, value: Any, *, unit: Unit | None = None,
              add_new_object: bool = False) -> dict[str, Any]:
    """Set object `name`'s state on `frame`; returns {"key", "object", "value", "previous"}."""
    ds = Path(ds)
    name = check_object_name(name)
    v = normalise_value(value, unit, where=f"{name} @ {frame}")
    frames = dataset_frames(ds)
    key = resolve_frame(frames, frame)
    if add_new_object and name not in read_objects(ds).values():
        refuse_new_objects_with_masks(ds, [name])
        add_object(ds, name)
    with edit_lock(ds):
        require_object(read_objects(ds), name)
        labels = read_labels_raw(ds)
        entry = labels.get(key)
        if not isinstance(entry, dict):  # a broken entry (`frame_00042: abc`) is replaced: that is the repair
            entry = labels[key] = {}
        previous = entry.get(name)
        entry[name] = v
        write_labels(ds, labels)
    return {"key": key, "object": name, "value": v, "previous": previous}


def unset_label(ds: str | Path, name: str, frame: Any) -> float | None:
    """Remove object `name`'s label on `frame`; returns the removed value (None when there was none)."""
    ds = Path(ds)
    key = resolve_frame(dataset_frames(ds), frame)
    with edit_lock(ds):
        labels = read_labels_raw(ds)
        entry = labels.get(key, {})
        if not isinstance(entry, dict):  # a broken entry: unsetting it removes it
            labels.pop(key, None)
            write_labels(ds, labels)
            return entry
        previous = entry.pop(name, None)
        if previous is None:
            return None
        if not entry:
            labels.pop(key, None)
        write_labels(ds, labels)
        return previous


def list_labels(ds: str | Path) -> list[tuple[str, str, Any]]:
    """(frame key, object, value) for every label, in frame then object-id order. Values are as stored: a bad
    one (a word, NaN, 5.0) is listed too, so it can be seen and overwritten; `check_labels` says what is wrong.
    An entry that is not {object: value} at all is listed with the object ''."""
    ds = Path(ds)
    order = {n: i for i, n in read_objects(ds).items()}
    labels = read_labels_raw(ds)
    rows: list[tuple[str, str, Any]] = []
    for key in sorted(labels, key=lambda k: (_safe_index(k), k)):
        entry = labels[key]
        if not isinstance(entry, dict):
            rows.append((key, "", entry))
            continue
        for name in sorted(entry, key=lambda n: (order.get(n, 1 << 20), n)):
            rows.append((key, name, entry[name]))
    return rows


def _safe_index(key: str) -> int:
    try:
        return frame_index(key)
    except ValueError:
        return 1 << 30


def check_labels(ds: str | Path) -> list[str]:
    """Problems in the labels already on disk (edited by hand, or objects / frames removed since)."""
    ds = Path(ds)
    names = set(read_objects(ds).values())
    try:
        frames = set(dataset_frames(ds))
    except InputError:
        frames = set()
    problems = []
    for key, name, value in list_labels(ds):
        idx = _safe_index(key)
        if idx == 1 << 30:
            problems.append(f"{key}: the key does not end in a frame number (use frame_00042)")
        elif frames and idx not in frames:
            problems.append(f"{key}: frame {idx} is not among the dataset's frames")
        if name == "":
            problems.append(f"{key}: {value!r} is not {{object name: value}}; replace it with `--set OBJECT {key} "
                            f"VALUE` or remove it with `--unset '' {key}`")
            continue
        if name not in names:
            problems.append(f"{key}: object {name!r} is not in mapping.yaml")
        why = label_value_problem(value)
        if why is not None:
            problems.append(f"{key}: {name} = {why}; repair it with `interreal label DS --set {name!r} {key} VALUE` "
                            f"or --unset {name!r} {key}")
    return problems


def format_table(ds: str | Path) -> str:
    """Frames down, objects across; '-' where an object has no label on that frame."""
    ds = Path(ds)
    names = [n for _, n in sorted(read_objects(ds).items())]
    rows = list_labels(ds)
    for _, n, _ in rows:
        if n not in names:
            names.append(n)
    if not names:
        return "no objects yet: add one with `interreal label DS --add-object NAME`"
    by_key: dict[str, dict[str, float]] = {}
    for key, n, v in rows:
        by_key.setdefault(key, {})[n] = v
    width = [max(11, len("frame"))] + [max(6, len(n)) for n in names]
    lines = ["  ".join(h.ljust(w) for h, w in zip(["frame"] + names, width))]
    lines.append("  ".join("-" * w for w in width))
    for key, entry in by_key.items():
        cells = [key] + [_cell(entry[n]) if n in entry else "-" for n in names]
        lines.append("  ".join(c.ljust(w) for c, w in zip(cells, width)))
    counts = [sum(1 for e in by_key.values() if n in e) for n in names]
    lines.append("  ".join(c.ljust(w) for c, w in zip(["labels"] + [str(c) for c in counts], width)))
    return "\n".join(lines)


def _cell(value: Any) -> str:
    """A label as the table shows it; a bad one is flagged with '!' (the warnings below the table say why)."""
    return f"{float(value):.3f}" if label_value_problem(value) is None else f"!{value!r}"


def refuse_new_objects_with_masks(ds: str | Path, names: Iterable[str]) -> None:
    """Adding an object to a masked dataset would leave every mask one channel short: refuse, say what to do."""
    names = list(names)
    if not names:
        return
    ds = Path(ds)
    masks = sorted((ds / MASKS_DIR).glob("*.npy")) if (ds / MASKS_DIR).is_dir() else []
    if not masks:
        return
    try:
        channels = npy_header(masks[0])[0][-1]
    except (OSError, ValueError, IndexError):
        channels = "?"
    raise InputError(f"{ds} has masks for {len(read_objects(ds))} object(s) ({channels} channels with the "
                     f"background): adding {names} would leave every mask with the wrong channel count; draw the new "
                     f"object(s) on the keyframes (`interreal annotate {ds}`) and re-run `interreal masks`, or fix "
                     "the object name(s) if they are typos")


# ----------------------------------------------------------------------------------------------------------------
# Import
# ----------------------------------------------------------------------------------------------------------------
def read_label_file(file: str | Path) -> list[dict[str, Any]]:
    """Rows {frame, object, value, unit, where} from a CSV (frame,object,value[,unit]) or key_frame_value YAML."""
    path = Path(file)
    if not path.is_file():
        raise InputError(f"{path}: no such file (expected a .csv or key_frame_value.yaml-style .yaml)")
    if path.suffix.lower() == ".csv":
        return _read_csv(path)
    if path.suffix.lower() in (".yaml", ".yml", ".json"):
        return _read_yaml_labels(path)
    raise InputError(f"{path}: unknown label file type {path.suffix!r}; use .csv or .yaml")


def _read_csv(path: Path) -> list[dict[str, Any]]:
    with open(path, newline="", encoding="utf-8-sig") as fh:
        reader = csv.DictReader(fh)
        fields = [f.strip().lower() for f in (reader.fieldnames or [])]
        missing = [c for c in ("frame", "object", "value") if c not in fields]
        if missing:
            raise InputError(f"{path}: CSV header must name the columns frame,object,value[,unit]; missing {missing}")
        rows = []
        for line, raw in enumerate(reader, start=2):
            rec = {str(k).strip().lower(): (v or "").strip() for k, v in raw.items() if k is not None}
            if not any(rec.values()):
                continue
            rows.append({"frame": rec["frame"], "object": rec["object"], "value": rec["value"],
                         "unit": rec.get("unit") if "unit" in fields else None, "where": f"{path.name}:{line}"})
    return rows


def _read_yaml_labels(path: Path) -> list[dict[str, Any]]:
    try:
        raw = read_yaml(path)
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not valid YAML ({exc})") from None
    if raw is None:
        return []
    if not isinstance(raw, dict):
        raise InputError(f"{path}: expected {{frame_00042: {{object name: value}}}}, got a {type(raw).__name__}")
    rows = []
    for key, entry in raw.items():
        if not isinstance(entry, dict):
            raise InputError(f"{path}[{key}]: expected {{object name: value}}, got {entry!r}")
        for name, value in entry.items():
            rows.append({"frame": key, "object": name, "value": value, "unit": None, "where": f"{path.name}[{key}][{name}]"})
    return rows


@dataclass
class ParsedImport:
    """A label file checked against a dataset: (key, object, value) rows, ready to write."""

    rows: list[tuple[str, str, float]]
    skipped: list[str]
    units: dict[str, Unit]

    def names(self) -> list[str]:
        return list(dict.fromkeys(n for _, n, _ in self.rows))


def parse_import(ds: str | Path, file: str | Path, *, degrees: Any = None, cm: Any = None,
                 skip_unknown_frames: bool = False) -> ParsedImport:
    """Read and check every row of a label file against DS (InputError listing the bad rows; nothing written)."""
    units = {u.name: u for u in (parse_range(degrees, "degrees"), parse_range(cm, "cm")) if u is not None}
    rows = read_label_file(file)
    if not rows:
        raise InputError(f"{file}: no labels in the file")
    has_unit_col = any(r["unit"] is not None for r in rows)
    if not has_unit_col and len(units) > 1:
        raise InputError(f"{file}: both --degrees and --cm given; add a unit column (deg / cm) to say which value is which")
    default_unit = next(iter(units.values())) if units and not has_unit_col else None
    frames = dataset_frames(ds)
    problems: list[str] = []
    out = ParsedImport([], [], units)
    for r in rows:
        try:
            name = check_object_name(r["object"])
            value = normalise_value(r["value"], default_unit, where=r["where"],
                                    row_unit=r["unit"] if has_unit_col else None, units=units)
            key = resolve_frame(frames, r["frame"], where=r["where"])
        except InputError as exc:
            if skip_unknown_frames and "is not among the dataset's frames" in str(exc):
                out.skipped.append(str(r["frame"]))
            else:
                problems.append(str(exc))
            continue
        out.rows.append((key, name, value))
    if problems:
        more = f"\n  ... and {len(problems) - 10} more" if len(problems) > 10 else ""
        raise InputError(f"{file}: {len(problems)} bad label(s), nothing imported:\n  " + "\n  ".join(problems[:10]) + more)
    return out


def _refuse_new_objects(file: str | Path, names: Iterable[str], known: Iterable[str]) -> None:
    known = list(known)
    new = [n for n in names if n not in known]
    if new:
        hints = []
        for n in new:
            close = difflib.get_close_matches(n, known, n=1, cutoff=0.6)
            if close:
                hints.append(f"{n!r}: did you mean {close[0]!r}?")
        raise InputError(f"{file}: unknown objects {new} (objects: {known}); "
                         + (" ".join(hints) + " " if hints else "")
                         + "fix the names, or import with --add-objects to add them as new objects")


def import_labels(ds: str | Path, file: str | Path, *, degrees: Any = None, cm: Any = None,
                  add_objects: bool | None = None,
                  replace: bool = False, skip_unknown_frames: bool = False, report: bool = True) -> dict[str, Any]:
    """Import labels from CSV or YAML into DS; every row is checked before anything is written.

    Physical values: a `unit` CSV column (deg, rad, cm, mm, m) with the range from `degrees` / `cm`
    ('LO:HI' or (lo, hi)), or, without the column, the one range given applies to every value.
    Bad input raises InputError before reports/labels.json is touched, so a typo does not mark the dataset failed.
    Objects the dataset does not have are refused (with a did-you-mean) unless `add_objects`; by default (None)
    they are added only to a dataset with no objects yet. A masked dataset never gets a new object (its masks
    would be a channel short). Returns {"imported", "added_objects", "skipped_frames", "labels", "objects"}.
    """
    ds = Path(ds)
    parsed = parse_import(ds, file, degrees=degrees, cm=cm, skip_unknown_frames=skip_unknown_frames)
    known = list(read_objects(ds).values())
    if add_objects is None:
        add_objects = not known
    if not add_objects:
        _refuse_new_objects(file, parsed.names(), known)
    refuse_new_objects_with_masks(ds, [n for n in parsed.names() if n not in known])
    ctx = StageReport(ds, "labels", inputs={"file": str(file), "fingerprints": labels_fingerprints(ds, replace)},
                      settings={"units": {k: [u.lo, u.hi] for k, u in parsed.units.items()}, "add_objects": add_objects,
                                "replace": replace, "skip_unknown_frames": skip_unknown_frames}) if report else None
    with (ctx or _null()) as rep:
        with edit_lock(ds):
            mapping = read_objects(ds)
            if not add_objects:  # again under the lock: another writer may have renamed an object since
                _refuse_new_objects(file, parsed.names(), mapping.values())
            new_names = [n for n in parsed.names() if n not in mapping.values()]
            for n in new_names:
                mapping[len(mapping)] = n
            if new_names:
                _write_objects(ds, mapping)
            before = {} if not (ds / LABELS_FILE).exists() else read_labels_raw(ds)
            labels = {} if replace else {k: (dict(v) if isinstance(v, dict) else v) for k, v in before.items()}
            for key, name, value in parsed.rows:
                if not isinstance(labels.get(key), dict):
                    labels[key] = {}
                labels[key][name] = value
            if labels != before or not (ds / LABELS_FILE).exists():  # unchanged: keep the file (and its stamp)
                write_labels(ds, labels)
        result = {"imported": len(parsed.rows), "added_objects": new_names, "skipped_frames": parsed.skipped,
                  "labels": sum(len(e) for e in labels.values()), "objects": [mapping[i] for i in sorted(mapping)]}
        if rep is not None:
            rep.figures.update(result)
            if parsed.skipped:
                rep.warn(f"{len(parsed.skipped)} label row(s) name frames that are not in the dataset and were skipped",
                         cause="unknown-frame", frames=parsed.skipped[:50])
        return result


def labels_fingerprints(ds: Path, replace: bool) -> dict[str, Any]:
    """What the labels were set on: the capture the frames came from. Labels kept from an earlier capture keep
    that capture's fingerprint (so `validate` goes on calling them stale) until they are replaced as a whole."""
    fps = provenance.fingerprints(ds, ["capture"])
    if replace or "capture" not in fps:
        return fps
    before = provenance.recorded(read_report(ds, "labels")).get("capture")
    try:
        has_labels = bool(read_labels_raw(ds))
    except DatasetError:
        has_labels = True
    if before and has_labels and before.get("content") != fps["capture"].get("content"):
        fps["capture"] = before
    return fps


@contextmanager
def _null() -> Iterator[None]:
    yield None


# ----------------------------------------------------------------------------------------------------------------
# CLI: interreal label
# ----------------------------------------------------------------------------------------------------------------
def add_unit_arguments(p) -> None:
    """--degrees / --cm: physical label values, shared by `label` and `process --labels` so they mean the same."""
    p.add_argument("--degrees", metavar="LO:HI",
                   help="values are angles; LO degrees = state 0, HI = state 1 (negative LO: --degrees=-10:80)")
    p.add_argument("--cm", metavar="LO:HI", help="values are distances in cm; LO = state 0, HI = state 1")


def add_arguments(p) -> None:
    p.add_argument("dataset", type=Path, help="dataset folder (frames in DS/images)")
    p.add_argument("--set", nargs=3, action="append", default=[], metavar=("OBJECT", "FRAME", "VALUE"),
                   help="set OBJECT's state on FRAME (42, 00042 or frame_00042); VALUE in [0, 1] or in --degrees/--cm")
    p.add_argument("--unset", nargs=2, action="append", default=[], metavar=("OBJECT", "FRAME"),
                   help="remove OBJECT's label on FRAME")
    p.add_argument("--from", dest="from_file", type=Path, metavar="FILE",
                   help="import labels: CSV with columns frame,object,value[,unit] or key_frame_value.yaml-style YAML")
    p.add_argument("--add-object", action="append", default=[], metavar="NAME",
                   help="add an object to mapping.yaml (repeatable); --set needs its object to exist")
    p.add_argument("--describe", nargs=2, action="append", default=[], metavar=("OBJECT", "TEXT"),
                   help="a one-line description of OBJECT for language grounding (prompts.yaml)")
    p.add_argument("--rename", nargs=2, metavar=("OLD", "NEW"),
                   help="rename an object in mapping.yaml, labels, keyframe annotations and prompts.yaml")
    p.add_argument("--list", action="store_true", help="print the labels as a table (the default with no edits)")
    p.add_argument("--json", action="store_true", help="with --list: print JSON rows instead of a table")
    add_unit_arguments(p)
    p.add_argument("--replace", action="store_true", help="with --from: replace all labels instead of merging")
    p.add_argument("--add-objects", action="store_true",
                   help="with --from: add objects the file names that mapping.yaml does not have (without it they "
                        "are refused with a did-you-mean, unless the dataset has no objects yet)")
    p.add_argument("--no-new-objects", action="store_true", help=argparse.SUPPRESS)  # the default now
    p.add_argument("--skip-unknown-frames", action="store_true",
                   help="with --from: skip rows whose frame is not in the dataset (with a warning) instead of failing")
    p.epilog = """examples:
  interreal label out/ds --add-object "fridge door" --set "fridge door" 42 0 --set "fridge door" 300 1
  interreal label out/ds --set "fridge door" 120 45 --degrees 0:90      # 45 degrees of 0..90 -> 0.5
  interreal label out/ds --set "top drawer" frame_00120 12 --cm 0:40   # 12 cm of 0..40 -> 0.3
  interreal label out/ds --from out/cap/annotations/states.yaml      # key_frame_value.yaml format
  interreal label out/ds --from states.csv --degrees 0:110 --cm 0:45  # CSV frame,object,value,unit
  interreal label out/ds --unset "fridge door" 42
  interreal label out/ds --rename "fridge door" "fridge"
  interreal label out/ds --list"""


@dataclass
class _Plan:
    """Every edit of one `interreal label` command, checked against the dataset before any is applied."""

    adds: list[str]
    describe: list[tuple[str, str]]
    rename: tuple[str, str] | None
    imported: ParsedImport | None
    sets: list[tuple[str, str, float]]
    unsets: list[tuple[str, str]]


def _plan(ds: Path, args) -> _Plan:
    """Check the whole command (InputError, nothing written), so a typo never leaves a failed labels report."""
    degrees, cm = parse_range(args.degrees, "degrees"), parse_range(args.cm, "cm")
    if args.set and degrees and cm:
        raise InputError("--set takes one unit: give --degrees or --cm, not both (run one command per unit)")
    names = list(read_objects(ds).values())
    adds = [check_object_name(n) for n in args.add_object]
    names += [n for n in adds if n not in names]
    describe = []
    for name, text in args.describe:
        require_object(dict(enumerate(names)), name, where=f"--describe {name}")
        describe.append((name, str(text)))
    rename = None
    if args.rename:
        old, new = args.rename[0], check_object_name(args.rename[1])
        require_object(dict(enumerate(names)), old, where=f"--rename {old}")
        if new != old and new in names:
            raise InputError(f"cannot rename {old!r} to {new!r}: an object called {new!r} exists already")
        names = [new if n == old else n for n in names]
        rename = (old, new)
    imported = None
    if args.from_file:
        imported = parse_import(ds, args.from_file, degrees=args.degrees, cm=args.cm,
                                skip_unknown_frames=args.skip_unknown_frames)
        if names and not (args.add_objects and not args.no_new_objects):
            _refuse_new_objects(args.from_file, imported.names(), names)
        names += [n for n in imported.names() if n not in names]
    known = set(read_objects(ds).values())
    refuse_new_objects_with_masks(ds, [n for n in adds + (imported.names() if imported else []) if n not in known])
    frames = dataset_frames(ds) if (args.set or args.unset) else {}
    sets = []
    for name, frame, value in args.set:
        where = f"--set {name} {frame} {value}"
        name = check_object_name(name)
        require_object(dict(enumerate(names)), name, where=where)
        v = normalise_value(value, degrees or cm, where=where)
        sets.append((name, resolve_frame(frames, frame, where=where), v))
    unsets = [(name, resolve_frame(frames, frame, where=f"--unset {name} {frame}")) for name, frame in args.unset]
    return _Plan(adds, describe, rename, imported, sets, unsets)


def main(args) -> int:
    ds: Path = args.dataset
    if not ds.is_dir():
        raise InputError(f"{ds} is not a folder")
    edits = bool(args.set or args.unset or args.from_file or args.add_object or args.rename or args.describe)
    if edits:
        plan = _plan(ds, args)
        done: list[str] = []
        fps = labels_fingerprints(ds, bool(args.replace and args.from_file))
        with StageReport(ds, "labels", inputs={"from": str(args.from_file) if args.from_file else None,
                                               "fingerprints": fps},
                         settings={"degrees": args.degrees, "cm": args.cm}) as rep:
            for name in plan.adds:
                oid = add_object(ds, name)
                done.append(f"object {oid}: {name}")
            for name, text in plan.describe:
                with edit_lock(ds):
                    write_prompts(ds, {**read_prompts(ds), name: text})
                done.append(f"described {name!r}")
            if plan.rename:
                rename_object(ds, *plan.rename)
                done.append(f"renamed {plan.rename[0]!r} -> {plan.rename[1]!r}")
            if args.from_file:
                res = import_labels(ds, args.from_file, degrees=args.degrees, cm=args.cm,
                                    add_objects=True, replace=args.replace,
                                    skip_unknown_frames=args.skip_unknown_frames, report=False)
                rep.figures["imported"] = res["imported"]
                done.append(f"imported {res['imported']} label(s) from {args.from_file}"
                            + (f"; new objects {res['added_objects']}" if res["added_objects"] else ""))
                if res["skipped_frames"]:
                    rep.warn(f"{len(res['skipped_frames'])} label row(s) name frames that are not in the dataset "
                             f"and were skipped", cause="unknown-frame", frames=res["skipped_frames"][:50])
                    done.append(f"skipped {len(res['skipped_frames'])} row(s) on frames not in the dataset")
            for name, key, v in plan.sets:
                set_label(ds, name, key, v)
                done.append(f"{key} {name} = {v:.4f}")
            for name, key in plan.unsets:
                prev = unset_label(ds, name, key)
                done.append(f"unset {name} @ {key}" + ("" if prev is not None else " (had no label)"))
            rows = list_labels(ds)
            rep.figures.update({"labels": len(rows), "objects": [n for _, n in sorted(read_objects(ds).items())],
                                "edits": done})
            for problem in check_labels(ds):
                rep.warn(problem, cause="stale-label")
        for line in done:
            print(line)
    if args.list or not edits:
        if args.json:
            print(json.dumps([{"frame": k, "object": n, "value": v if isinstance(v, (int, float, str)) else repr(v)}
                              for k, n, v in list_labels(ds)], indent=2))
        else:
            print(format_table(ds))
    for problem in check_labels(ds):
        print(f"warning: {problem}", file=sys.stderr)
    return 0

