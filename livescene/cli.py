"""`livescene` command line: train, render, eval, ground (each subcommand owned by its module)."""

from __future__ import annotations

import sys
from typing import Sequence

from interreal.cli import run_cli
from interreal.errors import InterRealError

from .errors import WRITE_ERRNOS, describe_write_error

COMMANDS: dict[str, tuple[str, str]] = {
    "train": ("livescene.trainer", "fit the interactive radiance field to a dataset (progress, checkpoints, resume)"),
    "render": ("livescene.render", "render images / videos at chosen object states and cameras"),
    "eval": ("livescene.evaluate", "PSNR, SSIM, depth L1, state error, mask IoU, novel-state PSNR -> JSON"),
    "ground": ("livescene.language", "find an object by text and render its mask in any view"),
    "view": ("livescene.viewer", "local browser viewer: orbit / fly camera, a slider per object, save views"),
}

EPILOG = """examples:
  livescene train out/ds --out out/run --preset cpu
  livescene render out/run --sweep "door=0:1:30" --video out/door.mp4
  livescene eval out/run --gt out/cap --out out/eval.json
  livescene ground out/run "the thing that keeps food cold" --out out/ground
  livescene view out/run                       # prints a http://127.0.0.1:PORT/?token=... URL to open
Run `livescene COMMAND --help` for each command's options and examples."""


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    try:
        return run_cli("livescene", COMMANDS, EPILOG, args, (InterRealError,))
    except BrokenPipeError:  # `livescene ground ... | head`: the reader left, nothing to report
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except OSError as exc:  # a write the command did not wrap itself: still one line, never a traceback
        if exc.errno not in WRITE_ERRNOS:
            raise
        name = args[0] if args else "livescene"
        print(f"livescene {name}: error: {describe_write_error(exc, '?')}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
