"""`livescene` command line: train, render, eval, ground (each subcommand owned by its module)."""

from __future__ import annotations

import sys
from typing import Sequence

from interreal.cli import run_cli
from interreal.errors import InterRealError

COMMANDS: dict[str, tuple[str, str]] = {
    "train": ("livescene.trainer", "fit the interactive radiance field to a dataset (progress, checkpoints, resume)"),
    "render": ("livescene.render", "render images / videos at chosen object states and cameras"),
    "eval": ("livescene.evaluate", "PSNR, SSIM, depth L1, state error, mask IoU, novel-state PSNR -> JSON"),
    "ground": ("livescene.language", "find an object by text and render its mask in any view"),
}

EPILOG = """examples:
  livescene train out/ds --out out/run --preset cpu
  livescene render out/run --sweep "door=0:1:30" --video out/door.mp4
  livescene eval out/run --gt out/cap --out out/eval.json
  livescene ground out/run "the thing that keeps food cold" --out out/ground
Run `livescene COMMAND --help` for each command's options and examples."""


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli("livescene", COMMANDS, EPILOG, argv, (InterRealError,))


if __name__ == "__main__":
    sys.exit(main())
