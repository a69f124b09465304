"""The annotation app's HTTP server (FastAPI on uvicorn), bound to 127.0.0.1 by default.

Security model: the app can write the dataset, so a web page open in the same browser must not reach it. The
rules below are enforced by `interreal.localserver.LocalGuard`, shared with `livescene view`:
- Every request carries the per-run token (`?token=` on the page URL, then a cookie named per port for images
  and the `X-Interreal-Token` header, which writes require: a cross-site page can send neither).
- The Host header must name this server (127.0.0.1 / localhost / [::1] and the port): defeats DNS rebinding.
  With `--host 0.0.0.0` (or `::`) the machine's own names and addresses are allowed too, so other machines can
  connect as the warning says; they still need the token.
- Paths containing `..` get 404, and every file is found from a frame id, never from a path in the URL; a file
  that resolves outside the dataset (a symlink out of images/, keyframes/, masks/) is refused with 403.
- Request size: a body over the limit (`--max-request-mb`, default 4 MiB, many times the largest request the page
  sends: a 10 000-point polygon is under 0.5 MiB) is answered 413 before it is read: by its Content-Length, or,
  for a streamed (chunked) body, as soon as the bytes received pass the limit. The server holds at most the limit
  of any one body, so memory is bounded by it (parsing a body at the limit made of tiny JSON values costs about
  20x its size, ~80 MiB at 4 MiB; a 52 MiB body costs nothing: it is refused unread).
- Bad input is 400 with a message naming what was wrong (JSON bodies are type-checked field by field; NaN and
  Infinity are refused), an unknown frame 404, an edit conflict 409; an unexpected exception is logged on the
  server's terminal and answered 500 without a traceback.
"""

from __future__ import annotations

import base64
import html
import inspect
import json
import math
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from ..errors import InputError, InterRealError, MissingExtraError
from ..layout import KEYFRAMES_DIR
from ..localserver import LocalGuard, LocalServer, MiB, allowed_hosts
from ..localserver import machine_addresses  # noqa: F401  (the addresses a wildcard bind is reached by)
from .store import Conflict, DatasetStore, Outside, UnknownFrame, encode_index_png, finite_number

STATIC_DIR = Path(__file__).resolve().parent / "static"
STATIC_FILES = {"app.js": "text/javascript; charset=utf-8", "app.css": "text/css; charset=utf-8"}
TOKEN_HEADER = "x-interreal-token"
DEFAULT_MAX_REQUEST_MB = 4.0


def _require_web() -> None:
    try:
        import fastapi  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError as exc:
        raise MissingExtraError("web", "interreal annotate") from exc


# --------------------------------------------------------------------------------------------------------------------
# Propagation in the background
# --------------------------------------------------------------------------------------------------------------------
@dataclass
class Propagation:
    """Runs `interreal.masks.propagate(ds, ds/keyframes)` in a thread; the page polls `status()`.

    Progress: a `progress=callable(done, total)` callback when propagate() takes one; otherwise the count of
    DS/masks/*.npy files written since the run started (the masks stage writes each frame as it goes).
    """

    ds: Path
    frames: Callable[[], int]  # how many frames the dataset has
    state: str = "idle"  # idle | running | done | failed
    done: int = 0
    total: int = 0
    message: str = ""
    result: dict[str, Any] = field(default_factory=dict)
    started: float = 0.0
    finished: float = 0.0
    runs: int = 0
    callback: bool = False  # progress comes from the callback (else from the mask files)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _thread: threading.Thread | None = None

    def status(self) -> dict[str, Any]:
        with self._lock:
            if self.state == "running" and not self.callback:
                self.done, self.total = self._files_written(), self.frames()
            now = self.finished if self.state in ("done", "failed") else time.time()
            return {"state": self.state, "done": self.done, "total": self.total, "message": self.message,
                    "result": self.result, "elapsed_s": round(now - self.started, 1) if self.started else 0.0,
                    "runs": self.runs}

    def _files_written(self) -> int:
        folder = self.ds / "masks"
        if not folder.is_dir():
            return 0
        since = int(self.started * 1e9) - 1_000_000_000  # 1 s slack for coarse file-system clocks
        n = 0
        for p in folder.glob("*.npy"):
            try:
                n += p.stat().st_mtime_ns >= since
            except FileNotFoundError:
                continue
        return n

    def start(self, keyframes: Path) -> dict[str, Any]:
        with self._lock:
            if self.state == "running":
                return {"state": "running", "started": False}
            self.state, self.done, self.total, self.message, self.result = "running", 0, self.frames(), "starting", {}
            self.started, self.finished, self.callback = time.time(), 0.0, False
            self.runs += 1
            self._thread = threading.Thread(target=self._run, args=(keyframes,), name="propagate", daemon=True)
            self._thread.start()
        return {"state": "running", "started": True}

    def _progress(self, done: int, total: int) -> None:
        with self._lock:
            self.done, self.total = int(done), int(total)

    def _run(self, keyframes: Path) -> None:
        try:
            try:
                from .. import masks
            except ImportError as exc:
                raise InterRealError(f"mask propagation is not available in this build ({exc})") from exc
            fn: Callable[..., Any] | None = getattr(masks, "propagate", None)
            if fn is None:
                raise InterRealError("interreal.masks has no propagate() in this build")
            kwargs: dict[str, Any] = {}
            if _takes_callback(fn, "progress"):
                kwargs["progress"] = self._progress
                self.callback = True
            with self._lock:
                self.message = "propagating keyframe masks to every frame"
            out = fn(self.ds, keyframes, **kwargs)
            summary = _summarise(out)
            with self._lock:
                self.state, self.result, self.finished = "done", summary, time.time()
                self.done = self.total = int(summary.get("frames", self.total) or self.total)
                self.message = "done"
        except Exception as exc:  # the page shows the message; the server keeps running
            if not isinstance(exc, InterRealError):
                traceback.print_exc()
            with self._lock:
                self.state, self.finished = "failed", time.time()
                self.message = f"{type(exc).__name__}: {exc}"


def _takes_callback(fn: Callable[..., Any], name: str) -> bool:
    """Whether fn has a parameter `name` meant for a callable (not, say, `progress: bool` for a tqdm bar)."""
    try:
        param = inspect.signature(fn).parameters.get(name)
    except (TypeError, ValueError):
        return False
    if param is None:
        return False
    return "Callable" in str(param.annotation) or (param.default is None and param.annotation is inspect.Parameter.empty)


def _summarise(out: Any) -> dict[str, Any]:
    """The JSON-friendly scalars, short lists and small {name: number} dicts of propagate()'s result, for the page."""
    if not isinstance(out, dict):
        return {}
    keep: dict[str, Any] = {}
    for k, v in out.items():
        if isinstance(v, (bool, int, float, str)) or v is None:
            keep[str(k)] = v
        elif isinstance(v, (list, tuple)) and len(v) <= 50 and all(isinstance(x, (int, float, str)) for x in v):
            keep[str(k)] = list(v)
        elif isinstance(v, dict) and len(v) <= 20 and all(isinstance(x, (int, float)) for x in v.values()):
            keep[str(k)] = {str(a): b for a, b in v.items()}
    return keep


# --------------------------------------------------------------------------------------------------------------------
# The app
# --------------------------------------------------------------------------------------------------------------------
def create_app(ds: str | Path, token: str, port: int, host: str = "127.0.0.1",
               max_request_mb: float = DEFAULT_MAX_REQUEST_MB):
    """The ASGI app for one dataset, one token and the port it is served on."""
    _require_web()
    from fastapi import FastAPI

    if not (isinstance(max_request_mb, (int, float)) and math.isfinite(max_request_mb) and max_request_mb > 0):
        raise InputError(f"--max-request-mb {max_request_mb}: give a positive size in MiB, e.g. 4")

    store = DatasetStore(ds)
    prop = Propagation(store.ds, frames=lambda: len(store.frame_list()))
    cookie = f"interreal_token_{port}"
    app = FastAPI(title="interreal annotate", docs_url=None, redoc_url=None, openapi_url=None)
    app.state.store, app.state.propagation, app.state.token = store, prop, token
    _error_handlers(app)
    _page_routes(app, store, token, cookie)
    _read_routes(app, store, prop)
    _edit_routes(app, store, prop)
    return LocalGuard(app, token, allowed_hosts(host, port), cookie, max_body=int(max_request_mb * MiB),
                      token_header=TOKEN_HEADER, command="interreal annotate", limit_flag="--max-request-mb")


NOCACHE = {"Cache-Control": "no-store"}
PAGE_HEADERS = {
    **NOCACHE, "X-Frame-Options": "DENY", "X-Content-Type-Options": "nosniff", "Referrer-Policy": "no-referrer",
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; script-src 'self'; style-src 'self'; "
                               "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'",
}


def _error_handlers(app) -> None:
    """Every error as one JSON line: 409 a conflicting edit, 400 bad input, 404 no such frame, 403 outside the
    dataset, 500 a bug (its traceback on the server's terminal)."""
    from fastapi import Request
    from fastapi.exceptions import RequestValidationError
    from fastapi.responses import JSONResponse

    @app.exception_handler(Conflict)
    async def _conflict(_req: Request, exc: Conflict):
        return JSONResponse({"error": str(exc), "conflict": True}, status_code=409)

    @app.exception_handler(InterRealError)
    async def _bad(_req: Request, exc: InterRealError):
        return JSONResponse({"error": str(exc)}, status_code=400)

    @app.exception_handler(UnknownFrame)
    async def _missing(_req: Request, exc: UnknownFrame):
        return JSONResponse({"error": f"no frame {str(exc)[:40]!r} in this dataset (frame ids are the numbers "
                                      f"of DS/images/frame_NNNNN.*, e.g. 00042)"}, status_code=404)

    @app.exception_handler(Outside)
    async def _outside(_req: Request, exc: Outside):
        return JSONResponse({"error": str(exc)}, status_code=403)

    @app.exception_handler(RequestValidationError)
    async def _invalid(_req: Request, exc: RequestValidationError):
        return JSONResponse({"error": f"malformed request: {exc.errors()[:3]}"}, status_code=400)

    @app.exception_handler(Exception)
    async def _bug(req: Request, exc: Exception):  # ServerErrorMiddleware: LocalGuard logs the traceback
        return JSONResponse({"error": f"internal error in the annotation server ({type(exc).__name__}); the "
                                      f"details are on its terminal: please report it"}, status_code=500)


def _page_routes(app, store: DatasetStore, token: str, cookie: str) -> None:
    """The page (it sets the token cookie) and its static files."""
    from fastapi import HTTPException
    from fastapi.responses import HTMLResponse, Response

    @app.get("/", response_class=HTMLResponse)
    def index():
        html = (STATIC_DIR / "index.html").read_text(encoding="utf-8").replace("{{DATASET}}", _html(store.ds.name))
        resp = HTMLResponse(html, headers=PAGE_HEADERS)
        resp.set_cookie(cookie, token, httponly=True, samesite="strict", path="/")
        return resp

    @app.get("/static/{name}")
    def static(name: str):
        if name not in STATIC_FILES:
            raise HTTPException(404)
        return Response((STATIC_DIR / name).read_bytes(), media_type=STATIC_FILES[name], headers=NOCACHE)


def _state(store: DatasetStore, prop: Propagation) -> dict[str, Any]:
    """Everything the page shows besides pixels: frames, objects, labels, keyframes, masks, suggestions."""
    store.refresh_frames()
    mapping, mversion = store.objects()
    labels, lversion, bad_labels = store.labels()
    return {
        "dataset": str(store.ds), "name": store.ds.name,
        "frames": store.frame_list(),
        "objects": [{"id": i, "name": n} for i, n in sorted(mapping.items())],
        "prompts": store.prompts(), "mapping_version": mversion,
        "labels": labels, "labels_version": lversion, "bad_labels": bad_labels,
        "keyframes": store.keyframe_fids(), "keyframe_stamps": store.keyframe_stamps(),
        "labelme": store.labelme_fids(),
        "masks": store.mask_fids(), "suggested": store.suggested(), "propagation": prop.status(),
    }


def _keyframe_json(store: DatasetStore, fid: str, index, versions) -> dict[str, Any]:
    png = None if index is None else "data:image/png;base64," + base64.b64encode(encode_index_png(index)).decode()
    return {"fid": store.fid(fid), "exists": index is not None, "versions": versions, "png": png,
            "read_only": store.fid(fid) in store.labelme_fids(), "keyframes": store.keyframe_fids()}


def _read_routes(app, store: DatasetStore, prop: Propagation) -> None:
    """GET: the state, a frame's image, thumbnail, propagated mask and keyframe, the propagation's progress."""
    from fastapi import HTTPException
    from fastapi.responses import JSONResponse, Response

    @app.get("/api/state")
    def get_state():
        return JSONResponse(_state(store, prop), headers=NOCACHE)

    @app.get("/api/image/{fid}")
    def image(fid: str):
        data, media = store.image_bytes(fid)
        return Response(data, media_type=media, headers={"Cache-Control": "private, max-age=60"})

    @app.get("/api/thumb/{fid}")
    def thumb(fid: str):
        return Response(store.thumbnail(fid), media_type="image/jpeg", headers={"Cache-Control": "private, max-age=60"})

    @app.get("/api/mask/{fid}")
    def mask(fid: str):
        data = store.mask_png(fid)
        if data is None:
            raise HTTPException(404, "no propagated mask for this frame yet")
        return Response(data, media_type="image/png", headers=NOCACHE)

    @app.get("/api/keyframe/{fid}")
    def get_keyframe(fid: str):
        index, versions = store.keyframe(fid)
        return JSONResponse(_keyframe_json(store, fid, index, versions), headers=NOCACHE)

    @app.get("/api/propagate")
    def propagate_status():
        return JSONResponse(prop.status(), headers=NOCACHE)


def _edit_routes(app, store: DatasetStore, prop: Propagation) -> None:
    """POST: keyframe strokes (paint, erase, undo, delete), labels, objects, and starting propagation."""
    from fastapi import Depends, Request

    async def body(request: Request) -> Fields:
        return Fields(parse_json(await request.body()), request.url.path)

    body.__annotations__ = {"request": Request, "return": Fields}  # FastAPI reads them; Request is a local import

    @app.post("/api/keyframe/{fid}")
    def edit_keyframe(fid: str, b: Fields = Depends(body)):
        op = {"object": b.integer("object"), "name": b.text("name", None),
              "shape": b.choice("shape", ("polygon", "box", "found")), "points": b.points("points"),
              "mode": b.choice("mode", ("paint", "erase")), "versions": b.versions("versions")}
        index, versions = store.edit_keyframe(fid, op)
        return _keyframe_json(store, fid, index, versions)

    @app.post("/api/keyframe/{fid}/click")
    def click_keyframe(fid: str, b: Fields = Depends(body)):
        store.fid(fid)  # an unknown frame is a 404 whatever the body says
        op = {"object": b.integer("object"), "name": b.text("name", None), "shape": "clicks",
              "clicks": b.clicks("clicks"), "versions": b.versions("versions")}
        index, versions = store.edit_keyframe(fid, op)
        return _keyframe_json(store, fid, index, versions)

    @app.post("/api/keyframe/{fid}/undo")
    def undo_keyframe(fid: str, b: Fields = Depends(body)):
        index, versions = store.undo_keyframe(fid, b.versions("versions"))
        return _keyframe_json(store, fid, index, versions)

    @app.post("/api/keyframe/{fid}/delete")
    def delete_keyframe(fid: str, b: Fields = Depends(body)):
        store.delete_keyframe(fid, b.versions("versions"))
        return _keyframe_json(store, fid, None, {})

    @app.post("/api/labels")
    def edit_labels(b: Fields = Depends(body)):
        return store.edit_labels(b.edits("edits"), b.text("version", None))

    @app.post("/api/objects")
    def add_object(b: Fields = Depends(body)):
        store.add_object(b.text("name"), b.text("description", None) or None)
        return _state(store, prop)

    @app.post("/api/objects/rename")
    def rename_object(b: Fields = Depends(body)):
        store.rename_object(b.text("old"), b.text("new"))
        return _state(store, prop)

    @app.post("/api/objects/describe")
    def describe_object(b: Fields = Depends(body)):
        store.describe_object(b.text("name"), b.text("text"))
        return _state(store, prop)

    @app.post("/api/propagate")
    def propagate():
        if not store.keyframe_fids():
            raise InterRealError("draw at least one keyframe mask before propagating")
        return prop.start(store.inside(store.ds / KEYFRAMES_DIR))


# --------------------------------------------------------------------------------------------------------------------
# Request bodies
# --------------------------------------------------------------------------------------------------------------------
_REQUIRED = object()
MAX_POINTS = 10000  # a polygon's vertices; the page sends far fewer


def parse_json(raw: bytes) -> Any:
    """The JSON document of a request body; InputError (HTTP 400) naming what is wrong with it."""
    if not raw.strip():
        raise InputError("this request needs a JSON body")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise InputError("the body is not UTF-8 text (send JSON)") from None
    try:
        return json.loads(text, parse_constant=_no_constant)
    except RecursionError:
        raise InputError("the JSON body is nested too deeply") from None
    except ValueError as exc:  # JSONDecodeError, NaN / Infinity, a number of thousands of digits
        raise InputError(f"the body is not valid JSON: {str(exc)[:120]}") from None


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number (send a finite number or null)")


def _kind(value: Any) -> str:
    """The JSON name of a value's type, for messages."""
    if value is None:
        return "null"
    for t, name in ((bool, "true/false"), (str, "a string"), (int, "an integer"), (float, "a number"),
                    (list, "a list"), (dict, "an object")):
        if isinstance(value, t):
            return name
    return type(value).__name__


class Fields:
    """A JSON object body read field by field with the type each must have: a missing or mistyped field is an
    InputError (HTTP 400) naming the field, what it must be and what it was."""

    def __init__(self, doc: Any, where: str):
        if not isinstance(doc, dict):
            raise InputError(f"{where}: the body must be a JSON object {{...}}, not {_kind(doc)}")
        self.doc, self.where = doc, where

    def _get(self, key: str, default: Any) -> Any:
        """The field's value; `default` when it is absent or null, unless it is required (then null is wrong)."""
        if default is not _REQUIRED and self.doc.get(key) is None:
            return default
        if key not in self.doc:
            raise InputError(f"{self.where}: the field {key!r} is missing")
        return self.doc[key]

    def _wrong(self, key: str, want: str) -> InputError:
        return InputError(f"{self.where}: {key!r} must be {want}, not {_kind(self.doc[key])}")

    def text(self, key: str, default: Any = _REQUIRED) -> Any:
        value = self._get(key, default)
        if value is not default and not isinstance(value, str):
            raise self._wrong(key, "a string")
        return value

    def integer(self, key: str, default: Any = _REQUIRED) -> Any:
        value = self._get(key, default)
        if value is not default and (isinstance(value, bool) or not isinstance(value, int)):
            raise self._wrong(key, "an integer")
        return value

    def choice(self, key: str, options: tuple[str, ...]) -> str:
        value = self.text(key, options[0])
        if value not in options:
            raise InputError(f"{self.where}: {key!r} is {value[:40]!r}; use one of {', '.join(options)}")
        return value

    def versions(self, key: str) -> dict[str, str]:
        """The {index value: hash} map read with a keyframe ({} when absent)."""
        value = self._get(key, {})
        if not isinstance(value, dict) or not all(isinstance(v, str) for v in value.values()):
            raise self._wrong(key, "the object of versions read with the keyframe ({\"1\": \"hash\", ...})")
        return value

    def points(self, key: str) -> list[list[float]]:
        value = self._get(key, _REQUIRED)
        if not isinstance(value, list):
            raise self._wrong(key, "a list of [x, y] pairs")
        if len(value) > MAX_POINTS:
            raise InputError(f"{self.where}: {len(value)} points; a shape may have at most {MAX_POINTS}")
        for p in value:
            if not (isinstance(p, list) and len(p) == 2
                    and all(finite_number(c) for c in p)):
                raise InputError(f"{self.where}: {key!r} must be a list of [x, y] pairs of numbers; "
                                 f"found {json.dumps(p)[:40]}")
        return value

    def clicks(self, key: str) -> list[list[Any]]:
        """[[x, y, positive], ...]: image pixels and true on the object, false on what is not."""
        value = self._get(key, _REQUIRED)
        if not isinstance(value, list):
            raise self._wrong(key, "a list of [x, y, positive] clicks")
        if not value:
            raise InputError(f"{self.where}: no clicks given")
        for c in value:
            if not (isinstance(c, list) and len(c) == 3 and all(finite_number(v) for v in c[:2])
                    and isinstance(c[2], bool)):
                raise InputError(f"{self.where}: {key!r} must be a list of [x, y, positive] (numbers, numbers, "
                                 f"true/false); found {json.dumps(c)[:40]}")
        return value

    def edits(self, key: str) -> list[dict[str, Any]]:
        value = self._get(key, _REQUIRED)
        if not isinstance(value, list):
            raise self._wrong(key, "a list of {frame, object, value, base}")
        if not value:
            raise InputError(f"{self.where}: no edits given")
        return value


def _html(text: str) -> str:
    return html.escape(text)


# --------------------------------------------------------------------------------------------------------------------
# Serving
# --------------------------------------------------------------------------------------------------------------------
class AnnotateServer(LocalServer):
    """The annotation app on a bound socket; `serve_forever()` in the foreground or `start()` in a thread (tests)."""

    def __init__(self, ds: str | Path, host: str = "127.0.0.1", port: int = 0, token: str | None = None,
                 max_request_mb: float = DEFAULT_MAX_REQUEST_MB):
        _require_web()
        super().__init__(lambda tok, p: create_app(ds, tok, p, host, max_request_mb=max_request_mb),
                         host, port, token, name="annotation server")
