"""`interreal masks`: propagate a few keyframe masks to every frame with OpenCV flow, with confidence.

Modules: keyframes (PNG / LabelMe input, GrabCut for boxes), flow (DIS / RLOF / Farneback, forward-backward
trust), appearance (per-label colour models), track (chains, fusion, refinement), confidence (where to add
keyframes), health (lost / jumped / drifting per frame, a predicted J, the warnings), preview, stage.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..report import warning_lines
from .stage import PREVIEW_KINDS, propagate

__all__ = ["propagate", "add_arguments", "main"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", type=Path, help="dataset folder with images/ (from `interreal frames`)")
    p.add_argument("--keyframes", type=Path, required=True,
                   help="folder of keyframe annotations: <frame id>.png index masks or <frame id>.json LabelMe")
    p.add_argument("--suggest", type=int, default=5, metavar="N",
                   help="print the N frames where one more keyframe would help most (default 5)")
    p.add_argument("--work-size", type=int, default=-1, metavar="PX",
                   help="long side of the flow/propagation resolution (0 = full size; default auto: 400 when "
                        "every keyframe gap is at most 12 frames, else 480)")
    p.add_argument("--flow", choices=("dis", "rlof", "farneback"), default="dis", help="optical flow (default dis)")
    p.add_argument("--preset", choices=("ultrafast", "fast", "medium"), default="fast", help="DIS preset")
    p.add_argument("--appearance", type=float, default=0.25, help="weight of the colour model (0 = off)")
    p.add_argument("--rigid", type=float, default=1.0, help="weight of the per-object homography motion (0 = off)")
    p.add_argument("--no-fusion", action="store_true", help="forward chain only (no backward fusion)")
    p.add_argument("--no-refine", action="store_true", help="no guided-filter boundary refinement")
    p.add_argument("--preview", choices=PREVIEW_KINDS, default="both",
                   help="DS/previews/masks_sheet.png and/or masks_overlay.mp4 (default both)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.epilog = """examples:
  interreal frames video.mp4 out/ds
  interreal masks out/ds --keyframes annotations/keyframes
  interreal masks out/ds --keyframes kf/ --suggest 3 --preview sheet
  interreal masks out/ds --keyframes kf/ --work-size 0 --preset medium   # slower, sharper
keyframes: DIR/00042.png (0 = background, k = object k-1, 255 = not annotated) or DIR/00042.json (LabelMe
polygons / rectangles); DIR/mapping.yaml names the objects when the dataset has no mapping.yaml.
outputs: DS/masks/<fid>.npy, DS/sfm_masks/<image>.png, DS/previews/, DS/reports/masks.json"""


def main(args: argparse.Namespace) -> int:
    fig = propagate(args.dataset, args.keyframes, work_long_side=args.work_size, flow=args.flow, preset=args.preset,
                    appearance=args.appearance, rigid=args.rigid, fusion=not args.no_fusion,
                    refine=not args.no_refine, suggest=args.suggest, preview=args.preview, progress=not args.quiet)
    print(f"masks: {fig['frames']} frames, {len(fig['objects'])} objects, {fig['fps']:.1f} frames/s")
    for name, c in fig["confidence_mean"].items():
        print(f"  {name}: predicted J {c:.2f} (lowest frame {fig['confidence_min'][name]:.2f})")
    for line in warning_lines(args.dataset, ["masks"]):
        print(line)
    if args.suggest > 0:
        print("annotate next: " + (", ".join(fig["suggested_frames"]) or "(nothing: every frame is a keyframe)"))
    return 0
