"""`interreal annotate` server: security (token, Host, `..`), the API, and merge-safe edits from two tabs."""

from __future__ import annotations

import json
import socket
import time

import numpy as np
import pytest

pytest.importorskip("fastapi", reason="the 'web' extra is part of the dev environment")
from fastapi.testclient import TestClient  # noqa: E402

from interreal.annotate.server import AnnotateServer, create_app  # noqa: E402
from interreal.annotate.store import _read_index_png  # noqa: E402
from interreal.atomic import write_image, write_json, write_npy  # noqa: E402
from interreal.conventions import index_to_onehot  # noqa: E402
from interreal.dataset import read_labels, read_mapping  # noqa: E402

TOKEN = "test-token-123"
PORT = 8765
H = {"X-Interreal-Token": TOKEN}
W, HT = 64, 48


@pytest.fixture
def ds(tmp_path):
    root = tmp_path / "ds"
    rng = np.random.default_rng(0)
    for i in (0, 3, 6):
        write_image(root / "images" / f"frame_{i:05d}.png", rng.integers(0, 255, (HT, W, 3), dtype=np.uint8))
    (tmp_path / "secret.txt").write_text("outside the dataset")
    return root


@pytest.fixture
def client(ds):
    c = TestClient(create_app(ds, TOKEN, PORT), base_url=f"http://127.0.0.1:{PORT}")
    c.headers.update(H)
    return c


def bare(ds) -> TestClient:
    return TestClient(create_app(ds, TOKEN, PORT), base_url=f"http://127.0.0.1:{PORT}")


def test_no_token_is_forbidden(ds):
    c = bare(ds)
    for path in ("/", "/api/state", "/api/image/00000", "/api/thumb/00000", "/static/app.js"):
        r = c.get(path)
        assert r.status_code == 403, path
        assert b"\x89PNG" not in r.content
    assert c.get("/api/state", headers={"X-Interreal-Token": "wrong"}).status_code == 403
    assert c.get("/api/state?token=wrong").status_code == 403
    assert c.post("/api/objects", json={"name": "x"}).status_code == 403
    assert not (ds / "mapping.yaml").exists()


def test_token_from_url_then_cookie_but_writes_need_header(ds):
    c = bare(ds)
    r = c.get(f"/?token={TOKEN}")
    assert r.status_code == 200 and "interreal annotate" in r.text
    assert f"interreal_token_{PORT}" in r.headers["set-cookie"] and "samesite=strict" in r.headers["set-cookie"].lower()
    csp = r.headers["content-security-policy"]
    assert "script-src 'self'" in csp and "frame-ancestors 'none'" in csp and r.headers["x-frame-options"] == "DENY"
    assert c.get("/api/state").status_code == 200  # the cookie now carries the token for GETs (images)
    assert c.post("/api/objects", json={"name": "x"}).status_code == 403  # a cookie alone cannot write
    assert c.post("/api/objects", json={"name": "x"}, headers=H).status_code == 200


@pytest.mark.parametrize("host", ["evil.example:8765", "attacker.test", "127.0.0.1:9999", "localhost", ""])
def test_foreign_host_is_forbidden(ds, host):
    c = bare(ds)
    r = c.get(f"/api/state?token={TOKEN}", headers={"host": host, **H})
    assert r.status_code == 403
    r = c.post("/api/objects", json={"name": "x"}, headers={"host": host, **H})
    assert r.status_code == 403
    assert not (ds / "mapping.yaml").exists()


def test_local_hosts_allowed_and_foreign_origin_refused(ds):
    c = bare(ds)
    for host in (f"127.0.0.1:{PORT}", f"localhost:{PORT}"):
        assert c.get("/api/state", headers={"host": host, **H}).status_code == 200
    r = c.post("/api/objects", json={"name": "x"}, headers={"origin": "http://evil.example", **H})
    assert r.status_code == 403


def raw_get(app, target: str, host: str = f"127.0.0.1:{PORT}") -> tuple[int, bytes]:
    """Send one GET with an exact request target to the ASGI app (HTTP clients normalise `..` away)."""
    import asyncio
    from urllib.parse import unquote

    path, _, query = target.partition("?")
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "GET", "scheme": "http",
             "path": unquote(path), "raw_path": path.encode(), "query_string": query.encode(), "root_path": "",
             "headers": [(b"host", host.encode()), (b"x-interreal-token", TOKEN.encode())],
             "client": ("127.0.0.1", 1234), "server": ("127.0.0.1", PORT)}
    out = {"status": 0, "body": b""}

    async def receive():
        return {"type": "http.request", "body": b"", "more_body": False}

    async def send(msg):
        if msg["type"] == "http.response.start":
            out["status"] = msg["status"]
        elif msg["type"] == "http.response.body":
            out["body"] += msg.get("body", b"")

    asyncio.run(app(scope, receive, send))
    return out["status"], out["body"]


@pytest.mark.parametrize("path", ["/static/../store.py", "/static/%2e%2e/store.py", "/static/%252e%252e/store.py",
                                  "/api/image/..%2F..%2Fsecret.txt", "/../secret.txt", "/api/thumb/%2E%2E",
                                  "/static/..%5c..%5csecret.txt"])
def test_dotdot_is_not_found_and_reads_nothing(ds, path):
    app = create_app(ds, TOKEN, PORT)
    assert raw_get(app, "/api/state")[0] == 200  # the helper itself works
    status, body = raw_get(app, path)
    assert status == 404
    assert b"outside the dataset" not in body and b"import" not in body


def test_dotdot_over_a_real_socket(ds):
    srv = AnnotateServer(ds, token=TOKEN).start()
    try:
        for target in ("/static/../../secret.txt", "/api/image/../../secret.txt", "/static/..%2f..%2fsecret.txt"):
            with socket.create_connection(("127.0.0.1", srv.port), timeout=5) as s:
                s.sendall(f"GET {target}?token={TOKEN} HTTP/1.1\r\nHost: 127.0.0.1:{srv.port}\r\n"
                          f"Connection: close\r\n\r\n".encode())
                data = b""
                while chunk := s.recv(65536):
                    data += chunk
            assert data.startswith(b"HTTP/1.1 404"), data[:80]
            assert b"outside the dataset" not in data
        assert srv.url.startswith(f"http://127.0.0.1:{srv.port}/?token=")
    finally:
        srv.stop()


def test_unknown_frames_and_static_files_404(client):
    for path in ("/api/image/00001", "/api/image/abc", "/api/thumb/99999", "/api/mask/00000", "/static/server.py",
                 "/api/keyframe/7"):
        assert client.get(path).status_code == 404, path


def test_images_thumbnails_and_state(client, ds):
    st = client.get("/api/state").json()
    assert [f["fid"] for f in st["frames"]] == ["00000", "00003", "00006"]
    assert st["objects"] == [] and st["labels"] == {} and st["suggested"] == []
    img = client.get("/api/image/00003")
    assert img.status_code == 200 and img.content == (ds / "images" / "frame_00003.png").read_bytes()
    th = client.get("/api/thumb/3")
    assert th.status_code == 200 and th.headers["content-type"] == "image/jpeg" and th.content[:2] == b"\xff\xd8"
    assert client.get("/static/app.js").headers["content-type"].startswith("text/javascript")


def test_masks_and_suggestions_from_the_masks_stage(client, ds):
    index = np.zeros((HT, W), np.uint8)
    index[10:20, 10:30] = 1
    write_npy(ds / "masks" / "00003.npy", index_to_onehot(index, 1))
    write_json(ds / "reports" / "masks.json", {"stage": "masks", "status": "ok",
                                               "suggested": [6, "frame_00000", {"fid": "00003", "reason": "low confidence"}, 1234]})
    st = client.get("/api/state").json()
    assert st["masks"] == ["00003"]
    assert st["suggested"] == [{"fid": "00006", "reason": ""}, {"fid": "00000", "reason": ""},
                               {"fid": "00003", "reason": "low confidence"}]
    import cv2

    png = client.get("/api/mask/00003").content
    got = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(got, index)


def _poly(oid, name, pts, versions, mode="paint", shape="polygon"):
    return {"object": oid, "name": name, "shape": shape, "points": pts, "mode": mode, "versions": versions}


def test_keyframe_polygon_box_erase(client, ds):
    client.post("/api/objects", json={"name": "door"})
    client.post("/api/objects", json={"name": "drawer"})
    kf = client.get("/api/keyframe/00003").json()
    assert kf["exists"] is False and kf["versions"] == {}
    r = client.post("/api/keyframe/00003", json=_poly(0, "door", [[10, 10], [30, 10], [30, 30], [10, 30]], {}))
    assert r.status_code == 200
    index = _read_index_png(ds / "keyframes" / "00003.png")
    assert index.shape == (HT, W) and index.dtype == np.uint8
    assert (index == 1).sum() == 400 and set(np.unique(index)) == {0, 1}
    assert read_mapping(ds / "keyframes") == {0: "door", 1: "drawer"}  # the --keyframes DIR format
    v = r.json()["versions"]
    r = client.post("/api/keyframe/00003", json=_poly(1, "drawer", [[20, 20], [40, 40]], v, shape="box"))
    assert r.status_code == 200
    index = _read_index_png(ds / "keyframes" / "00003.png")
    assert (index == 2).sum() == 400 and (index == 1).sum() == 400 - 100
    v = r.json()["versions"]
    r = client.post("/api/keyframe/00003", json=_poly(0, "door", [[0, 0], [64, 0], [64, 15], [0, 15]], v, mode="erase"))
    assert r.status_code == 200
    index = _read_index_png(ds / "keyframes" / "00003.png")
    assert (index == 1).sum() == 300 - 100 and (index == 2).sum() == 400  # erase leaves other objects alone
    assert client.get("/api/state").json()["keyframes"] == ["00003"]
    bad = client.post("/api/keyframe/00003", json=_poly(0, "door", [[1, 1], [2, 2]], r.json()["versions"]))
    assert bad.status_code == 400 and "three points" in bad.json()["error"]
    r = client.post("/api/keyframe/00003/delete", json={"versions": r.json()["versions"]})
    assert r.status_code == 200 and not (ds / "keyframes" / "00003.png").exists()


def test_two_tabs_keyframe_edits_merge_or_conflict(client, ds):
    client.post("/api/objects", json={"name": "door"})
    client.post("/api/objects", json={"name": "drawer"})
    client.post("/api/keyframe/00000", json=_poly(0, "door", [[0, 0], [10, 0], [10, 10], [0, 10]], {}))
    seen = client.get("/api/keyframe/00000").json()["versions"]  # both tabs read this
    a = client.post("/api/keyframe/00000", json=_poly(1, "drawer", [[40, 30], [50, 40]], seen, shape="box"))
    assert a.status_code == 200
    # tab B, stale: a stroke for the door that does not touch the drawer merges
    b = client.post("/api/keyframe/00000", json=_poly(0, "door", [[0, 20], [10, 20], [10, 30]], seen))
    assert b.status_code == 200
    index = _read_index_png(ds / "keyframes" / "00000.png")
    assert (index == 2).sum() == 100 and (index[:10, :10] == 1).all() and index[21, 8] == 1 and index[28, 2] == 0
    # tab B, stale: painting over the drawer that tab A changed since B read it is refused
    c = client.post("/api/keyframe/00000", json=_poly(0, "door", [[35, 25], [55, 45]], seen, shape="box"))
    assert c.status_code == 409 and "'drawer'" in c.json()["error"] and "not saved" in c.json()["error"]
    assert (_read_index_png(ds / "keyframes" / "00000.png") == index).all()


def test_two_tabs_labels_merge_or_conflict(client, ds):
    client.post("/api/objects", json={"name": "door"})
    client.post("/api/objects", json={"name": "drawer"})
    v0 = client.get("/api/state").json()["labels_version"]
    a = client.post("/api/labels", json={"version": v0, "edits": [{"frame": "frame_00003", "object": "door", "value": 0.3, "base": None}]})
    assert a.status_code == 200 and a.json()["merged"] is False
    b = client.post("/api/labels", json={"version": v0, "edits": [{"frame": "3", "object": "drawer", "value": 0.6, "base": None}]})
    assert b.status_code == 200 and b.json()["merged"] is True
    assert read_labels(ds) == {"frame_00003": {"door": 0.3, "drawer": 0.6}}
    c = client.post("/api/labels", json={"version": v0, "edits": [{"frame": "3", "object": "door", "value": 0.9, "base": None}]})
    assert c.status_code == 409 and "door on frame_00003 was changed elsewhere" in c.json()["error"]
    assert read_labels(ds) == {"frame_00003": {"door": 0.3, "drawer": 0.6}}
    d = client.post("/api/labels", json={"version": b.json()["version"], "edits": [{"frame": "3", "object": "door", "value": None, "base": 0.3}]})
    assert d.status_code == 200 and read_labels(ds) == {"frame_00003": {"drawer": 0.6}}


@pytest.mark.parametrize("edit, status, message", [
    ({"frame": "3", "object": "door", "value": float("nan"), "base": None}, 400, "not a finite number"),
    ({"frame": "3", "object": "door", "value": 1.5, "base": None}, 400, "outside [0, 1]"),
    ({"frame": "4", "object": "door", "value": 0.5, "base": None}, 400, "not among the dataset's frames"),
    ({"frame": "3", "object": "oven", "value": 0.5, "base": None}, 409, "unknown object 'oven'"),
])
def test_bad_label_edits(client, ds, edit, status, message):
    client.post("/api/objects", json={"name": "door"})
    import json as _json

    r = client.post("/api/labels", content=_json.dumps({"version": "0", "edits": [edit]}).replace("NaN", '"nan"'),
                    headers={"content-type": "application/json"})
    assert r.status_code == status and message in r.json()["error"]
    assert read_labels(ds) == {}


def test_add_and_rename_object_from_the_page(client, ds):
    st = client.post("/api/objects", json={"name": "door", "description": "the white one"}).json()
    assert st["objects"] == [{"id": 0, "name": "door"}] and st["prompts"] == {"door": "the white one"}
    assert client.post("/api/objects", json={"name": "door"}).status_code == 409
    client.post("/api/keyframe/00006", json=_poly(0, "door", [[1, 1], [9, 1], [9, 9]], {}))
    client.post("/api/labels", json={"version": "0", "edits": [{"frame": "6", "object": "door", "value": 1, "base": None}]})
    st = client.post("/api/objects/rename", json={"old": "door", "new": "fridge door"}).json()
    assert st["objects"] == [{"id": 0, "name": "fridge door"}]
    assert read_mapping(ds) == read_mapping(ds / "keyframes") == {0: "fridge door"}
    assert read_labels(ds) == {"frame_00006": {"fridge door": 1.0}}
    assert st["prompts"] == {"fridge door": "the white one"}
    stale = client.post("/api/keyframe/00006", json=_poly(0, "door", [[1, 1], [9, 1], [9, 9]], {}))
    assert stale.status_code == 409 and "now called 'fridge door'" in stale.json()["error"]
    assert client.post("/api/objects/rename", json={"old": "door", "new": "x"}).status_code == 409


def test_propagation_runs_in_background(client, ds, monkeypatch):
    """The button's endpoint runs interreal.masks.propagate(ds, ds/keyframes, progress=...) in a thread."""
    import sys
    import types

    calls = []

    def propagate(ds_, keyframes_dir, progress=None):
        calls.append((ds_, keyframes_dir))
        for i in range(3):
            progress(i + 1, 3)
        return {"frames": 3, "suggested": [6], "big": list(range(100))}

    fake = types.ModuleType("interreal.masks")
    fake.propagate = propagate
    monkeypatch.setitem(sys.modules, "interreal.masks", fake)
    import interreal

    monkeypatch.setattr(interreal, "masks", fake, raising=False)
    assert client.post("/api/propagate").status_code == 400  # no keyframe yet
    client.post("/api/objects", json={"name": "door"})
    client.post("/api/keyframe/00000", json=_poly(0, "door", [[1, 1], [9, 1], [9, 9]], {}))
    assert client.post("/api/propagate").json()["state"] == "running"
    for _ in range(100):
        st = client.get("/api/propagate").json()
        if st["state"] != "running":
            break
        time.sleep(0.05)
    assert st["state"] == "done" and st["done"] == 3 and st["total"] == 3
    assert st["result"] == {"frames": 3, "suggested": [6]}
    assert calls == [(ds.resolve(), ds.resolve() / "keyframes")]


def test_propagation_progress_from_mask_files(client, ds, monkeypatch):
    """With `progress: bool` (a tqdm switch, as interreal.masks has it) progress is read off DS/masks/*.npy."""
    import threading

    step = threading.Event()
    seen = {}

    def propagate(ds_, keyframes_dir, *, suggest: int = 5, progress: bool = True):
        seen["progress"] = progress
        for i, fid in enumerate(["00000", "00003", "00006"]):
            write_npy(ds_ / "masks" / f"{fid}.npy", index_to_onehot(np.zeros((HT, W), np.uint8), 1))
            if i == 1:
                step.wait(10)
        return {"frames": 3, "confidence_mean": {"door": 0.9}, "confidence": {"door": {"00000": 1.0}}}

    _install_fake_masks(monkeypatch, client, propagate)
    client.post("/api/propagate")
    for _ in range(200):
        st = client.get("/api/propagate").json()
        if st["done"] >= 2:
            break
        time.sleep(0.02)
    assert st["state"] == "running" and st["done"] == 2 and st["total"] == 3
    step.set()
    for _ in range(200):
        st = client.get("/api/propagate").json()
        if st["state"] != "running":
            break
        time.sleep(0.02)
    assert st["state"] == "done" and st["done"] == st["total"] == 3 and seen["progress"] is True
    assert st["result"] == {"frames": 3, "confidence_mean": {"door": 0.9}}
    assert client.post("/api/propagate").json()["state"] == "running"  # it can run again


def test_suggestions_from_the_masks_report_figures(client, ds):
    write_json(ds / "reports" / "masks.json", {"stage": "masks", "status": "ok", "figures": {
        "suggested_frames": ["00006", "00003"],
        "confidence": {"door": {"00006": 0.41, "00003": 0.7}, "drawer": {"00006": 0.9, "00003": 0.55}}}})
    assert client.get("/api/state").json()["suggested"] == [
        {"fid": "00006", "reason": "confidence 0.41 (door)"}, {"fid": "00003", "reason": "confidence 0.55 (drawer)"}]


def test_a_fine_parts_warning_is_shown_on_the_keyframe_with_most_of_them(client, ds):
    msg = "'door': 23 % of its keyframe masks are parts narrower than 5 px (lines, cables, thin rods) ..."
    report = {"stage": "masks", "status": "ok", "warnings": [
        {"cause": "masks-unreliable", "message": "'door': masks are unreliable", "object": "door"},
        {"cause": "masks-fine-parts", "message": msg, "object": "door"}],
        "figures": {"keyframes": ["00003", "00006"], "suggested_frames": ["00000"],
                    "fine_parts": {"width_px": 5, "share": {"door": 0.23}, "keyframe": {"door": "00006"}}}}
    write_json(ds / "reports" / "masks.json", report)
    assert client.get("/api/state").json()["suggested"] == [{"fid": "00006", "reason": msg},
                                                           {"fid": "00000", "reason": ""}]
    del report["figures"]["fine_parts"]  # a report without the keyframe: the first one
    write_json(ds / "reports" / "masks.json", report)
    assert client.get("/api/state").json()["suggested"][0] == {"fid": "00003", "reason": msg}


def test_propagation_failure_is_reported(client, ds, monkeypatch):

    def propagate(ds_, keyframes_dir):
        raise ValueError("keyframe 00000 has no object pixels")

    _install_fake_masks(monkeypatch, client, propagate)
    client.post("/api/propagate")
    for _ in range(100):
        st = client.get("/api/propagate").json()
        if st["state"] != "running":
            break
        time.sleep(0.05)
    assert st["state"] == "failed" and "no object pixels" in st["message"]


def test_cli_help_and_bad_dataset(tmp_path, capsys):
    from interreal.cli import main as cli

    with pytest.raises(SystemExit):
        cli(["annotate", "--help"])
    assert "token" in capsys.readouterr().out
    assert cli(["annotate", str(tmp_path / "missing")]) == 2
    assert "is not a folder" in capsys.readouterr().err


def test_labelme_keyframes_are_shown_not_edited(client, ds):
    client.post("/api/objects", json={"name": "door"})
    write_json(ds / "keyframes" / "00006.json", {"shapes": [
        {"label": "door", "shape_type": "rectangle", "points": [[10, 10], [20, 30]]},
        {"label": "door", "shape_type": "polygon", "points": [[40, 0], [50, 0], [50, 10], [40, 10]]},
        {"label": "unknown thing", "shape_type": "polygon", "points": [[0, 40], [5, 40], [5, 45]]}]})
    st = client.get("/api/state").json()
    assert st["keyframes"] == ["00006"] and st["labelme"] == ["00006"]
    kf = client.get("/api/keyframe/00006").json()
    assert kf["read_only"] and kf["exists"]
    import base64

    import cv2

    index = cv2.imdecode(np.frombuffer(base64.b64decode(kf["png"].split(",", 1)[1]), np.uint8), cv2.IMREAD_UNCHANGED)
    # the mask `interreal masks` propagates from this file (its unknown label aside): the box cut out by GrabCut,
    # the polygon as LabelMe draws it (outline included)
    from interreal.dataset import read_image_rgb
    from interreal.masks.labelme import rasterise

    doc = json.loads((ds / "keyframes" / "00006.json").read_text())
    write_json(ds.parent / "known" / "00006.json", {"shapes": [s for s in doc["shapes"] if s["label"] == "door"]})
    expect = rasterise(ds.parent / "known" / "00006.json", (W, HT), ["door"],
                       lambda: read_image_rgb(ds / "images" / "frame_00006.png"))
    assert np.array_equal(index, expect) and (index > 1).sum() == 0
    box = np.zeros_like(index, bool)
    box[10:30, 10:20] = True
    assert index[0:11, 40:51].all() and (index[~box] == 1).sum() == 11 * 11
    r = client.post("/api/keyframe/00006", json=_poly(0, "door", [[1, 1], [9, 1], [9, 9]], kf["versions"]))
    assert r.status_code == 400 and "LabelMe" in r.json()["error"]
    assert not (ds / "keyframes" / "00006.png").exists()


def test_undo_last_stroke(client, ds):
    client.post("/api/objects", json={"name": "door"})
    client.post("/api/objects", json={"name": "drawer"})
    assert client.post("/api/keyframe/00003/undo", json={"versions": {}}).status_code == 400  # nothing to undo
    a = client.post("/api/keyframe/00003", json=_poly(0, "door", [[0, 0], [10, 10]], {}, shape="box")).json()
    b = client.post("/api/keyframe/00003", json=_poly(1, "drawer", [[5, 5], [20, 20]], a["versions"], shape="box")).json()
    r = client.post("/api/keyframe/00003/undo", json={"versions": b["versions"]})
    assert r.status_code == 200 and r.json()["versions"] == a["versions"]
    index = _read_index_png(ds / "keyframes" / "00003.png")
    assert (index == 1).sum() == 100 and (index == 2).sum() == 0
    # another tab strokes after ours: our undo is refused rather than dropping its work
    c = client.post("/api/keyframe/00003", json=_poly(1, "drawer", [[30, 30], [40, 40]], r.json()["versions"], shape="box")).json()
    stale = client.post("/api/keyframe/00003/undo", json={"versions": r.json()["versions"]})
    assert stale.status_code == 409 and "cannot be undone" in stale.json()["error"]
    assert client.post("/api/keyframe/00003/undo", json={"versions": c["versions"]}).status_code == 200
    r = client.post("/api/keyframe/00003/undo", json={"versions": a["versions"]})
    assert r.status_code == 200 and r.json()["exists"] is False and not (ds / "keyframes" / "00003.png").exists()


def _install_fake_masks(monkeypatch, client, propagate) -> None:
    """Stand in `propagate` for interreal.masks, and give the app one object with one keyframe to propagate."""
    import sys
    import types

    import interreal

    fake = types.ModuleType("interreal.masks")
    fake.propagate = propagate
    monkeypatch.setitem(sys.modules, "interreal.masks", fake)
    monkeypatch.setattr(interreal, "masks", fake, raising=False)
    client.post("/api/objects", json={"name": "door"})
    client.post("/api/keyframe/00000", json=_poly(0, "door", [[1, 1], [9, 1], [9, 9]], {}))
