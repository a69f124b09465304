"""`interreal annotate DS`: a local web app to draw keyframe masks, set keyframe states and run propagation.

The page is plain HTML/JS shipped in `static/` (no CDN, no build step); the server is `server.py`
(FastAPI + uvicorn, token + Host checks); every edit goes through `store.py` (atomic, merge-safe).
Keyframe masks are stored as index PNGs in DS/keyframes/<fid>.png + DS/keyframes/mapping.yaml, which is the
`interreal masks DS --keyframes DIR` input format.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from .server import AnnotateServer

__all__ = ["add_arguments", "main"]


def add_arguments(p) -> None:
    p.add_argument("dataset", type=Path, help="dataset folder (frames in DS/images)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1: only this machine can connect; 0.0.0.0: other "
                        "machines too, at this machine's addresses, which are printed; they still need the token)")
    p.add_argument("--port", type=int, default=0, help="port (default 0: any free port)")
    p.add_argument("--open", action="store_true", help="open the page in the default browser")
    p.add_argument("--max-request-mb", type=float, default=4.0, metavar="MB",
                   help="largest request body accepted, in MiB (default 4: a 10000-point polygon is under 0.5); "
                        "a bigger one is refused with HTTP 413 before it is read, so memory stays bounded")
    p.epilog = """examples:
  interreal annotate out/ds                 # prints http://127.0.0.1:PORT/?token=... ; open it in a browser
  interreal annotate out/ds --port 8765 --open
keys on the page: left/right = previous/next frame, p = polygon, b = box, e = erase/paint,
c = click to segment (click on the object, shift+click or right click on what is not; the mask follows each click),
enter / double-click = close the polygon, escape = cancel the shape, 1-9 = choose object, ctrl+z = undo"""


def main(args) -> int:
    ds: Path = args.dataset
    if not ds.is_dir():
        raise InputError(f"{ds} is not a folder: give the dataset folder (with images/ inside)")
    if not (0 <= args.port < 65536):
        raise InputError(f"--port {args.port}: use 0 (any free port) or 1..65535")
    mb = getattr(args, "max_request_mb", 4.0)
    if not (mb > 0 and mb != float("inf")):
        raise InputError(f"--max-request-mb {mb}: give a positive size in MiB, e.g. 4")
    try:
        server = AnnotateServer(ds, host=args.host, port=args.port, max_request_mb=mb)
    except (OSError, UnicodeError) as exc:
        raise InputError(f"cannot listen on {args.host}:{args.port} ({exc}); choose another --host / --port") from None
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        others = server.remote_urls if args.host in ("0.0.0.0", "::", "") else [server.url]
        print(f"warning: listening on {args.host}: other machines can reach the app (they still need the token)"
              + "".join(f"\n  from another machine: {u}" for u in others))
    print(f"annotating {ds.resolve()}\nopen {server.url}\n(ctrl-c to stop; every edit is saved at once)", flush=True)
    if args.open:
        import webbrowser

        webbrowser.open(server.url)
    server.serve_forever()
    return 0
