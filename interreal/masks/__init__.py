"""`interreal masks`: propagate a few keyframe masks to every frame with OpenCV flow, with confidence.

Modules: keyframes (PNG / LabelMe input, GrabCut for boxes), flow (DIS / RLOF / Farneback, forward-backward
trust), appearance (per-label colour models), track (chains, fusion, refinement; a GrabCut of each frame where no
second keyframe corrects the chain), redetect (finding an object
again after its mask collapsed, from its keyframe's colours and ORB features), confidence (where to add
keyframes), health (lost / jumped / drifting per frame, a predicted J, the warnings), reuse (a re-run makes again
only what a keyframe change touched), preview, stage.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..report import warning_lines
from ..options import add_flags, values_from_args
from .config import MasksConfig
from .stage import left_view_lines, propagate, transient_line

__all__ = ["MasksConfig", "left_view_lines", "propagate", "transient_line", "add_arguments", "main", "masks_options"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", type=Path, help="dataset folder with images/ (from `interreal frames`)")
    p.add_argument("--keyframes", type=Path, required=True,
                   help="folder of keyframe annotations: <frame id>.png index masks or <frame id>.json LabelMe")
    add_masks_options(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.epilog = """examples:
  interreal frames video.mp4 out/ds
  interreal masks out/ds --keyframes annotations/keyframes
  interreal masks out/ds --keyframes kf/ --suggest 3 --preview sheet
  interreal masks out/ds --keyframes kf/ --work-size 0 --preset medium   # slower, sharper
  interreal masks out/ds --keyframes kf/ --cut 0                         # faster where one keyframe must carry
keyframes: DIR/00042.png (0 = background, k = object k-1, 254 = ignore: a person / hand, 255 = not annotated) or
DIR/00042.json (LabelMe polygons / rectangles; label ignore, person, hand or arm = the ignore class);
DIR/mapping.yaml names the objects when the dataset has no mapping.yaml. The ignore class is propagated like an
object into DS/transients/ (left out of poses, motions and training). With --transients auto (the default) the hand
model finds the hands on every frame and the layer grows them to the arm and sleeve, no painting needed
(mediapipe 0.10.21, installed by .ci/setup; without it one line says so). Run again after adding or changing a
keyframe: only the stretches between keyframes the change touched are made again (DS/cache/; --no-reuse: all).
outputs: DS/masks/<fid>.npy, DS/sfm_masks/<image>.png, DS/transients/<fid>.png, DS/previews/, DS/reports/masks.json"""


def add_masks_options(p) -> None:
    """The masks flags (shared with `interreal process`): one per `option` field of `MasksConfig`."""
    add_flags(p, MasksConfig)


def masks_options(args: argparse.Namespace) -> dict:
    """`propagate` options from the parsed flags (every flagged field, its default when not given)."""
    return values_from_args(MasksConfig, args)


def main(args: argparse.Namespace) -> int:
    opts = masks_options(args)
    fig = propagate(args.dataset, args.keyframes, progress=not args.quiet, **opts)
    kept = fig.get("reused_frames", 0)
    print(f"masks: {fig['frames']} frames, {len(fig['objects'])} objects, {fig['fps']:.1f} frames/s"
          + (f" ({kept} kept from the last run: no keyframe change touched them)" if kept else ""))
    tr = fig.get("transients") or {}
    line = transient_line(fig)
    if line:
        print(f"  {line} -> {args.dataset / 'transients'}")
    for name, frames in (tr.get("occluded") or {}).items():
        print(f"  {name}: hidden behind the person / hand at frames {frames} (occluded, not lost)")
    for line in left_view_lines(fig):
        print(f"  {line}")
    for name, frames in (fig.get("redetected") or {}).items():
        if frames:
            print(f"  {name}: found again after its mask collapsed at frames {', '.join(frames[:8])}")
    for name, c in fig["confidence_mean"].items():
        print(f"  {name}: predicted J {c:.2f} (lowest frame {fig['confidence_min'][name]:.2f})")
    for line in warning_lines(args.dataset, ["masks"]):
        print(line)
    if opts["suggest"] > 0:
        print("annotate next: " + (", ".join(fig["suggested_frames"]) or "(nothing: every frame is a keyframe)"))
    return 0
