"""`livescene eval RUN --out FILE [--gt DIR]`: `evaluate.evaluate` on a run, against the truth in DIR when given."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from interreal import atomic

from ..device import configure_threads
from ..errors import LiveSceneError, writing
from ..evaluate import evaluate, open_truth
from ..official_split import use_split
from ..run import load_run
from ..unseen import support_lines


def add_arguments(p) -> None:
    p.add_argument("run", type=Path, help="run folder of `livescene train`")
    p.add_argument("--gt", type=Path, default=None,
                   help="a folder with the truth, e.g. an `interreal synth` capture (read by the truth reader that "
                        "knows it: `livescene.evaluate.open_truth`)")
    p.add_argument("--out", type=Path, required=True, help="JSON file for the figures")
    p.add_argument("--max-frames", type=int, default=0, help="evaluate this many held-out frames, evenly spread (0 = all)")
    p.add_argument("--scale", type=float, default=1.0, help="render scale (e.g. 0.5 for a quicker estimate)")
    p.add_argument("--novel", type=int, default=4, help="held-out cameras rendered at novel states (needs --gt)")
    p.add_argument("--device", default="auto")
    p.add_argument("--dataset", type=Path, default=None, help="the run's dataset where it is now, when it was moved")
    p.add_argument("--exact", action="store_true",
                   help="render with the exact renderer (every sample read; slower) instead of the fast one")
    p.add_argument("--split", choices=("ours", "official"), default="ours",
                   help="held-out frames: the run's own (default), or the official LiveScene split, so figures "
                        "compare with the paper's (needs a run trained with --set split=official)")
    p.epilog = ("examples:\n"
                "  livescene eval out/run --out out/eval.json\n"
                "  livescene eval out/run --gt out/cap --out out/eval.json --max-frames 8")


def main(args) -> int:
    configure_threads(0)
    if not (np.isfinite(args.scale) and 0 < args.scale <= 4) or args.max_frames < 0 or args.novel < 0:
        raise LiveSceneError("--scale must be in (0, 4], --max-frames and --novel at least 0")
    if args.gt is not None and not args.gt.is_dir():
        raise LiveSceneError(f"--gt {args.gt} is not a folder: give the `interreal synth` capture folder")
    run = load_run(args.run, device=args.device, dataset=args.dataset)
    split = use_split(run, args.split)  # --split official: the paper's eval frames (refused if trained on)
    truth = open_truth(args.gt, run.views) if args.gt else None
    res = evaluate(run, truth, max_frames=args.max_frames, scale=args.scale, novel=args.novel, fast=not args.exact)
    res["split"] = split
    with writing(args.out):
        atomic.write_json(args.out, res)
    for line in support_lines(res.get("unsupported") or []):
        print(f"livescene eval: {line}")
    keys = ["psnr", "psnr_interpolated", "ssim", "mask_iou", "depth_l1", "state_mae", "state_mae_labelled_train",
            "state_mae_labelled_held_out", "state_mae_measured_held_out", "novel_state_psnr", "composition_psnr"]
    print("livescene eval: " + ", ".join(f"{k} {res[k]:.4g}" for k in keys if res.get(k) is not None)
          + f" ({res['speed']['renderer']} renderer, {res['speed']['seconds_per_frame'] or 0:.2f} s a frame, "
            f"{res['speed']['rays_per_s'] or 0:,} rays/s) -> {args.out}")
    return 0
