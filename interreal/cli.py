"""`interreal` command line: one subcommand per stage, each owned by its module.

A stage module exposes `add_arguments(parser)` and `main(args) -> int`. Modules are imported only for the
subcommand that runs, so `interreal validate` does not pay for torch or pycolmap imports.
Expected failures (`InterRealError`) print one line and exit non-zero, without a traceback.
"""

from __future__ import annotations

import sys
from typing import Sequence

from .allocator import keep_freed_blocks
from .errors import InterRealError
from .runner import run_cli

PROG = "interreal"
# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "synth": ("interreal.synth.cli", "simulate a phone capture of an articulated room, with full ground truth"),
    "frames": ("interreal.frames", "video / image folder / RAW folder -> DS/images (sharpest frame per window)"),
    "masks": ("interreal.masks", "propagate keyframe masks to every frame -> DS/masks"),
    "poses": ("interreal.sfm.cli", "pycolmap SfM on DS/images (object pixels masked out) -> transforms.json"),
    "process": ("interreal.process", "frames -> masks -> poses -> labels in one go"),
    "motions": ("interreal.motions", "measure each object's rigid motion (hinge / slide) -> DS/articulation.json"),
    "label": ("interreal.labels.cli", "set / unset / list / import keyframe state labels"),
    "annotate": ("interreal.annotate", "local web app: draw keyframe masks, set states, run propagation"),
    "validate": ("interreal.dataset.validation", "is this a loadable LiveScene dataset? exit 0 / the full list of problems"),
    "demo": ("interreal.demo", "the whole job on a simulated capture (or your video), end to end"),
    "batch": ("interreal.batch", "many captures: process (and train) each as one task, on Ray or a local pool"),
    "export-official": ("interreal.official.cli", "copy a dataset into the layout the official LiveScene trainer reads "
                        "without NaN or rescaled labels (--check: run its reader's rules on a folder)"),
}

EPILOG = """examples:
  interreal demo                               # everything, on a simulated capture
  interreal synth out/cap --frames 120         # a simulated phone capture with truth
  interreal process out/cap/video.mp4 out/ds --keyframes out/cap/annotations/keyframes \\
      --labels out/cap/annotations/states.yaml
  interreal validate out/ds
Run `interreal COMMAND --help` for each command's options and examples."""


def main(argv: Sequence[str] | None = None) -> int:
    keep_freed_blocks()  # the stages churn through image-sized temporaries (see interreal.allocator)
    return run_cli(PROG, COMMANDS, EPILOG, argv, (InterRealError,))


if __name__ == "__main__":
    sys.exit(main())
