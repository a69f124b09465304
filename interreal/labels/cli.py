"""`interreal label DS`: set / unset / import / list labels and edit the object list, every edit checked first."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

from ..dataset import read_prompts, write_prompts
from ..errors import InputError
from ..report import StageReport
from .edit import check_labels, format_table, list_labels, refuse_new_objects_with_masks, set_label, unset_label
from .importing import ParsedImport, import_labels, labels_fingerprints, parse_import, refuse_unknown_objects
from .objects import (add_object, check_object_name, dataset_frames, edit_lock, read_objects, rename_object,
                      require_object, resolve_frame)
from .values import normalise_value, parse_range


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
    p.add_argument("--objects", action="store_true", help="print the dataset's object names, one per line (scripts)")
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
            refuse_unknown_objects(args.from_file, imported.names(), names)
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
    if args.objects:
        for _, name in sorted(read_objects(ds).items()):
            print(name)
        return 0
    if args.list or not edits:
        if args.json:
            print(json.dumps([{"frame": k, "object": n, "value": v if isinstance(v, (int, float, str)) else repr(v)}
                              for k, n, v in list_labels(ds)], indent=2))
        else:
            print(format_table(ds))
    for problem in check_labels(ds):
        print(f"warning: {problem}", file=sys.stderr)
    return 0
