"""Set, unset, merge, list and check the labels (`key_frame_value.yaml`): `merge_labels` is the one way labels
change, for the CLI and the annotation app alike."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable

from ..conventions import MASKS_DIR, frame_index
from ..dataset import label_value_problem, npy_header, read_labels_raw, write_labels
from ..errors import InputError
from .objects import (add_object, check_object_name, dataset_frames, edit_lock, read_objects, require_object,
                      resolve_frame)
from .values import Unit, normalise_value


def merge_labels(labels: dict[str, Any], edits: Iterable[tuple[str, str, float | None]]) -> dict[str, Any]:
    """The one way labels change (`label --set / --unset / --import` and the annotation app): a copy of the labels
    as stored (`read_labels_raw`, bad entries included) with each (frame key, object, value) set, or unset when the
    value is None. An entry that is not {object: value} is replaced by a set and dropped by an unset (that is its
    repair); a frame left with no label is dropped; every other entry is kept as it was."""
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in labels.items()}
    for key, name, value in edits:
        entry = out.get(key)
        if value is None:
            if not isinstance(entry, dict):
                out.pop(key, None)
            elif name in entry:
                del entry[name]
                if not entry:
                    del out[key]
            continue
        if not isinstance(entry, dict):
            entry = out[key] = {}
        entry[name] = value
    return out


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
        previous = entry.get(name) if isinstance(entry, dict) else None
        write_labels(ds, merge_labels(labels, [(key, name, v)]))
    return {"key": key, "object": name, "value": v, "previous": previous}


def unset_label(ds: str | Path, name: str, frame: Any) -> float | None:
    """Remove object `name`'s label on `frame`; returns the removed value (None when there was none)."""
    ds = Path(ds)
    key = resolve_frame(dataset_frames(ds), frame)
    with edit_lock(ds):
        labels = read_labels_raw(ds)
        entry = labels.get(key, {})
        previous = entry.get(name) if isinstance(entry, dict) else entry  # a broken entry: unsetting removes it
        if previous is None:
            return None
        write_labels(ds, merge_labels(labels, [(key, name, None)]))
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
