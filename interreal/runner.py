"""The command-line driver both packages' entry points share (`interreal`, `livescene`): a subcommand per module,
imported only when it runs; an expected error (`error_types`) is one line and a non-zero exit, Ctrl-C / SIGTERM one
line and 130 / 143, a full disk or a permission problem one line naming the path, a closed pipe a quiet 141.

A command module exposes `add_arguments(parser)` and `main(args) -> int`. Like `report` and `atomic`, this is a
utility both packages may import; it imports no stage.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import io
import os
import signal
import sys
import threading
from typing import Callable, Sequence

from . import __version__
from .report import Terminated


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
    restore = _sigterm_as_interrupt()  # while the command's modules load (seconds) as while it runs
    try:
        return _run_command(prog, name, module_name, helptext, argv[1:], error_types)
    finally:
        restore()


def _run_command(prog: str, name: str, module_name: str, helptext: str, argv: list[str],
                 error_types: tuple[type[BaseException], ...]) -> int:
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
    args = parser.parse_args(argv)
    main_fn: Callable[[argparse.Namespace], int] = module.main
    _sigterm_as_interrupt()  # again: an import may have set its own (pycolmap's glog dumps a stack)
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


def _sigterm_as_interrupt() -> Callable[[], None]:
    """SIGTERM (`timeout`, `docker stop`, a scheduler) stops a command as Ctrl-C does: one line, 143, its report
    "interrupted". Set before the command's modules are imported and again after (pycolmap's glog sets its own,
    which dumps a stack). Returns what puts the earlier handler back (nothing to do off the main thread: signals
    are the main thread's)."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    def handler(signum, frame):  # noqa: ARG001 - the signal module's signature
        raise Terminated("terminated (SIGTERM)")

    before = signal.signal(signal.SIGTERM, handler)
    return lambda: signal.signal(signal.SIGTERM, signal.SIG_DFL if before is None else before)


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
