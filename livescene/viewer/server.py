"""The viewer's HTTP server: FastAPI routes over a `ViewerSession`, behind `LocalGuard`, served by uvicorn.

The local-server rules (token, Host / Origin checks, the body limit, a 500 without a traceback) are
`interreal.localserver`'s, shared with `interreal annotate`.
Routes (all need the token): GET / (the page), GET /static/NAME, GET /api/info,
POST /api/render (a PNG; 204 when a newer request superseded it), POST /api/save, POST /api/sweep,
GET /api/sweep (progress), POST /api/command. Bad input -> 400 with {"error": "..."}.

(No `from __future__ import annotations` here: FastAPI reads the route functions' annotations, and `Request` is
imported inside `create_app`, so they must be evaluated where the routes are defined.)
"""

import html
import json
import time
from pathlib import Path
from typing import Any

from interreal.errors import InterRealError, MissingExtraError
from interreal.localserver import LocalGuard, LocalServer, allowed_hosts

from .session import ViewError, ViewerSession, parse_view

STATIC_DIR = Path(__file__).resolve().parent.parent / "viewer_static"
STATIC_FILES = {"viewer.js": "text/javascript; charset=utf-8", "viewer.css": "text/css; charset=utf-8"}
NO_STORE = {"Cache-Control": "no-store"}
TOKEN_HEADER = "x-livescene-token"
MAX_BODY = 64 * 1024  # a view, its states and a command are a few hundred bytes
PAGE_HEADERS = {
    **NO_STORE, "X-Frame-Options": "DENY", "X-Content-Type-Options": "nosniff", "Referrer-Policy": "no-referrer",
    "Content-Security-Policy": "default-src 'self'; img-src 'self' blob: data:; script-src 'self'; style-src 'self'; "
                               "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'",
}


def require_web() -> None:
    try:
        import fastapi  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError as exc:
        raise MissingExtraError("web", "livescene view") from exc


def create_app(session: "ViewerSession", token: str, port: int, host: str = "127.0.0.1") -> LocalGuard:
    """The ASGI app for one session, one token and the port it is served on."""
    require_web()
    from fastapi import FastAPI, HTTPException, Request
    from fastapi.responses import HTMLResponse, JSONResponse, Response
    from starlette.concurrency import run_in_threadpool

    cookie = f"livescene_token_{port}"
    app = FastAPI(title="livescene view", docs_url=None, redoc_url=None, openapi_url=None)
    app.state.session = session

    @app.exception_handler(InterRealError)
    async def _bad(_req: Request, exc: InterRealError):
        return JSONResponse({"error": str(exc)}, status_code=400, headers=NO_STORE)

    async def body(request: Request) -> Any:
        try:
            return json.loads(await request.body())
        except (ValueError, UnicodeDecodeError) as exc:
            raise ViewError(f"the request body is not JSON ({exc})") from exc

    @app.get("/", response_class=HTMLResponse)
    def index():
        page = (STATIC_DIR / "index.html").read_text(encoding="utf-8")
        resp = HTMLResponse(page.replace("{{RUN}}", html.escape(Path(session.run.run_dir).name)),
                            headers=PAGE_HEADERS)
        resp.set_cookie(cookie, token, httponly=True, samesite="strict", path="/")
        return resp

    @app.get("/static/{name}")
    def static(name: str):
        if name not in STATIC_FILES:
            raise HTTPException(404)
        return Response((STATIC_DIR / name).read_bytes(), media_type=STATIC_FILES[name], headers=NO_STORE)

    @app.get("/api/info")
    def info():
        return JSONResponse(session.info(), headers=NO_STORE)

    @app.post("/api/render")
    async def render(request: Request):
        data = await body(request)
        view = parse_view(data, session.names)
        seq = data.get("seq", 0)
        if not isinstance(seq, int) or isinstance(seq, bool):
            raise ViewError(f"seq must be a whole number, got {seq!r}")
        out = await run_in_threadpool(session.render, view)
        if out is None:  # a newer request came in while this one waited
            return Response(status_code=204, headers={**NO_STORE, "X-Seq": str(seq), "X-Superseded": "1"})
        t = out.timing()
        headers = {**NO_STORE, "X-Seq": str(seq), "X-Image-Size": f"{out.w}x{out.h}",
                   "X-Render-Ms": str(t["render_ms"]), "X-Encode-Ms": str(t["encode_ms"]),
                   "X-Wait-Ms": str(t["wait_ms"]),
                   "Server-Timing": ", ".join(f"{k[:-3]};dur={v}" for k, v in t.items()),
                   "X-Unseen": json.dumps(out.unseen, ensure_ascii=True)}
        return Response(out.png, media_type="image/png", headers=headers)

    @app.post("/api/save")
    async def save(request: Request):
        view = parse_view(await body(request), session.names)
        t0 = time.perf_counter()
        paths = await run_in_threadpool(session.save, view)
        return JSONResponse({**paths, "ms": round((time.perf_counter() - t0) * 1e3, 1)}, headers=NO_STORE)

    @app.post("/api/sweep")
    async def sweep(request: Request):
        data = await body(request)
        view = parse_view(data, session.names)
        return JSONResponse(session.start_sweep(view, data.get("object"), data.get("count", 30), data.get("fps", 15)),
                            headers=NO_STORE)

    @app.get("/api/sweep")
    def sweep_status():
        return JSONResponse(session.sweep.status(), headers=NO_STORE)

    @app.post("/api/command")
    async def command(request: Request):
        data = await body(request)
        text = data.get("text") if isinstance(data, dict) else None
        return JSONResponse(await run_in_threadpool(session.command, text), headers=NO_STORE)

    return LocalGuard(app, token, allowed_hosts(host, port), cookie, max_body=MAX_BODY, token_header=TOKEN_HEADER,
                      command="livescene view")


class ViewerServer(LocalServer):
    """The viewer on a bound socket; `serve_forever()` in the foreground or `start()` in a thread (tests)."""

    def __init__(self, session: "ViewerSession", host: str = "127.0.0.1", port: int = 0, token: str | None = None):
        require_web()
        super().__init__(lambda tok, p: create_app(session, tok, p, host), host, port, token, name="viewer server")
