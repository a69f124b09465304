"""Bad-input corpus for the `interreal annotate` server: every malformed, oversized, hostile or out-of-dataset
request gets a 4xx with a message naming the problem, never a 500 or a traceback, and nothing outside the
dataset is read or written. Plus: a dataset whose labels file holds a non-numeric state still loads and the
bad entry can be overwritten from the page."""

from __future__ import annotations

import asyncio
import json
import socket
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("fastapi", reason="the 'web' extra is part of the dev environment")
from fastapi.testclient import TestClient  # noqa: E402
from test_annotate import HT, PORT, TOKEN, W, H, client, ds, raw_get  # noqa: E402,F401  (fixtures reused)

from interreal.annotate.server import AnnotateServer, create_app, machine_addresses  # noqa: E402
from interreal.atomic import write_image, write_npy  # noqa: E402
from interreal.conventions import index_to_onehot  # noqa: E402
from interreal.dataset import read_labels  # noqa: E402

BASE = f"http://127.0.0.1:{PORT}"
MiB = 1 << 20


def no_trace(r) -> None:
    assert r.status_code != 500, r.text
    assert "Traceback" not in r.text and 'File "' not in r.text


def error_of(r) -> str:
    try:
        doc = r.json()
    except ValueError:
        return r.text
    return str(doc.get("error", doc.get("detail", doc))) if isinstance(doc, dict) else str(doc)


@pytest.fixture
def door(client):
    assert client.post("/api/objects", json={"name": "door"}).status_code == 200
    return client


def _box(**over):
    op = {"object": 0, "name": "door", "shape": "box", "points": [[1, 1], [9, 9]], "mode": "paint", "versions": {}}
    op.update(over)
    return op


def _edit(**over):
    e = {"frame": "3", "object": "door", "value": 0.5, "base": None}
    e.update(over)
    return {"version": "0", "edits": [e]}


# ------------------------------------------------------------------------------------------------ malformed bodies
BODIES = [
    # (path, raw body, expected status, words the message must contain)
    ("/api/objects", b"{not json", 400, "not valid JSON"),
    ("/api/objects", b"", 400, "needs a JSON body"),
    ("/api/objects", b"[1, 2]", 400, "must be a JSON object"),
    ("/api/objects", b'"door"', 400, "must be a JSON object"),
    ("/api/objects", b"\xff\xfe{}", 400, "not UTF-8"),
    ("/api/objects", b"[" * 100000 + b"]" * 100000, 400, "nested too deeply"),
    ("/api/objects", b'{"name": 5}', 400, "'name' must be a string, not an integer"),
    ("/api/objects", b"{}", 400, "'name' is missing"),
    ("/api/objects", b'{"name": "x", "description": ["a"]}', 400, "'description' must be a string"),
    ("/api/objects/rename", b'{"old": null, "new": "x"}', 400, "'old' must be a string, not null"),
    ("/api/objects/rename", b'{"old": "door"}', 400, "'new' is missing"),
    ("/api/objects/describe", b'{"name": "door", "text": {"a": 1}}', 400, "'text' must be a string, not an object"),
    ("/api/labels", b'{"edits": "x"}', 400, "'edits' must be a list"),
    ("/api/labels", b'{"edits": []}', 400, "no edits given"),
    ("/api/labels", b'{"edits": [5]}', 400, "is not an object"),
    ("/api/labels", json.dumps(_edit(base="x")).encode(), 400, "'base'"),
    ("/api/labels", json.dumps(_edit(base=[1])).encode(), 400, "'base'"),
    ("/api/labels", json.dumps(_edit(base=True)).encode(), 400, "'base'"),
    ("/api/labels", json.dumps(_edit(value=True)).encode(), 400, "'value' must be a number"),
    ("/api/labels", json.dumps(_edit(value=[0.5])).encode(), 400, "'value' must be a number"),
    ("/api/labels", json.dumps(_edit(value="abc")).encode(), 400, "is not a number"),
    ("/api/labels", json.dumps(_edit(object=7)).encode(), 400, "'object' must be an object name"),
    ("/api/labels", json.dumps(_edit(frame={"a": 1})).encode(), 400, "is not a frame"),
    ("/api/labels", json.dumps(_edit(frame="\u0663")).encode(), 400, "ASCII digits"),  # arabic-indic 3
    ("/api/labels", json.dumps(_edit(frame="frame_\u0660\u0660\u0660\u0660\u0663")).encode(), 400, "ASCII digits"),
    ("/api/labels", json.dumps(_edit(frame=None)).encode(), 400, "is not a frame"),
    ("/api/labels", json.dumps({**_edit(), "version": 5}).encode(), 400, "'version' must be a string"),
    ("/api/labels", b'{"version": "0", "edits": [{"frame": "3", "object": "door", "value": NaN, "base": null}]}',
     400, "NaN is not a number"),
    ("/api/labels", b'{"version": "0", "edits": [{"frame": "3", "object": "door", "value": 0.5, "base": Infinity}]}',
     400, "Infinity is not a number"),
    ("/api/labels", b'{"version": "0", "edits": [{"frame": "3", "object": "door", "value": 1e999, "base": null}]}',
     400, "not a finite number"),
    ("/api/labels", b'{"version": "0", "edits": [{"frame": "3", "object": "door", "value": 1' + b"0" * 400 + b"}]}",
     400, "outside [0, 1]"),
    ("/api/labels", b'{"edits": [{"frame": "3", "object": "door", "value": 1' + b"0" * 5000 + b"}]}",
     400, "not valid JSON"),
    ("/api/keyframe/00003", json.dumps(_box(object="0")).encode(), 400, "'object' must be an integer, not a string"),
    ("/api/keyframe/00003", json.dumps(_box(object=True)).encode(), 400, "'object' must be an integer"),
    ("/api/keyframe/00003", json.dumps(_box(object=0.5)).encode(), 400, "'object' must be an integer"),
    ("/api/keyframe/00003", json.dumps(_box(points="abc")).encode(), 400, "list of [x, y] pairs"),
    ("/api/keyframe/00003", json.dumps(_box(points=[[1, 2, 3]])).encode(), 400, "[x, y] pairs"),
    ("/api/keyframe/00003", json.dumps(_box(points=[["1", 2], [3, 4]])).encode(), 400, "[x, y] pairs of numbers"),
    ("/api/keyframe/00003", b'{"object": 0, "shape": "box", "points": [[NaN, 1], [2, 2]]}', 400, "NaN"),
    ("/api/keyframe/00003", json.dumps(_box(shape="polygon", points=[[1e300, 0], [0, 1e300], [5, 5]])).encode(),
     400, "pixel coordinates"),
    ("/api/keyframe/00003", json.dumps(_box(points=[[0, 0]] * 10001)).encode(), 400, "at most 10000"),
    ("/api/keyframe/00003", json.dumps(_box(shape="circle")).encode(), 400, "use one of polygon, box"),
    ("/api/keyframe/00003", json.dumps(_box(mode=5)).encode(), 400, "'mode' must be a string"),
    ("/api/keyframe/00003", json.dumps(_box(versions="abc")).encode(), 400, "'versions' must be"),
    ("/api/keyframe/00003", json.dumps(_box(versions={"1": 5})).encode(), 400, "'versions' must be"),
    ("/api/keyframe/00003", json.dumps({"object": 0}).encode(), 400, "'points' is missing"),
    ("/api/keyframe/00003", json.dumps(_box(name=3)).encode(), 400, "'name' must be a string"),
    # the click tool: a click outside the 64x48 frame, an object that does not exist, malformed clicks
    ("/api/keyframe/00003/click", b'{"object": 0, "clicks": [[64, 5, true]]}', 400, "outside the 64x48 image"),
    ("/api/keyframe/00003/click", b'{"object": 0, "clicks": [[3, -0.5, false]]}', 400, "click 1 at (3, -0.5)"),
    ("/api/keyframe/00003/click", b'{"object": 3, "clicks": [[3, 3, true]]}', 400, "object id 3 does not exist"),
    ("/api/keyframe/00003/click", b'{"object": -2, "clicks": [[3, 3, true]]}', 400, "object id -2 does not exist"),
    ("/api/keyframe/00003/click", b'{"object": 0, "clicks": [[3, NaN, true]]}', 400, "NaN"),
    ("/api/keyframe/00003/click", b'{"object": 0, "clicks": [[3, 3, 1]]}', 400, "[x, y, positive]"),
    ("/api/keyframe/00003/click", b'{"object": 0, "clicks": [[3, 3, true]], "versions": 1}', 400, "'versions' must"),
    ("/api/keyframe/00003/click", json.dumps({"object": 0, "clicks": [[3, 3, True]] * 201}).encode(), 400,
     "at most 200"),
    ("/api/keyframe/00003/click", b'{"object": 0}', 400, "'clicks' is missing"),
    ("/api/keyframe/00003/undo", b'{"versions": [1]}', 400, "'versions' must be"),
    ("/api/keyframe/00003/delete", b'{"versions": "x"}', 400, "'versions' must be"),
    ("/api/keyframe/00003/delete", b"null", 400, "must be a JSON object"),
]


@pytest.mark.parametrize("path, body, status, words", BODIES, ids=[f"{i:02d}{b[0]}" for i, b in enumerate(BODIES)])
def test_malformed_body_is_400_naming_the_problem(door, ds, path, body, status, words):
    r = door.post(path, content=body, headers={"content-type": "application/json"})
    no_trace(r)
    assert r.status_code == status, r.text
    assert words in error_of(r), error_of(r)
    assert read_labels(ds) == {} and not (ds / "keyframes" / "00003.png").exists()  # nothing was written


# ------------------------------------------------------------------------------------------------ malformed paths
PATHS = [
    ("GET", "/api/image/\u0660\u0660\u0660\u0660\u0663"),  # arabic-indic 00003: str.isdigit() says yes
    ("GET", "/api/thumb/\u00b2"),  # superscript two: isdigit() but int() fails
    ("GET", "/api/keyframe/\U0001d7d1"),  # mathematical bold 3
    ("GET", "/api/mask/99999999999999999999"),
    ("GET", "/api/image/" + "9" * 5000),  # int() of > 4300 digits raises
    ("GET", "/api/image/-3"),
    ("GET", "/api/image/3.0"),
    ("GET", "/api/image/%00"),
    ("POST", "/api/keyframe/\u0660\u0660\u0660\u0660\u0663"),
    ("POST", "/api/keyframe/\u00b2/undo"),
    ("POST", "/api/keyframe/abc/delete"),
    ("POST", "/api/keyframe/42/click"),
]


@pytest.mark.parametrize("method, path", PATHS)
def test_malformed_frame_id_is_not_found(door, ds, method, path):
    if method == "GET":
        r = door.get(path)
    else:
        r = door.post(path, json=_box())
    no_trace(r)
    assert r.status_code == 404 and "no frame" in error_of(r) and "00042" in error_of(r)
    assert not (ds / "keyframes").exists()


@pytest.mark.parametrize("target", [
    "/static/../store.py", "/static/%2e%2e/store.py", "/static/%2E%2E%2Fstore.py", "/api/image/..%2f..%2fsecret.txt",
    "/api/image//etc/passwd", "/static//etc/passwd", "/static/%2fetc%2fpasswd", "/api/thumb/%2e%2e%2f%2e%2e%2fsecret.txt",
    "/static/app.js%00.py", "//etc/passwd",
])
def test_traversal_and_absolute_paths_read_nothing(ds, target):
    status, body = raw_get(create_app(ds, TOKEN, PORT), target)
    assert status == 404, (target, status, body[:200])
    assert b"outside the dataset" not in body and b"root:" not in body and b"import" not in body


# ------------------------------------------------------------------------------------------------ size limit
def asgi(app, method: str, path: str, headers: dict[str, str], chunks: list[bytes]) -> tuple[int, bytes, int]:
    """Send one request to the ASGI app with the body in `chunks`; (status, body, bytes of the body it read)."""
    sent = {"n": 0, "i": 0}
    out = {"status": 0, "body": b""}
    hs = [(k.lower().encode(), v.encode()) for k, v in {"host": f"127.0.0.1:{PORT}", **headers}.items()]
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": method, "scheme": "http",
             "path": path, "raw_path": path.encode(), "query_string": b"", "root_path": "", "headers": hs,
             "client": ("127.0.0.1", 1234), "server": ("127.0.0.1", PORT)}

    async def receive():
        i = sent["i"]
        if i >= len(chunks):
            await asyncio.sleep(3600)  # the client waits; a disconnect never comes in this test
        sent["i"] += 1
        sent["n"] += len(chunks[i])
        return {"type": "http.request", "body": chunks[i], "more_body": i + 1 < len(chunks)}

    async def send(msg):
        if msg["type"] == "http.response.start":
            out["status"] = msg["status"]
        elif msg["type"] == "http.response.body":
            out["body"] += msg.get("body", b"")

    asyncio.run(asyncio.wait_for(app(scope, receive, send), 30))
    return out["status"], out["body"], sent["n"]


def test_oversized_body_by_content_length_is_413_unread(ds):
    app = create_app(ds, TOKEN, PORT, max_request_mb=1)
    chunk = b"x" * 65536
    status, body, read = asgi(app, "POST", "/api/objects", {"x-interreal-token": TOKEN,
                                                           "content-length": str(52 * MiB)}, [chunk] * 832)
    assert status == 413 and b"52.0 MiB is over the limit of 1 MiB" in body and b"--max-request-mb" in body
    assert read == 0  # refused on the header: not one byte of the body was read


def test_oversized_chunked_body_is_413_after_the_limit(ds):
    app = create_app(ds, TOKEN, PORT, max_request_mb=1)
    chunk = b"x" * 65536
    status, body, read = asgi(app, "POST", "/api/labels", {"x-interreal-token": TOKEN,
                                                          "transfer-encoding": "chunked"}, [chunk] * 832)
    assert status == 413 and b"over the limit of 1 MiB" in body
    assert MiB < read <= MiB + len(chunk)  # stopped reading as soon as the limit was passed


def test_oversized_body_with_testclient_both_ways(ds):
    c = TestClient(create_app(ds, TOKEN, PORT, max_request_mb=0.5), base_url=BASE)
    big = json.dumps({"name": "x" * MiB}).encode()
    r = c.post("/api/objects", content=big, headers={**H, "content-type": "application/json"})
    assert r.status_code == 413 and "over the limit of 0.5 MiB" in r.text

    def stream():
        for _ in range(16):
            yield b" " * 65536

    r = c.post("/api/objects", content=stream(), headers={**H, "content-type": "application/json"})
    assert r.status_code == 413 and "over the limit" in r.text
    assert c.post("/api/objects", json={"name": "door"}, headers=H).status_code == 200  # a normal one still works


def test_a_large_legitimate_polygon_fits_the_default_limit(door, ds):
    t = np.linspace(0, 2 * np.pi, 10000, endpoint=False)
    pts = np.stack([32 + 20.123456789 * np.cos(t), 24 + 20.123456789 * np.sin(t)], 1).tolist()
    body = json.dumps(_box(shape="polygon", points=pts))
    assert len(body) > 300_000
    r = door.post("/api/keyframe/00003", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 200, r.text


def test_size_check_comes_after_the_token(ds):
    app = create_app(ds, TOKEN, PORT, max_request_mb=1)
    status, body, read = asgi(app, "POST", "/api/objects", {"content-length": str(52 * MiB)}, [b"x"])
    assert status == 403 and b"token" in body and read == 0


@pytest.mark.parametrize("length, status, words", [("-5", 400, b"bad Content-Length"), ("1e9", 400, b"bad Content"),
                                                    ("9" * 5000, 413, b"over the limit")])
def test_bad_content_length(ds, length, status, words):
    app = create_app(ds, TOKEN, PORT)
    got, body, read = asgi(app, "POST", "/api/objects", {"x-interreal-token": TOKEN, "content-length": length}, [b"{}"])
    assert got == status and words in body and read == 0


def test_chunked_stream_over_a_real_socket_is_cut_off(ds):
    srv = AnnotateServer(ds, token=TOKEN, max_request_mb=1).start()
    try:
        with socket.create_connection(("127.0.0.1", srv.port), timeout=10) as s:
            s.sendall(f"POST /api/objects HTTP/1.1\r\nHost: 127.0.0.1:{srv.port}\r\nX-Interreal-Token: {TOKEN}\r\n"
                      f"Content-Type: application/json\r\nTransfer-Encoding: chunked\r\n\r\n".encode())
            chunk = b"%x\r\n" % 65536 + b" " * 65536 + b"\r\n"
            sent = 0
            try:
                for _ in range(52 * 16):  # up to 52 MiB; the server answers and closes long before
                    s.sendall(chunk)
                    sent += 65536
            except OSError:
                pass
            data = b""
            try:
                while part := s.recv(65536):
                    data += part
            except OSError:
                pass
        assert data.startswith(b"HTTP/1.1 413"), data[:200]
        assert b"over the limit of 1 MiB" in data
        assert sent < 52 * MiB  # the server closed the connection instead of swallowing the rest
        import httpx

        r = httpx.get(f"http://127.0.0.1:{srv.port}/api/state", headers=H)
        assert r.status_code == 200  # and it still serves
    finally:
        srv.stop()


# ------------------------------------------------------------------------------------------------ token, Host, Origin
@pytest.mark.parametrize("headers, words", [
    ({"X-Interreal-Token": "wrong"}, "token"),
    ({"X-Interreal-Token": ""}, "token"),
    ({"X-Interreal-Token": (TOKEN + "\u00e9").encode("utf-8")}, "token"),
    ({"X-Interreal-Token": TOKEN, "host": "evil.example"}, "answers only to"),
    ({"X-Interreal-Token": TOKEN, "host": f"127.0.0.1.evil.example:{PORT}"}, "answers only to"),
    ({"X-Interreal-Token": TOKEN, "origin": "http://evil.example"}, "cross-origin"),
    ({"X-Interreal-Token": TOKEN, "origin": "null"}, "cross-origin"),
])
def test_bad_token_host_origin_are_403(ds, headers, words):
    c = TestClient(create_app(ds, TOKEN, PORT), base_url=BASE)
    r = c.post("/api/objects", json={"name": "x"}, headers=headers)
    assert r.status_code == 403 and words in r.text
    assert not (ds / "mapping.yaml").exists()


def test_wildcard_host_answers_to_this_machines_addresses_with_the_token(ds):
    names = machine_addresses("0.0.0.0")
    if not names:
        pytest.skip("this machine has no non-loopback address")
    c = TestClient(create_app(ds, TOKEN, PORT, host="0.0.0.0"), base_url=BASE)
    for name in names:
        assert c.get("/api/state", headers={"host": f"{name}:{PORT}", **H}).status_code == 200, name
    assert c.get("/api/state", headers={"host": f"{names[0]}:{PORT}"}).status_code == 403  # token still needed
    assert c.get("/api/state", headers={"host": f"evil.example:{PORT}", **H}).status_code == 403
    assert c.post("/api/objects", json={"name": "x"},
                  headers={"host": f"{names[0]}:{PORT}", "origin": f"http://{names[0]}:{PORT}", **H}).status_code == 200
    # a loopback-only server still refuses the machine's other addresses
    local = TestClient(create_app(ds, TOKEN, PORT), base_url=BASE)
    assert local.get("/api/state", headers={"host": f"{names[0]}:{PORT}", **H}).status_code == 403


def test_cli_help_documents_the_limit_and_host(capsys):
    from interreal.cli import main as cli

    with pytest.raises(SystemExit):
        cli(["annotate", "--help"])
    out = capsys.readouterr().out
    assert "--max-request-mb" in out and "413" in out and "0.0.0.0" in out


# ------------------------------------------------------------------------------------------------ symlinks out
def _outside_png(tmp: Path) -> Path:
    p = tmp / "outside.png"
    write_image(p, np.full((HT, W, 3), 7, np.uint8))
    return p


def _link(link: Path, target: Path) -> None:
    link.parent.mkdir(parents=True, exist_ok=True)
    link.symlink_to(target)


LINKS = ["image", "thumb", "image-draw", "keyframe-read", "keyframe-write", "keyframe-dir", "labelme", "mask",
         "labels-file"]


@pytest.mark.parametrize("case", LINKS)
def test_symlinks_out_of_the_dataset_are_refused(door, ds, tmp_path, case):
    outside = _outside_png(tmp_path)
    before = outside.read_bytes()
    if case in ("image", "thumb", "image-draw"):
        _link(ds / "images" / "frame_00009.png", outside)
        assert door.get("/api/state").status_code == 200  # the app lists the new frame
        r = {"image": lambda: door.get("/api/image/00009"), "thumb": lambda: door.get("/api/thumb/00009"),
             "image-draw": lambda: door.post("/api/keyframe/00009", json=_box())}[case]()
    elif case in ("keyframe-read", "keyframe-write"):
        _link(ds / "keyframes" / "00003.png", outside)
        r = door.get("/api/keyframe/00003") if case == "keyframe-read" else door.post("/api/keyframe/00003", json=_box())
    elif case == "keyframe-dir":
        (tmp_path / "elsewhere").mkdir()
        _link(ds / "keyframes", tmp_path / "elsewhere")
        r = door.post("/api/keyframe/00003", json=_box())
        assert list((tmp_path / "elsewhere").iterdir()) == []
    elif case == "labelme":
        (tmp_path / "shapes.json").write_text(json.dumps({"shapes": []}))
        _link(ds / "keyframes" / "00003.json", tmp_path / "shapes.json")
        r = door.get("/api/keyframe/00003")
    elif case == "mask":
        write_npy(tmp_path / "m.npy", index_to_onehot(np.zeros((HT, W), np.uint8), 1))
        _link(ds / "masks" / "00003.npy", tmp_path / "m.npy")
        r = door.get("/api/mask/00003")
    else:
        (tmp_path / "labels.yaml").write_text("frame_00003: {door: 0.25}\n")
        _link(ds / "key_frame_value.yaml", tmp_path / "labels.yaml")
        r = door.get("/api/state")
    no_trace(r)
    assert r.status_code == 403, r.text
    assert "outside the dataset" in error_of(r)
    assert b"\x89PNG" not in r.content and b"0.25" not in r.content
    assert outside.read_bytes() == before


# ------------------------------------------------------------------------------------------------ bad labels on disk
@pytest.mark.parametrize("content, shown", [
    ({"frame_00003": {"door": "abc"}}, "'abc' is not a number"),
    ({"frame_00003": "oops"}, "expected {object name: value}"),
    ({"frame_00003": {"door": float("nan")}}, "not a finite number"),
    ({"frame_00003": {"door": 5.0}}, "outside [0, 1]"),
    ({"frame_00003": {"door": [0.5]}}, "is not a number"),
    ({"frame_00003": {"door": True}}, "is not a number"),
])
def test_a_bad_label_on_disk_is_flagged_and_can_be_overwritten(door, ds, content, shown):
    (ds / "key_frame_value.yaml").write_text(yaml.safe_dump({**content, "frame_00006": {"door": 0.75}}))
    st = door.get("/api/state")
    assert st.status_code == 200, st.text
    doc = st.json()
    assert doc["labels"] == {"frame_00006": {"door": 0.75}}
    assert len(doc["bad_labels"]) == 1 and doc["bad_labels"][0]["frame"] == "frame_00003"
    assert shown in doc["bad_labels"][0]["problem"] and "key_frame_value.yaml" in doc["bad_labels"][0]["problem"]
    for path in ("/api/image/00003", "/api/thumb/00006", "/api/keyframe/00003", "/static/app.js", "/"):
        assert door.get(path).status_code == 200, path  # the rest of the app works
    r = door.post("/api/labels", json={"version": doc["labels_version"],
                                       "edits": [{"frame": "3", "object": "door", "value": 0.4, "base": None}]})
    assert r.status_code == 200, r.text
    assert r.json()["bad_labels"] == []
    assert read_labels(ds) == {"frame_00003": {"door": 0.4}, "frame_00006": {"door": 0.75}}


def test_untouched_bad_labels_are_kept_and_can_be_removed(door, ds):
    (ds / "key_frame_value.yaml").write_text("frame_00003: {door: abc}\n")
    r = door.post("/api/labels", json=_edit(frame="6", value=0.5))
    assert r.status_code == 200 and [b["frame"] for b in r.json()["bad_labels"]] == ["frame_00003"]
    assert yaml.safe_load((ds / "key_frame_value.yaml").read_text()) == {"frame_00003": {"door": "abc"},
                                                                         "frame_00006": {"door": 0.5}}
    r = door.post("/api/labels", json=_edit(frame="3", value=None))  # clear the bad entry
    assert r.status_code == 200 and r.json()["bad_labels"] == []
    assert read_labels(ds) == {"frame_00006": {"door": 0.5}}


@pytest.mark.parametrize("file, text, words", [
    ("key_frame_value.yaml", "frame_00003: {door: [unclosed\n", "not valid YAML"),
    ("key_frame_value.yaml", "- 1\n- 2\n", "got a list"),
    ("mapping.yaml", "{abc: door}\n", "mapping.yaml"),
    ("mapping.yaml", "[door]\n", "mapping.yaml"),
    ("prompts.yaml", "door: [a\n", "prompts.yaml"),
])
def test_unreadable_dataset_files_are_400_naming_the_file(door, ds, file, text, words):
    (ds / file).write_text(text)
    r = door.get("/api/state")
    no_trace(r)
    assert r.status_code == 400 and words in error_of(r), r.text


@pytest.mark.parametrize("case", ["corrupt-image", "corrupt-mask", "corrupt-keyframe", "labelme-garbage",
                                  "report-list"])
def test_corrupt_files_in_the_dataset_are_clear_errors(door, ds, case):
    if case == "corrupt-image":
        (ds / "images" / "frame_00006.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really")
        r = door.get("/api/thumb/00006")
        assert r.status_code == 400 and "frame_00006.png" in error_of(r)
    elif case == "corrupt-mask":
        (ds / "masks").mkdir()
        (ds / "masks" / "00003.npy").write_bytes(b"\x93NUMPY garbage")
        r = door.get("/api/mask/00003")
        assert r.status_code == 400 and "not a readable .npy" in error_of(r)
    elif case == "corrupt-keyframe":
        (ds / "keyframes").mkdir()
        (ds / "keyframes" / "00003.png").write_bytes(b"garbage")
        r = door.get("/api/keyframe/00003")
        assert r.status_code == 400 and "not a readable index PNG" in error_of(r)
    elif case == "labelme-garbage":
        (ds / "keyframes").mkdir()
        (ds / "keyframes" / "00003.json").write_text(json.dumps({"shapes": [{"label": ["door"], "shape_type": {}},
                                                                             5, {"label": "door", "points": "x"}]}))
        r = door.get("/api/keyframe/00003")
        assert r.status_code == 200 and r.json()["read_only"]
    else:
        (ds / "reports").mkdir()
        (ds / "reports" / "masks.json").write_text("[1, 2]")
        r = door.get("/api/state")
        assert r.status_code == 200 and r.json()["suggested"] == []
    no_trace(r)


def test_an_unexpected_exception_is_500_without_a_traceback(client, monkeypatch):
    store = client.app.app.state.store

    def broken(fid):
        raise RuntimeError("secret internal detail /home/user/x.py")

    monkeypatch.setattr(store, "thumbnail", broken)
    r = client.get("/api/thumb/00003")
    assert r.status_code == 500 and "internal error" in error_of(r) and "RuntimeError" in error_of(r)
    assert "secret internal detail" not in r.text and "Traceback" not in r.text
    assert client.get("/api/state").status_code == 200  # and the server goes on
