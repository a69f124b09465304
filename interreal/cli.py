"""`interreal` command line: one subcommand per stage, each owned by its module.

A stage module exposes `add_arguments(parser)` and `main(args) -> int`. Modules are imported only for the
subcommand that runs, so `interreal validate` does not pay for torch or pycolmap imports.
Expected failures (`InterRealError`) print one line and exit non-zero, without a traceback.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import io
import os
import sys
from typing import Callable, Sequence

from . import __version__
from .allocator import keep_freed_blocks
from .errors import InterRealError
from .report import Terminated

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


def run_cli(prog: str, commands: dict[str, tuple[str, str]], epilog: str, argv: Sequence[str] | None,
            error_types: tuple[type[BaseException], ...]) -> int:
    """Shared driver for both packages' entry points."""
    try:
        return _run_cli(prog, commands, epilog, argv, error_types)
    except BrokenPipeError:
        return _reader_went_away()
    except KeyboardInterrupt as exc:  # Ctrl-C while the command's modules load (torch takes seconds): one line
        return _interrupted(prog, exc)


def _interrupted(prog: str, exc: KeyboardInterrupt) -> int:
    """One line for Ctrl-C or SIGTERM (what the command saved is in its message); 130 / 143 as a shell reports."""
    print(f"{prog}: {str(exc) or 'interrupted'}", file=sys.stderr)
    return 143 if isinstance(exc, Terminated) else 130


def _run_cli(prog: str, commands: dict[str, tuple[str, str]], epilog: str, argv: Sequence[str] | None,
             error_types: tuple[type[BaseException], ...]) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    top = argparse.ArgumentParser(prog=prog, epilog=epilog, formatter_class=argparse.RawDescriptionHelpFormatter)
    top.add_argument("--version", action="store_true", help="print the version and exit")
    sub = top.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, helptext) in commands.items():
        sub.add_parser(name, help=helptext)
    if not argv or argv[0] in ("-h", "--help"):
        top.print_help()
        return 0 if argv else 2
    if argv[0] == "--version":
        print(f"{prog} {__version__}")
        return 0
    name = argv[0]
    if name not in commands:
        top.error(f"unknown command {name!r}; choose from {', '.join(commands)}")
    module_name, helptext = commands[name]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.startswith(module_name.split(".")[0]):
            print(f"{prog} {name}: not available in this build ({exc})", file=sys.stderr)
            return 2
        raise
    parser = argparse.ArgumentParser(prog=f"{prog} {name}", description=helptext,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    module.add_arguments(parser)
    args = parser.parse_args(argv[1:])
    main_fn: Callable[[argparse.Namespace], int] = module.main
    try:
        code = int(main_fn(args) or 0)
        sys.stdout.flush()
        return code
    except error_types as exc:
        print(f"{prog} {name}: error: {exc}", file=sys.stderr)
        return int(getattr(exc, "exit_code", 2))
    except KeyboardInterrupt as exc:
        return _interrupted(f"{prog} {name}", exc)
    except OSError as exc:
        if isinstance(exc, BrokenPipeError) or exc.errno not in SYSTEM_ERRNOS:
            raise
        print(f"{prog} {name}: error: {system_error_message(exc)}", file=sys.stderr)
        return 2


# disk full and permission problems: the user's to fix, so one line, not a traceback
SYSTEM_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EROFS}


def system_error_message(exc: OSError) -> str:
    """One line for a disk-full / read-only / permission error, naming the path."""
    where = exc.filename or "the output folder"
    what = {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "disk quota exceeded",
            errno.EROFS: "the file system is read-only", errno.EACCES: "permission denied",
            errno.EPERM: "operation not permitted"}.get(exc.errno, exc.strerror or str(exc))
    todo = "free some space" if exc.errno in (errno.ENOSPC, errno.EDQUOT) else "choose a folder you can write to"
    return f"{where}: {what}; {todo} and run the command again"


def _reader_went_away() -> int:
    """`interreal validate DS | head`: the reader closed the pipe; stop quietly, as `cat` does (exit 141 = SIGPIPE).
    stdout is pointed at /dev/null so the interpreter's final flush does not print a traceback either."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError, io.UnsupportedOperation):
        pass
    return 141


def main(argv: Sequence[str] | None = None) -> int:
    keep_freed_blocks()  # the stages churn through image-sized temporaries (see interreal.allocator)
    return run_cli(PROG, COMMANDS, EPILOG, argv, (InterRealError,))


if __name__ == "__main__":
    sys.exit(main())
