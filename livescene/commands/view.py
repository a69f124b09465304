"""`livescene view RUN`: serve a trained run to the browser viewer (`livescene.viewer`), or `--bench` its speed."""

from __future__ import annotations

import argparse
import json
import sys
import webbrowser
from pathlib import Path

from ..device import configure_threads
from ..errors import LiveSceneError
from ..run import load_run
from ..viewer import ViewerServer, require_web
from ..viewer.session import ViewerSession, measure


EPILOG = """examples:
  livescene view out/run                       # prints http://127.0.0.1:PORT/?token=...; open it in a browser
  livescene view out/run --port 8890 --open    # a fixed port, and open the browser
  livescene view out/run --low 120 --sharp 480 # smaller images while moving, larger at rest
  livescene view out/run --bench               # its speed here: first image, frames/s while dragging, sharp
In the page: drag to orbit, right-drag (or shift-drag) to pan, wheel to zoom, W A S D / Q E to fly, arrow keys
to look around; a slider per object; a command such as "open the fridge" (needs the language extra); the
training cameras to jump to; Save view writes RUN/views/view_NNN.png (+ .json, a camera file for
`livescene render RUN --cameras`), Sweep video writes RUN/views/sweep_OBJECT_NNN.mp4.
The server answers only on this machine (127.0.0.1) and only to the URL's token."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.epilog = EPILOG
    p.add_argument("run", type=Path, help="run folder of `livescene train`")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default 127.0.0.1: this machine only; the token is required anyway)")
    p.add_argument("--port", type=int, default=0, help="port (default: a free one)")
    p.add_argument("--low", type=int, default=160, help="longer side of the image while moving (default 160)")
    p.add_argument("--sharp", type=int, default=320, help="longer side of the image at rest (default 320)")
    p.add_argument("--device", default="auto", help="torch device: auto | cpu | cuda")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = auto)")
    p.add_argument("--open", action="store_true", help="open the page in the default browser")
    p.add_argument("--bench", action="store_true",
                   help="print the viewer's speed on this run as JSON (first low image after a slider move, "
                        "frames/s while dragging, sharp image) and exit, without serving")


def main(args: argparse.Namespace) -> int:
    require_web()
    if not args.run.is_dir():
        raise LiveSceneError(f"{args.run} is not a run folder: train one with `livescene train DS --out RUN`")
    for opt in ("low", "sharp"):
        if not 16 <= getattr(args, opt) <= 2048:
            raise LiveSceneError(f"--{opt} {getattr(args, opt)} must be in [16, 2048] pixels")
    configure_threads(args.threads)
    session = ViewerSession(load_run(args.run, device=args.device), low=args.low, sharp=args.sharp)
    if args.bench:
        print(json.dumps(measure(session)))
        return 0
    print(f"livescene view: renderer ready ({session.warm_up():.1f} s to warm up)", flush=True)
    server = ViewerServer(session, host=args.host, port=args.port)
    print(f"livescene view: {args.run} on {server.url}\n(Ctrl-C to stop)", flush=True)
    if args.open:
        webbrowser.open(server.url)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.sock.close()
    print("livescene view: stopped", file=sys.stderr)
    return 0
