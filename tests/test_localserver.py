"""interreal.localserver: the guard both local web apps serve behind, on a bare ASGI app (its parameters: the token
header, the command named in messages, the body limit and its flag; the catch-all 500), the viewer getting the
catch-all too, and the threaded server base (a failed app leaves no socket bound)."""

from __future__ import annotations

import asyncio
import logging
import socket
from types import SimpleNamespace

import pytest

from interreal.localserver import LocalGuard, LocalServer, allowed_hosts

TOKEN = "localserver-test-token"
PORT = 8767


async def echo(scope, receive, send):
    """The app behind the guard: answers 200 with the body it was given; /boom raises, /late raises mid-answer."""
    if scope["path"] == "/boom":
        raise RuntimeError("secret internal detail /home/user/x.py")
    message = await receive()
    await send({"type": "http.response.start", "status": 200, "headers": []})
    if scope["path"] == "/late":
        raise RuntimeError("after the answer started")
    await send({"type": "http.response.body", "body": message.get("body", b"")})


def guard(**kw) -> LocalGuard:
    args = {"max_body": 64 * 1024, "token_header": "X-Livescene-Token", "command": "livescene view"} | kw
    return LocalGuard(echo, TOKEN, allowed_hosts("127.0.0.1", PORT), f"t_{PORT}", **args)


def call(app, method: str, path: str, headers: dict[str, str], chunks: list[bytes] = (b"",)) -> tuple[list, bytes]:
    """One request through the ASGI app; (the http.response.start messages, the body)."""
    hs = [(k.lower().encode(), v.encode()) for k, v in {"host": f"127.0.0.1:{PORT}", **headers}.items()]
    scope = {"type": "http", "method": method, "path": path, "raw_path": path.encode(), "query_string": b"",
             "headers": hs}
    todo, starts, body = list(chunks), [], []

    async def receive():
        chunk = todo.pop(0) if todo else b""
        return {"type": "http.request", "body": chunk, "more_body": bool(todo)}

    async def send(msg):
        (starts if msg["type"] == "http.response.start" else body).append(msg)

    asyncio.run(asyncio.wait_for(app(scope, receive, send), 10))
    return starts, b"".join(m.get("body", b"") for m in body)


def test_token_header_and_command_are_the_apps():
    app = guard()
    starts, body = call(app, "POST", "/x", {"x-interreal-token": TOKEN}, [b"{}"])  # the other app's header
    assert starts[0]["status"] == 403 and b"`livescene view` printed" in body
    starts, body = call(app, "POST", "/x", {"x-livescene-token": TOKEN}, [b"{}"])
    assert starts[0]["status"] == 200 and body == b"{}"
    starts, _ = call(app, "GET", "/x", {"cookie": f"other=1; t_{PORT}={TOKEN}"})
    assert starts[0]["status"] == 200  # a page load may use the per-port cookie
    starts, _ = call(app, "POST", "/x", {"cookie": f"t_{PORT}={TOKEN}"}, [b"{}"])
    assert starts[0]["status"] == 403  # a write never
    starts, _ = call(app, "GET", "/a/%2e%2e/x", {"x-livescene-token": TOKEN})
    assert starts[0]["status"] == 404


def test_body_limit_messages_name_the_limit_and_its_flag():
    viewer = guard()
    starts, body = call(viewer, "POST", "/x", {"x-livescene-token": TOKEN, "content-length": "100000"}, [b"x"])
    assert starts[0]["status"] == 413 and body == b"request body of 97.7 KiB is over the limit of 64 KiB"
    assert (b"connection", b"close") in starts[0]["headers"]
    starts, body = call(viewer, "POST", "/x", {"x-livescene-token": TOKEN}, [b"x" * 40_000] * 2)  # streamed
    assert starts[0]["status"] == 413 and body == b"request body is over the limit of 64 KiB"
    annotate = guard(max_body=1 << 21, token_header="X-Interreal-Token", command="interreal annotate",
                     limit_flag="--max-request-mb")
    starts, body = call(annotate, "POST", "/x", {"x-interreal-token": TOKEN, "content-length": str(3 << 20)})
    assert body == b"request body of 3.0 MiB is over the limit of 2 MiB (interreal annotate --max-request-mb)"


def test_an_escaping_exception_is_logged_and_answered_500_without_a_traceback(caplog):
    with caplog.at_level(logging.ERROR, logger="interreal.localserver"):
        starts, body = call(guard(), "GET", "/boom", {"x-livescene-token": TOKEN})
    assert starts[0]["status"] == 500 and b"internal error in the `livescene view` server" in body
    assert b"secret" not in body and b"Traceback" not in body
    assert "secret internal detail" in caplog.text and "Traceback" in caplog.text
    starts, _ = call(guard(), "GET", "/late", {"x-livescene-token": TOKEN})
    assert [m["status"] for m in starts] == [200]  # the answer had started: no second one
    with pytest.raises(RuntimeError):
        call(guard(catch_all=False), "GET", "/boom", {"x-livescene-token": TOKEN})


def test_the_viewer_gets_the_catch_all():
    pytest.importorskip("fastapi", reason="the 'web' extra is part of the dev environment")
    from fastapi.testclient import TestClient

    from livescene.viewer import create_app

    def info():
        raise RuntimeError("secret internal detail")

    session = SimpleNamespace(info=info, names=["door"], run=SimpleNamespace(run_dir="run"))
    app = create_app(session, TOKEN, PORT)
    assert isinstance(app, LocalGuard) and app.max_body == 64 * 1024
    r = TestClient(app, base_url=f"http://127.0.0.1:{PORT}").get("/api/info", headers={"X-Livescene-Token": TOKEN})
    assert r.status_code == 500 and "secret" not in r.text and "Traceback" not in r.text


def test_a_failing_app_leaves_no_socket_bound():
    pytest.importorskip("uvicorn", reason="the 'web' extra is part of the dev environment")
    seen = {}

    def broken(token: str, port: int):
        seen["port"] = port
        raise ValueError("bad option")

    with pytest.raises(ValueError):
        LocalServer(broken, host="127.0.0.1", port=0)
    with socket.socket() as s:  # the port is free again
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", seen["port"]))
    srv = LocalServer(lambda token, port: guard(), host="0.0.0.0", port=0, token=TOKEN)
    try:
        assert srv.url == f"http://127.0.0.1:{srv.port}/?token={TOKEN}"  # a wildcard bind is opened via loopback
    finally:
        srv.sock.close()
