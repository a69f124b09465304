"""`livescene` command line: dispatches to the command modules of `livescene.commands` (the table there)."""

from __future__ import annotations

import os
import sys
from typing import Sequence

from interreal.runner import run_cli
from interreal.errors import InterRealError

from .commands import COMMANDS
from .errors import WRITE_ERRNOS, describe_write_error

__all__ = ["COMMANDS", "main"]

EPILOG = """examples:
  livescene train out/ds --out out/run --preset cpu
  livescene render out/run --sweep "door=0:1:30" --video out/door.mp4
  livescene eval out/run --gt out/cap --out out/eval.json
  livescene ground out/run "the thing that keeps food cold" --out out/ground
  livescene view out/run                       # prints a http://127.0.0.1:PORT/?token=... URL to open
  livescene export out/run --format urdf --out out/asset   # URDF: a link per object, joints from its motion
Run `livescene COMMAND --help` for each command's options and examples."""


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    try:
        return run_cli("livescene", COMMANDS, EPILOG, args, (InterRealError,))
    except BrokenPipeError:  # `livescene ground ... | head`: the reader left, nothing to report
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
