"""`livescene ground RUN "text"`: which object the text names (ranked candidates), and with --out its mask in
a few views (`language.grounding`); a command ("open the fridge") grounds its object and renders it at that state."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from interreal import atomic
from interreal.errors import InputError
from interreal.report import StageReport

from ..data import require_valid_run_dataset
from ..language.commands import Command, ground_query, object_texts, parse_command
from ..language.encoders import check_extra, get_encoder
from ..language.grounding import check_run_has_masks, frame_views, render_mask, write_view
from ..language.retrieval import Candidate, RetrievalConfig, check_query, require_match
from ..run import load_run


EPILOG = """examples:
  livescene ground out/run "the fridge"                          # which object (ranked candidates), no rendering
  livescene ground out/run "the thing that keeps food cold" --out out/ground   # + masks / overlays of 4 views
  livescene ground out/run "top drawer" --views 00042,00120 --mask-threshold 0.6 --out out/g
  livescene ground out/run "laptop" --views held-out --out out/g --json
  livescene ground out/run "open the fridge" --out out/g         # a command: grounds "the fridge", renders it open
  livescene ground out/run "lid" --encoder clip:/models/clip-vit-b-16   # local CLIP weights (transformers folder)
Writes DIR/ground.json, DIR/mask_<view>.png (0/255), DIR/prob_<view>.png, DIR/overlay_<view>.png and
DIR/reports/ground.json. Exit 0 when an object matched, 2 when none did (the ranked candidates are printed).
Needs the optional extra: pip install 'interreal[language]'."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.epilog = EPILOG
    p.add_argument("run", type=Path, help="trained run folder (livescene train --out RUN)")
    p.add_argument("query", help="object description or command, e.g. \"the fridge\", \"open the top drawer\"")
    p.add_argument("--out", type=Path, help="write masks, overlays and ground.json here (omit: retrieval only)")
    p.add_argument("--views", default=None,
                   help="dataset frames to render: ids/indices separated by commas, 'held-out' or 'all' "
                        "(default: 4 spread over the capture)")
    p.add_argument("--threshold", type=float, default=RetrievalConfig.threshold,
                   help=f"minimum text similarity of the chosen object (default {RetrievalConfig.threshold})")
    p.add_argument("--mask-threshold", type=float, default=0.5,
                   help="probability above which a pixel belongs to the object (default 0.5)")
    p.add_argument("--encoder", default=None,
                   help="text encoder: 'minilm' (default, packaged) | 'clip:/local/transformers/folder' | "
                        "'clip:ViT-B-16@/local/open_clip.pt'")
    p.add_argument("--top", type=int, default=5, help="candidates to print (default 5)")
    p.add_argument("--device", default="auto", help="torch device for rendering: auto | cpu | cuda")
    p.add_argument("--json", action="store_true", help="print the result as JSON instead of a table")


def main(args: argparse.Namespace) -> int:
    query = check_query(args.query)
    if not 0.0 < args.mask_threshold < 1.0:
        raise InputError(f"--mask-threshold {args.mask_threshold} must be in (0, 1)")
    if not args.run.is_dir():
        raise InputError(f"{args.run} is not a run folder: train one with `livescene train DS --out RUN`")
    require_valid_run_dataset(args.run, "ground")  # an invalid dataset is refused, as by train/render/eval
    check_extra("livescene ground")  # the user's own input first, then what to install; still before loading a run
    try:
        cmd: Command | None = parse_command(query)
    except InputError:
        cmd = None
    encoder = get_encoder(args.encoder)
    config = RetrievalConfig(threshold=args.threshold)
    result = ground_query(args.run, cmd.query if cmd else query, encoder=encoder, config=config)
    names, descs = object_texts(args.run)
    bare = [n for n in names if not (descs or {}).get(n)]  # grounded by their names alone: said, not hidden
    payload: dict[str, Any] = {"run": str(args.run), "input": query, **result.to_json(),
                               "command": {"verb": cmd.verb, "value": cmd.value} if cmd else None,
                               "encoder": encoder.id, "mask_threshold": args.mask_threshold, "views": [],
                               "by_name_alone": bare}
    if not args.json:
        print(f"query {result.query!r} ({encoder.id}):\n{result.table(args.top)}")
        if bare:
            print(f"note: no description of {', '.join(repr(n) for n in bare)} (prompts.yaml): found by name alone; "
                  f"describe them with `interreal label DS --describe NAME TEXT`")
    if not result.ok:
        if args.out:
            atomic.write_json(args.out / "ground.json", payload)
        if args.json:
            print(json.dumps(payload, indent=2))
        require_match(result)
    best = result.best
    if args.out:
        payload["views"] = _render_views(args, best, cmd, payload)
        atomic.write_json(args.out / "ground.json", payload)
    if args.json:
        print(json.dumps(payload, indent=2))
    else:
        state = f", set to {cmd.value:g}" if cmd else ""
        print(f"-> {best.name} (score {best.score:.3f}, p {best.prob:.3f}{state})"
              + (f"; masks in {args.out}" if args.out else ""))
    return 0


def _render_views(args: argparse.Namespace, best: Candidate, cmd: Command | None, payload: dict) -> list[dict]:
    out: Path = args.out
    settings = {"query": payload["input"], "views": args.views, "threshold": args.threshold,
                "mask_threshold": args.mask_threshold, "encoder": payload["encoder"]}
    with StageReport(out, "ground", inputs={"run": str(args.run)}, settings=settings) as rep:
        with rep.step("load"):
            run = load_run(args.run, device=args.device)
            check_run_has_masks(run)
        views = frame_views(run, args.views)
        records = []
        with rep.step("render"):
            for view in tqdm(views, desc="ground: render", unit="view", leave=False):
                if cmd is not None:
                    view.states = {best.name: cmd.value}
                vm = render_mask(run, view, best.index, args.mask_threshold)
                files = write_view(out, vm)
                records.append({"view": view.name, "mask_area": round(vm.area, 5),
                                "max_prob": round(float(vm.prob.max()), 4), **files})
        rep.figures.update({"object": best.name, "score": best.score, "views": len(records),
                            "mean_mask_area": float(np.mean([r["mask_area"] for r in records]))})
        empty = [r["view"] for r in records if r["mask_area"] == 0]
        if empty:
            rep.warn(f"empty mask in views {', '.join(empty)}: the object may be out of view, or lower "
                     f"--mask-threshold", cause="empty_mask")
    return records
