"""`interreal label DS --from FILE`: labels imported from CSV or key_frame_value YAML, every row checked first."""

from __future__ import annotations

import csv
import difflib
import io
import re
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator

import yaml

from .. import provenance
from ..conventions import LABELS_FILE
from ..dataset import read_labels_raw, write_labels
from ..errors import DatasetError, InputError
from ..report import StageReport, read_report
from .edit import merge_labels, refuse_new_objects_with_masks
from .objects import check_object_name, dataset_frames, edit_lock, read_objects, resolve_frame, write_objects
from .values import Unit, normalise_value, parse_range


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


_DECIMAL_COMMA = re.compile(r"^[-+]?\d*,\d+$")


def _delimiter(header: str) -> str:
    """The CSV's delimiter from its header line: `,`, or `;` / tab, what spreadsheets write where the decimal
    mark is a comma (the one that splits the header into the most columns)."""
    return max((",", ";", "\t"), key=lambda d: (header.count(d), d == ","))


def _read_csv(path: Path) -> list[dict[str, Any]]:
    with open(path, newline="", encoding="utf-8-sig") as fh:
        text = fh.read()
    delimiter = _delimiter(text.splitlines()[0] if text.strip() else "")
    reader = csv.DictReader(io.StringIO(text), delimiter=delimiter)
    fields = [f.strip().lower() for f in (reader.fieldnames or [])]
    missing = [c for c in ("frame", "object", "value") if c not in fields]
    if missing:
        raise InputError(f"{path}: CSV header must name the columns frame,object,value[,unit] (separated by commas, "
                         f"semicolons or tabs); missing {missing} in {fields}")
    rows = []
    for line, raw in enumerate(reader, start=2):
        rec = {str(k).strip().lower(): (v or "").strip() for k, v in raw.items() if k is not None}
        if not any(rec.values()):
            continue
        value = rec["value"]
        if delimiter != "," and _DECIMAL_COMMA.match(value):  # "0,5" from a spreadsheet with a decimal comma
            value = value.replace(",", ".")
        rows.append({"frame": rec["frame"], "object": rec["object"], "value": value,
                     "unit": rec.get("unit") if "unit" in fields else None, "where": f"{path.name}:{line}"})
    return rows


class _UniqueKeyLoader(yaml.SafeLoader):
    """A YAML loader that refuses a key given twice in one mapping (the plain loader keeps the last, silently)."""


def _mapping_without_repeats(loader: _UniqueKeyLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    seen: dict[Any, int] = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in seen:
            raise InputError(f"{loader.name}: {key!r} is given twice (lines {seen[key] + 1} and "
                             f"{key_node.start_mark.line + 1}): keep one")
        seen[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _mapping_without_repeats)


def _read_yaml_labels(path: Path) -> list[dict[str, Any]]:
    try:
        with open(path, encoding="utf-8") as fh:
            raw = yaml.load(fh, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass
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
    given: dict[tuple[str, str], tuple[float, str]] = {}
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
        if (key, name) in given:
            first, where = given[(key, name)]
            if abs(first - value) > 1e-9:
                problems.append(f"{r['where']}: {name!r} on {key} is labelled twice, {first:g} at {where} and "
                                f"{value:g} here: keep one")
            continue
        given[(key, name)] = (value, r["where"])
        out.rows.append((key, name, value))
    if problems:
        more = f"\n  ... and {len(problems) - 10} more" if len(problems) > 10 else ""
        raise InputError(f"{file}: {len(problems)} bad label(s), nothing imported:\n  " + "\n  ".join(problems[:10]) + more)
    return out


def refuse_unknown_objects(file: str | Path, names: Iterable[str], known: Iterable[str]) -> None:
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
        refuse_unknown_objects(file, parsed.names(), known)
    refuse_new_objects_with_masks(ds, [n for n in parsed.names() if n not in known])
    ctx = StageReport(ds, "labels", inputs={"file": str(file), "fingerprints": labels_fingerprints(ds, replace)},
                      settings={"units": {k: [u.lo, u.hi] for k, u in parsed.units.items()}, "add_objects": add_objects,
                                "replace": replace, "skip_unknown_frames": skip_unknown_frames}) if report else None
    with (ctx or _null()) as rep:
        with edit_lock(ds):
            mapping = read_objects(ds)
            if not add_objects:  # again under the lock: another writer may have renamed an object since
                refuse_unknown_objects(file, parsed.names(), mapping.values())
            new_names = [n for n in parsed.names() if n not in mapping.values()]
            for n in new_names:
                mapping[len(mapping)] = n
            if new_names:
                write_objects(ds, mapping)
            before = {} if not (ds / LABELS_FILE).exists() else read_labels_raw(ds)
            labels = merge_labels({} if replace else before, parsed.rows)
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
