"""The annotation app's HTTP server (FastAPI on uvicorn), bound to 127.0.0.1 by default.

Security model: the app can write the dataset, so a web page open in the same browser must not reach it.
- Every request carries the per-run token (`?token=` on the page URL, then a cookie named per port for images
  and the `X-Interreal-Token` header, which writes require: a cross-site page can send neither).
- The Host header must name this server (127.0.0.1 / localhost / [::1] and the port): defeats DNS rebinding.
- Paths containing `..` get 404, and every file is found from a frame id, never from a path in the URL.
"""

from __future__ import annotations

import base64
import inspect
import secrets
import socket
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable
from urllib.parse import unquote

from ..errors import InterRealError, MissingExtraError
from .store import Conflict, DatasetStore, UnknownFrame, encode_index_png

STATIC_DIR = Path(__file__).resolve().parent / "static"
STATIC_FILES = {"app.js": "text/javascript; charset=utf-8", "app.css": "text/css; charset=utf-8"}
TOKEN_HEADER = "x-interreal-token"
LOCAL_NAMES = ("127.0.0.1", "localhost", "[::1]")


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
class Guard:
    """ASGI middleware: `..` -> 404, foreign Host -> 403, missing / wrong token -> 403 (before any route runs)."""

    def __init__(self, app, token: str, hosts: set[str], cookie: str):
        self.app, self.token, self.hosts, self.cookie = app, token, hosts, cookie

    async def __call__(self, scope, receive, send):
        if scope["type"] == "lifespan":
            return await self.app(scope, receive, send)
        if scope["type"] != "http":
            return await _plain(send, 403, "forbidden")
        raw = scope.get("raw_path") or scope.get("path", "").encode()
        raw_text = raw.decode("latin-1")
        if ".." in scope.get("path", "") or ".." in unquote(unquote(raw_text)):
            return await _plain(send, 404, "not found")
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        if headers.get("host", "").lower() not in self.hosts:
            return await _plain(send, 403, "forbidden: this server answers only to " + ", ".join(sorted(self.hosts)))
        origin = headers.get("origin")
        if origin and origin.lower().split("://", 1)[-1] not in self.hosts:
            return await _plain(send, 403, "forbidden: cross-origin request")
        if not self._token_ok(scope, headers):
            return await _plain(send, 403, "forbidden: open the URL with the token that `interreal annotate` printed")
        return await self.app(scope, receive, send)

    def _token_ok(self, scope, headers: dict[str, str]) -> bool:
        given = headers.get(TOKEN_HEADER)
        if scope.get("method", "GET") not in ("GET", "HEAD"):
            return given is not None and secrets.compare_digest(given.encode(), self.token.encode())
        if given is None:
            from urllib.parse import parse_qs

            q = parse_qs(scope.get("query_string", b"").decode("latin-1")).get("token")
            given = q[0] if q else None
        if given is None:
            for part in headers.get("cookie", "").split(";"):
                name, _, value = part.strip().partition("=")
                if name == self.cookie:
                    given = value
        return given is not None and secrets.compare_digest(given.encode(), self.token.encode())


async def _plain(send, status: int, text: str) -> None:
    body = text.encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"text/plain; charset=utf-8"), (b"content-length", str(len(body)).encode()),
                            (b"cache-control", b"no-store")]})
    await send({"type": "http.response.body", "body": body})


def allowed_hosts(host: str, port: int) -> set[str]:
    names = set(LOCAL_NAMES)
    if host not in ("0.0.0.0", "::", ""):
        names.add(f"[{host}]" if ":" in host else host)
    hosts = {f"{n}:{port}".lower() for n in names}
    if port == 80:  # browsers leave the default port out of the Host header
        hosts |= {n.lower() for n in names}
    return hosts


def create_app(ds: str | Path, token: str, port: int, host: str = "127.0.0.1"):
    """The ASGI app for one dataset, one token and the port it is served on."""
    _require_web()
    from fastapi import Body, FastAPI, HTTPException, Request
    from fastapi.responses import HTMLResponse, JSONResponse, Response

    store = DatasetStore(ds)
    prop = Propagation(store.ds, frames=lambda: len(store.frame_list()))
    cookie = f"interreal_token_{port}"
    app = FastAPI(title="interreal annotate", docs_url=None, redoc_url=None, openapi_url=None)
    app.state.store, app.state.propagation, app.state.token = store, prop, token

    @app.exception_handler(Conflict)
    async def _conflict(_req: Request, exc: Conflict):
        return JSONResponse({"error": str(exc), "conflict": True}, status_code=409)

    @app.exception_handler(InterRealError)
    async def _bad(_req: Request, exc: InterRealError):
        return JSONResponse({"error": str(exc)}, status_code=400)

    @app.exception_handler(UnknownFrame)
    async def _missing(_req: Request, exc: UnknownFrame):
        return JSONResponse({"error": f"no frame {exc} in this dataset"}, status_code=404)

    nocache = {"Cache-Control": "no-store"}
    page_headers = {
        **nocache, "X-Frame-Options": "DENY", "X-Content-Type-Options": "nosniff", "Referrer-Policy": "no-referrer",
        "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; script-src 'self'; style-src 'self'; "
                                   "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'",
    }

    @app.get("/", response_class=HTMLResponse)
    def index():
        html = (STATIC_DIR / "index.html").read_text(encoding="utf-8").replace("{{DATASET}}", _html(store.ds.name))
        resp = HTMLResponse(html, headers=page_headers)
        resp.set_cookie(cookie, token, httponly=True, samesite="strict", path="/")
        return resp

    @app.get("/static/{name}")
    def static(name: str):
        if name not in STATIC_FILES:
            raise HTTPException(404)
        return Response((STATIC_DIR / name).read_bytes(), media_type=STATIC_FILES[name], headers=nocache)

    def state() -> dict[str, Any]:
        store.refresh_frames()
        mapping, mversion = store.objects()
        labels, lversion = store.labels()
        from ..dataset import read_prompts

        return {
            "dataset": str(store.ds), "name": store.ds.name,
            "frames": store.frame_list(),
            "objects": [{"id": i, "name": n} for i, n in sorted(mapping.items())],
            "prompts": read_prompts(store.ds), "mapping_version": mversion,
            "labels": labels, "labels_version": lversion,
            "keyframes": store.keyframe_fids(), "keyframe_stamps": store.keyframe_stamps(),
            "labelme": store.labelme_fids(),
            "masks": store.mask_fids(), "suggested": store.suggested(), "propagation": prop.status(),
        }

    @app.get("/api/state")
    def get_state():
        return JSONResponse(state(), headers=nocache)

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
        return Response(data, media_type="image/png", headers=nocache)

    def keyframe_json(fid: str, index, versions) -> dict[str, Any]:
        png = None if index is None else "data:image/png;base64," + base64.b64encode(encode_index_png(index)).decode()
        return {"fid": store.fid(fid), "exists": index is not None, "versions": versions, "png": png,
                "read_only": store.fid(fid) in store.labelme_fids(), "keyframes": store.keyframe_fids()}

    @app.get("/api/keyframe/{fid}")
    def get_keyframe(fid: str):
        index, versions = store.keyframe(fid)
        return JSONResponse(keyframe_json(fid, index, versions), headers=nocache)

    @app.post("/api/keyframe/{fid}")
    def edit_keyframe(fid: str, op: dict = Body(...)):
        index, versions = store.edit_keyframe(fid, op)
        return keyframe_json(fid, index, versions)

    @app.post("/api/keyframe/{fid}/undo")
    def undo_keyframe(fid: str, body: dict = Body(...)):
        index, versions = store.undo_keyframe(fid, body.get("versions") or {})
        return keyframe_json(fid, index, versions)

    @app.post("/api/keyframe/{fid}/delete")
    def delete_keyframe(fid: str, body: dict = Body(...)):
        store.delete_keyframe(fid, body.get("versions") or {})
        return keyframe_json(fid, None, {})

    @app.post("/api/labels")
    def edit_labels(body: dict = Body(...)):
        return store.edit_labels(body.get("edits"), body.get("version"))

    @app.post("/api/objects")
    def add_object(body: dict = Body(...)):
        store.add_object(body.get("name", ""), body.get("description") or None)
        return state()

    @app.post("/api/objects/rename")
    def rename_object(body: dict = Body(...)):
        store.rename_object(str(body.get("old", "")), body.get("new", ""))
        return state()

    @app.post("/api/objects/describe")
    def describe_object(body: dict = Body(...)):
        store.describe_object(str(body.get("name", "")), str(body.get("text", "")))
        return state()

    @app.post("/api/propagate")
    def propagate():
        if not store.keyframe_fids():
            raise InterRealError("draw at least one keyframe mask before propagating")
        return prop.start(store.ds / "keyframes")

    @app.get("/api/propagate")
    def propagate_status():
        return JSONResponse(prop.status(), headers=nocache)

    return Guard(app, token, allowed_hosts(host, port), cookie)


def _html(text: str) -> str:
    import html

    return html.escape(text)


# --------------------------------------------------------------------------------------------------------------------
# Serving
# --------------------------------------------------------------------------------------------------------------------
class AnnotateServer:
    """A bound socket + uvicorn server; `serve_forever()` in the foreground or `start()` in a thread (tests)."""

    def __init__(self, ds: str | Path, host: str = "127.0.0.1", port: int = 0, token: str | None = None):
        _require_web()
        import uvicorn

        self.token = token or secrets.token_urlsafe(24)
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.sock = socket.socket(family, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind((host, port))
        self.host, self.port = host, self.sock.getsockname()[1]
        self.app = create_app(ds, self.token, self.port, host)
        config = uvicorn.Config(self.app, log_level="warning", access_log=False, lifespan="off")
        self.server = uvicorn.Server(config)
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        shown = "127.0.0.1" if self.host in ("0.0.0.0", "") else (f"[{self.host}]" if ":" in self.host else self.host)
        return f"http://{shown}:{self.port}/?token={self.token}"

    def serve_forever(self) -> None:
        self.server.run(sockets=[self.sock])

    def start(self, timeout: float = 20.0) -> "AnnotateServer":
        self._thread = threading.Thread(target=self.serve_forever, name="annotate-server", daemon=True)
        self._thread.start()
        t0 = time.time()
        while not self.server.started:
            if time.time() - t0 > timeout or not self._thread.is_alive():
                raise RuntimeError("the annotation server did not start")
            time.sleep(0.05)
        return self

    def stop(self) -> None:
        self.server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout=10)
        self.sock.close()
