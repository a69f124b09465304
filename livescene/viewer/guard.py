"""The local-server rules of `livescene view`, as ASGI middleware in front of the app.

A page open in the same browser must not be able to drive the viewer (it renders on this machine's cores and
writes into the run folder), and another machine must not reach it:
- the token printed at start is required: `?token=` on the page URL (then a per-port SameSite=strict cookie for
  page loads); every POST needs it in the `X-Livescene-Token` header, which a cross-site page cannot send;
- the Host header must name this server (127.0.0.1 / localhost / [::1] and the port): defeats DNS rebinding;
- an Origin header, when sent, must be this server too;
- a request body larger than `max_body` bytes is refused with 413 (by its Content-Length, and while it streams).
The same rules as `interreal annotate`'s server (interreal/annotate/server.py), which livescene may not import.
"""

from __future__ import annotations

import secrets
from typing import Any, Awaitable, Callable
from urllib.parse import parse_qs, unquote

TOKEN_HEADER = "x-livescene-token"
LOCAL_NAMES = ("127.0.0.1", "localhost", "[::1]")
MAX_BODY = 64 * 1024  # a view, its states and a command are a few hundred bytes

Scope = dict[str, Any]
Receive = Callable[[], Awaitable[dict[str, Any]]]
Send = Callable[[dict[str, Any]], Awaitable[None]]


def allowed_hosts(host: str, port: int) -> set[str]:
    """Host header values this server answers to (lower case, with the port)."""
    names = set(LOCAL_NAMES)
    if host not in ("0.0.0.0", "::", ""):
        names.add(f"[{host}]" if ":" in host else host)
    hosts = {f"{n}:{port}".lower() for n in names}
    if port == 80:  # browsers leave the default port out of the Host header
        hosts |= {n.lower() for n in names}
    return hosts


class LocalGuard:
    """`..` -> 404, foreign Host or Origin -> 403, missing / wrong token -> 403, body over the limit -> 413."""

    def __init__(self, app: Callable, token: str, hosts: set[str], cookie: str, max_body: int = MAX_BODY,
                 command: str = "livescene view"):
        self.app, self.token, self.hosts, self.cookie = app, token, hosts, cookie
        self.max_body, self.command = max_body, command

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "lifespan":
            return await self.app(scope, receive, send)
        if scope["type"] != "http":
            return await plain(send, 403, "forbidden")
        raw = (scope.get("raw_path") or scope.get("path", "").encode()).decode("latin-1")
        if ".." in scope.get("path", "") or ".." in unquote(unquote(raw)):
            return await plain(send, 404, "not found")
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        if headers.get("host", "").lower() not in self.hosts:
            return await plain(send, 403, "forbidden: this server answers only to " + ", ".join(sorted(self.hosts)))
        origin = headers.get("origin")
        if origin and origin.lower().split("://", 1)[-1] not in self.hosts:
            return await plain(send, 403, "forbidden: cross-origin request")
        if not self._token_ok(scope, headers):
            return await plain(send, 403, f"forbidden: open the URL with the token that `{self.command}` printed")
        length = headers.get("content-length", "0").strip()
        if not (length.isascii() and length.isdigit()):
            return await plain(send, 400, f"bad Content-Length {length[:40]!r}")
        if len(length) > 15 or int(length) > self.max_body:
            return await plain(send, 413, f"request body over the limit of {self.max_body} bytes")
        body = await read_body(receive, self.max_body)  # a chunked body is counted as it streams
        if body is None:
            return await plain(send, 413, f"request body over the limit of {self.max_body} bytes")
        return await self.app(scope, replay(body, receive), send)

    def _token_ok(self, scope: Scope, headers: dict[str, str]) -> bool:
        given = headers.get(TOKEN_HEADER)
        if scope.get("method", "GET") not in ("GET", "HEAD"):
            return given is not None and secrets.compare_digest(given.encode(), self.token.encode())
        if given is None:
            q = parse_qs(scope.get("query_string", b"").decode("latin-1")).get("token")
            given = q[0] if q else None
        if given is None:
            for part in headers.get("cookie", "").split(";"):
                name, _, value = part.strip().partition("=")
                if name == self.cookie:
                    given = value
        return given is not None and secrets.compare_digest(given.encode(), self.token.encode())


async def plain(send: Send, status: int, text: str) -> None:
    body = text.encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"text/plain; charset=utf-8"),
                            (b"content-length", str(len(body)).encode()),
                            (b"cache-control", b"no-store")]})
    await send({"type": "http.response.body", "body": body})


async def read_body(receive: Receive, limit: int) -> bytes | None:
    """The whole request body, or None as soon as more than `limit` bytes arrived (the rest is never read)."""
    chunks, size = [], 0
    while True:
        message = await receive()
        if message["type"] != "http.request":  # http.disconnect: the client has gone
            break
        chunk = message.get("body", b"")
        size += len(chunk)
        if size > limit:
            return None
        chunks.append(chunk)
        if not message.get("more_body", False):
            break
    return b"".join(chunks)


def replay(body: bytes, receive: Receive) -> Receive:
    """A receive() that hands the app the body already read, then passes on what the server sends next."""
    sent = False

    async def again() -> dict[str, Any]:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return again
