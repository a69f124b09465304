"""`interreal export-official DS OUT` and `interreal export-official --check FOLDER`."""

from __future__ import annotations

import json
from pathlib import Path

from ..errors import InputError
from .export import export_official
from .rules import check_official


def add_arguments(p) -> None:
    p.add_argument("dataset", type=Path, help="dataset folder (ours), or with --check any folder to check")
    p.add_argument("out", type=Path, nargs="?", default=None, help="new folder for the official-layout copy")
    p.add_argument("--check", action="store_true", help="only run the official reader's rules on DATASET")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.epilog = ("examples:\n  interreal export-official out/room out/room_official\n"
                "  interreal export-official --check out/room_official")


def main(args) -> int:
    if args.check:
        if args.out is not None:
            raise InputError("--check takes one folder (the one to check), not an output folder")
        res = check_official(args.dataset)
        if args.json:
            print(json.dumps({"ok": res.ok, "problems": res.problems, "notes": res.notes, "split": res.split},
                             indent=2))
            return 0 if res.ok else 1
        print(f"{args.dataset}: {'passes' if res.ok else 'fails'} the official LiveScene reader's rules "
              f"(split: {res.split.get('how', '?')}, {res.split.get('train', 0)} train / "
              f"{res.split.get('eval', 0)} eval)")
        for p in res.problems:
            print(f"  problem: {p}")
        for n in res.notes:
            print(f"  note: {n}")
        return 0 if res.ok else 1
    if args.out is None:
        raise InputError("give an output folder: interreal export-official DS OUT (or --check DS)")
    log = export_official(args.dataset, args.out)
    if args.json:
        print(json.dumps(log, indent=2))
        return 0
    print(f"wrote {args.out}: {log['frames']} frames, {len(log['objects'])} objects, split {log['split']['train']} "
          f"train / {log['split']['eval']} eval ({log['split']['how']})")
    for n in log["notes"]:
        print(f"  - {n}")
    print("train it with the official code:")
    print(f"  {log['command']}")
    return 0
