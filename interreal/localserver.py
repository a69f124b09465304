"""The rules every local web app of the toolkit serves under (`interreal annotate`, `livescene view`).

A web page open in the same browser must not be able to drive such an app (they write files and use this
machine's cores), and nothing but this machine, or the machines a wildcard bind names, may reach it:
- the token printed at start is required: `?token=` on the page URL, then a per-port SameSite=strict cookie for
  page loads and images; every other method (POST) needs it in the app's token header, which a cross-site page
  cannot send;
- the Host header must name this server (127.0.0.1 / localhost / [::1], the bound address, and for a wildcard bind
  the machine's own names and addresses, never an arbitrary name): defeats DNS rebinding;
- an Origin header, when sent, must be this server too; paths containing `..` get 404;
- a request body over the limit is refused with 413 before it is read (by its Content-Length), or as soon as a
  streamed body passes it: the server never holds more than the limit of any one body;
- an exception escaping the app is logged on the server's terminal and answered 500 without a traceback.

This module imports nothing of `interreal` or `livescene`, so both packages may use it (docs/architecture.md).
"""

from __future__ import annotations

import ipaddress
import logging
import secrets
import socket
import struct
import threading
import time
import traceback
from pathlib import Path
from typing import Any, Awaitable, Callable, TypeVar
from urllib.parse import parse_qs, unquote

try:
    import fcntl
except ImportError:  # pragma: no cover - not on Windows: interface addresses come from /proc only
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger("interreal.localserver")

LOCAL_NAMES = ("127.0.0.1", "localhost", "[::1]")
WILDCARD_HOSTS = ("0.0.0.0", "::", "")
MiB = 1 << 20

Scope = dict[str, Any]
Receive = Callable[[], Awaitable[dict[str, Any]]]
Send = Callable[[dict[str, Any]], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]
Server = TypeVar("Server", bound="LocalServer")


# --------------------------------------------------------------------------------------------------------------------
# Who may connect
# --------------------------------------------------------------------------------------------------------------------
def allowed_hosts(host: str, port: int) -> set[str]:
    """Host header values this server answers to: loopback names, the bound address, and for a wildcard bind the
    machine's own names and addresses (never an arbitrary name: that is what stops DNS rebinding)."""
    names = set(LOCAL_NAMES)
    if host not in WILDCARD_HOSTS:
        names.add(f"[{host}]" if ":" in host else host)
    names |= set(machine_addresses(host))
    hosts = {f"{n}:{port}".lower() for n in names}
    if port == 80:  # browsers leave the default port out of the Host header
        hosts |= {n.lower() for n in names}
    return hosts


def machine_addresses(host: str) -> list[str]:
    """The names and addresses other machines may use to reach a server bound to a wildcard `host`.

    The host name, its fully qualified name, what they resolve to, every interface address (Linux), and the
    address of the default route. IPv4 only for 0.0.0.0; both families for `::` (a dual-stack socket).
    """
    if host not in WILDCARD_HOSTS:
        return []
    names: set[str] = set()
    for name in (socket.gethostname(), socket.getfqdn()):
        if name:
            names.add(name)
            try:
                names |= {info[4][0] for info in socket.getaddrinfo(name, None)}
            except (OSError, UnicodeError):
                pass
    names |= _interface_addresses()
    for family, target in ((socket.AF_INET, "192.0.2.1"), (socket.AF_INET6, "2001:db8::1")):
        try:  # connect() on UDP sends nothing: it only picks the interface of the default route
            with socket.socket(family, socket.SOCK_DGRAM) as s:
                s.connect((target, 9))
                names.add(s.getsockname()[0])
        except OSError:
            pass
    out = []
    for name in names:
        name = name.split("%", 1)[0]
        try:
            ip = ipaddress.ip_address(name)
        except ValueError:
            if name.lower() != "localhost":
                out.append(name.lower())
            continue
        if ip.is_loopback or ip.is_unspecified or ip.is_link_local or (ip.version == 6 and host == "0.0.0.0"):
            continue
        out.append(f"[{ip}]" if ip.version == 6 else str(ip))
    return sorted(set(out))


def _interface_addresses() -> set[str]:
    """IPv4 addresses of every network interface (Linux ioctl) and IPv6 ones from /proc; empty elsewhere."""
    out: set[str] = set()
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for _, name in socket.if_nameindex():
                try:
                    req = struct.pack("256s", name.encode()[:15])
                    out.add(socket.inet_ntoa(fcntl.ioctl(s.fileno(), 0x8915, req)[20:24]))  # SIOCGIFADDR
                except OSError:
                    continue
    except (ImportError, OSError, AttributeError):
        pass
    try:
        for line in Path("/proc/net/if_inet6").read_text().splitlines():
            raw = line.split()[0]
            out.add(str(ipaddress.IPv6Address(bytes.fromhex(raw))))
    except (OSError, ValueError, IndexError):
        pass
    return out


# --------------------------------------------------------------------------------------------------------------------
# The guard
# --------------------------------------------------------------------------------------------------------------------
class LocalGuard:
    """ASGI middleware, before any route runs: `..` -> 404, foreign Host / Origin -> 403, missing or wrong token
    -> 403, body over `max_body` bytes -> 413 (never buffered past the limit); with `catch_all`, an exception
    escaping the app is logged here and answered 500 without a traceback.

    `token_header` is the header POSTs carry the token in, `command` names the command in messages (whose token
    to use, which server failed), `limit_flag` the option that sets the body limit, when there is one.
    """

    def __init__(self, app: ASGIApp, token: str, hosts: set[str], cookie: str, *, max_body: int, token_header: str,
                 command: str, limit_flag: str | None = None, catch_all: bool = True):
        self.app, self.token, self.hosts, self.cookie, self.max_body = app, token, hosts, cookie, max_body
        self.token_header, self.command, self.limit_flag = token_header.lower(), command, limit_flag
        self.catch_all = catch_all

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not self.catch_all:
            return await self._checked(scope, receive, send)
        started = False

        async def tracking_send(message: dict[str, Any]) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            return await self._checked(scope, receive, tracking_send)
        except Exception:  # a server bug: the client gets a line, the terminal the traceback
            log.error("%s: unexpected error on %s %s\n%s", self.command, scope.get("method"), scope.get("path"),
                      traceback.format_exc())
            if not started:
                await plain(send, 500, f"internal error in the `{self.command}` server (details on its terminal); "
                                       "please report it", close=True)

    async def _checked(self, scope: Scope, receive: Receive, send: Send) -> None:
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
        length = headers.get("content-length")
        if length is not None:
            if not (length.isascii() and length.strip().isdigit()):
                return await plain(send, 400, f"bad Content-Length {length[:40]!r}", close=True)
            size = int(length.strip()) if len(length.strip()) <= 15 else 10 ** 15  # (int() refuses 5000 digits)
            if size > self.max_body:
                return await plain(send, 413, f"request body of {self._size(size, '.1f')} is over the limit of "
                                              f"{self._limit()}", close=True)
        body = await read_body(receive, self.max_body)  # a chunked body is counted as it streams
        if body is None:
            return await plain(send, 413, f"request body is over the limit of {self._limit()}", close=True)
        return await self.app(scope, replay(body, receive), send)

    def _size(self, n: int, spec: str = "g") -> str:
        """`n` bytes in the unit the limit reads best in (MiB from 100 KiB up, else KiB)."""
        unit, name = (MiB, "MiB") if self.max_body >= 100 * 1024 else (1024, "KiB")
        return f"{n / unit:{spec}} {name}"

    def _limit(self) -> str:
        flag = f" ({self.command} {self.limit_flag})" if self.limit_flag else ""
        return self._size(self.max_body) + flag

    def _token_ok(self, scope: Scope, headers: dict[str, str]) -> bool:
        given = headers.get(self.token_header)
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


async def plain(send: Send, status: int, text: str, close: bool = False) -> None:
    """A text/plain answer, never cached; `close` when the body was not (all) read, so the connection cannot
    carry another request."""
    body = text.encode()
    headers = [(b"content-type", b"text/plain; charset=utf-8"), (b"content-length", str(len(body)).encode()),
               (b"cache-control", b"no-store")]
    if close:
        headers.append((b"connection", b"close"))
    await send({"type": "http.response.start", "status": status, "headers": headers})
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
    """An ASGI receive that gives the app the body read already, then waits on the real one (for disconnects)."""
    sent = False

    async def again() -> dict[str, Any]:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return again


# --------------------------------------------------------------------------------------------------------------------
# Serving
# --------------------------------------------------------------------------------------------------------------------
class LocalServer:
    """A bound socket + uvicorn server for the app `make_app(token, port)` returns (the app needs the port for its
    cookie and Host checks, so the socket is bound first); `serve_forever()` in the foreground or `start()` in a
    thread (tests). Needs uvicorn: callers check their web extra first."""

    def __init__(self, make_app: Callable[[str, int], ASGIApp], host: str = "127.0.0.1", port: int = 0,
                 token: str | None = None, name: str = "local server"):
        import uvicorn

        self.token, self.name = token or secrets.token_urlsafe(24), name
        self.sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self.sock.bind((host, port))
            self.host, self.port = host, self.sock.getsockname()[1]
            self.app = make_app(self.token, self.port)
        except BaseException:  # a bad option or a port in use: no socket left open
            self.sock.close()
            raise
        self.server = uvicorn.Server(uvicorn.Config(self.app, log_level="warning", access_log=False, lifespan="off"))
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        """The page's URL on this machine (a wildcard bind is reached through 127.0.0.1)."""
        if self.host in WILDCARD_HOSTS:
            shown = "127.0.0.1"
        else:
            shown = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{shown}:{self.port}/?token={self.token}"

    @property
    def remote_urls(self) -> list[str]:
        """The page's URL as other machines may open it (wildcard binds only; IP addresses first)."""
        names = machine_addresses(self.host)
        names.sort(key=lambda n: (not (n[0].isdigit() or n.startswith("[")), n))
        return [f"http://{n}:{self.port}/?token={self.token}" for n in names]

    def serve_forever(self) -> None:
        self.server.run(sockets=[self.sock])

    def start(self: Server, timeout: float = 20.0) -> Server:
        self._thread = threading.Thread(target=self.serve_forever, name=self.name.replace(" ", "-"), daemon=True)
        self._thread.start()
        t0 = time.time()
        while not self.server.started:
            if time.time() - t0 > timeout or not self._thread.is_alive():
                raise RuntimeError(f"the {self.name} did not start")
            time.sleep(0.05)
        return self

    def stop(self) -> None:
        self.server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout=10)
        self.sock.close()
