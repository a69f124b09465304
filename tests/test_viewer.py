"""`livescene view` server (no browser): the local-server rules (token, Host, Origin, body size), 400 for bad
views, PNGs of the asked size, an object's slider changes the image where the object is and nowhere else, stale
requests dropped, saved views that `livescene render --cameras` reads back, sweep videos, commands."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("fastapi", reason="the 'web' extra is part of the dev environment")
from fastapi.testclient import TestClient  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_livescene_toy import ToyScene, toy_dataset  # noqa: E402

from livescene.viewer import ViewerServer, create_app  # noqa: E402
from livescene.viewer.session import LatestWins, View, ViewerSession  # noqa: E402

TOKEN = "viewer-test-token"
PORT = 8766
H = {"X-Livescene-Token": TOKEN}
BASE = f"http://127.0.0.1:{PORT}"


def train_tiny_run(root: Path, steps: int = 300, frames: int = 24) -> Path:
    """A one-object toy room (a door on a hinge) fitted with the tiny preset. 300 steps: the door is learned
    (about 15 s on an idle core, a minute on a crowded one); 2 steps: a valid run in a few seconds, for the tests
    that need the server and not a good picture."""
    from livescene.config import load_preset
    from livescene.trainer import train

    ds = toy_dataset(root / "ds", n_frames=frames, size=(40, 30))
    cfg = load_preset("tiny")
    cfg.steps = steps
    if steps < cfg.eval_every:
        cfg.eval_every = cfg.ckpt_every = 0
    train(ds, root / "run", cfg, device="cpu", show_progress=False)
    return root / "run"


pytestmark = pytest.mark.usefixtures("one_thread")


def open_session(run_dir: Path):
    from livescene.trainer import load_run

    return ViewerSession(load_run(run_dir, device="cpu"), low=40, sharp=80)


@pytest.fixture(scope="module")
def session(one_thread, tmp_path_factory):
    return open_session(train_tiny_run(tmp_path_factory.mktemp("viewer_quick"), steps=2, frames=8))


@pytest.fixture(scope="module")
def trained(one_thread, tmp_path_factory):
    return open_session(train_tiny_run(tmp_path_factory.mktemp("viewer_trained")))


def app_client(session) -> TestClient:
    c = TestClient(create_app(session, TOKEN, PORT), base_url=BASE)
    c.headers.update(H)
    return c


@pytest.fixture(scope="module")
def client(session):
    return app_client(session)


def bare(session, host: str = "127.0.0.1") -> TestClient:
    return TestClient(create_app(session, TOKEN, PORT), base_url=f"http://{host}:{PORT}")


def camera(session, index: int | None = None, w: int = 40, h: int = 30) -> dict:
    info = session.info()
    cam = info["cameras"][info["start"] if index is None else index]
    return {"c2w": cam["c2w"], "w": w, "h": h, "fov_y": cam["fov_y"]}


def body(session, states: dict | None = None, **cam) -> dict:
    return {"camera": camera(session, **cam), "states": {"door": 0.5} if states is None else states}


def decode(png: bytes) -> np.ndarray:
    import cv2

    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None, "not a PNG"
    return img[..., ::-1].astype(np.float32) / 255


# ----------------------------------------------------------------------------------------------------------------
# Local-server rules
# ----------------------------------------------------------------------------------------------------------------
def test_no_token_is_forbidden(session):
    c = bare(session)
    for path in ("/", "/api/info", "/static/viewer.js", "/api/sweep"):
        assert c.get(path).status_code == 403, path
    assert c.get("/api/info?token=wrong").status_code == 403
    assert c.get("/api/info", headers={"X-Livescene-Token": "wrong"}).status_code == 403
    r = c.post("/api/render", json=body(session))
    assert r.status_code == 403 and b"\x89PNG" not in r.content


def test_token_in_url_then_cookie_but_posts_need_the_header(session):
    c = bare(session)
    r = c.get(f"/?token={TOKEN}")
    assert r.status_code == 200 and "livescene view" in r.text
    assert "default-src 'self'" in r.headers["content-security-policy"]
    assert "samesite=strict" in r.headers["set-cookie"].lower()
    assert c.get("/api/info").status_code == 200  # the cookie now
    assert c.get("/static/viewer.js").status_code == 200
    assert c.post("/api/render", json=body(session)).status_code == 403  # a cookie alone never renders / writes
    assert c.post("/api/save", json=body(session)).status_code == 403
    assert c.get("/static/../viewer/server.py").status_code == 404
    assert c.get("/static/%2e%2e/viewer/server.py").status_code == 404
    assert c.get("/static/index.html").status_code == 404  # only the listed static files


def test_foreign_host_and_origin_are_refused(session):
    evil = bare(session, host="evil.example")  # DNS rebinding: the right IP under a foreign name
    assert evil.get(f"/api/info?token={TOKEN}").status_code == 403
    c = bare(session)
    c.headers.update(H)
    assert c.get("/api/info", headers={"host": f"127.0.0.1:{PORT + 1}"}).status_code == 403
    assert c.post("/api/render", json=body(session), headers={"origin": "http://evil.example"}).status_code == 403
    assert c.post("/api/render", json=body(session), headers={"origin": f"http://localhost:{PORT}"}).status_code == 200
    assert c.get("/api/info", headers={"host": f"localhost:{PORT}"}).status_code == 200


def test_request_size_limit(client, session):
    big = body(session)
    big["pad"] = "x" * 100_000
    r = client.post("/api/render", json=big)
    assert r.status_code == 413
    # no Content-Length (chunked): counted while it streams
    chunks = (b"x" * 20_000 for _ in range(5))
    r = client.post("/api/render", content=chunks, headers={"content-type": "application/json"})
    assert r.status_code == 413


def test_server_binds_localhost_with_a_printed_token(session):
    srv = ViewerServer(session, port=0).start()
    try:
        assert srv.sock.getsockname()[0] == "127.0.0.1"
        assert srv.url.startswith(f"http://127.0.0.1:{srv.port}/?token=") and len(srv.token) >= 24
        with urllib.request.urlopen(srv.url.replace("/?", "/api/info?"), timeout=30) as r:
            assert json.loads(r.read())["objects"] == ["door"]
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(f"http://127.0.0.1:{srv.port}/api/info", timeout=30)
        assert err.value.code == 403
    finally:
        srv.stop()


# ----------------------------------------------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------------------------------------------
def test_bad_views_get_400_naming_the_problem(client, session):
    good = body(session)
    c2w = good["camera"]["c2w"]
    cases = {
        "finite number": {**good, "states": {"door": "NaN-as-text"}},
        "unknown object 'fridge'": {**good, "states": {"fridge": 0.5}},
        "states are in [0, 1]": {**good, "states": {"door": 1.5}},
        "is -0.1": {**good, "states": {"door": -0.1}},
        "16 numbers": {**good, "camera": {**good["camera"], "c2w": c2w[:15]}},
        "rigid transform": {**good, "camera": {**good["camera"], "c2w": [2 * x for x in c2w[:12]] + c2w[12:]}},
        "camera.c2w entries": {**good, "camera": {**good["camera"], "c2w": [None] + c2w[1:]}},
        "camera.w and camera.h": {**good, "camera": {**good["camera"], "w": 100000}},
        "camera.fov_y": {**good, "camera": {**good["camera"], "fov_y": 0}},
        "layer": {**good, "layer": "normals"},
        "expected": {"states": {}},
    }
    for needle, data in cases.items():
        r = client.post("/api/render", json=data)
        assert r.status_code == 400, (needle, r.status_code, r.text)
        assert needle in r.json()["error"], (needle, r.json())
    raw = json.dumps(good).replace('"door": 0.5', '"door": NaN')  # Python's json reads NaN: refused all the same
    r = client.post("/api/render", content=raw, headers={"content-type": "application/json"})
    assert r.status_code == 400 and "finite" in r.json()["error"]
    r = client.post("/api/render", content=b"{not json", headers={"content-type": "application/json"})
    assert r.status_code == 400 and "not JSON" in r.json()["error"]
    assert client.post("/api/sweep", json={**good, "object": "fridge"}).status_code == 400
    assert client.post("/api/sweep", json={**good, "object": "door", "count": 10_000}).status_code == 400
    assert client.post("/api/command", json={"text": ""}).status_code == 400


# ----------------------------------------------------------------------------------------------------------------
# Rendering
# ----------------------------------------------------------------------------------------------------------------
def test_render_returns_a_png_of_the_asked_size_with_timings(client, session):
    for w, h, layer in ((40, 30, "rgb"), (36, 52, "objects"), (24, 18, "depth")):
        r = client.post("/api/render", json={**body(session, w=w, h=h), "layer": layer, "seq": 7})
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        assert decode(r.content).shape == (h, w, 3)
        assert r.headers["x-image-size"] == f"{w}x{h}" and r.headers["x-seq"] == "7"
        assert float(r.headers["x-render-ms"]) > 0 and "render;dur=" in r.headers["server-timing"]
        assert isinstance(json.loads(r.headers["x-unseen"]), dict)


@pytest.mark.slow
def test_a_slider_changes_the_image_where_the_object_is_and_nowhere_else(trained):
    """The door from closed to open, seen from a training camera: the pixels that change are the door's (the
    simulator's truth in either state), the walls the model also calls static do not change."""
    session, client = trained, app_client(trained)
    run = session.run
    i = run.views.train[5]
    w, h = 80, 60
    cam = camera(session, index=int(i), w=w, h=h)
    imgs = []
    for v in (0.0, 1.0):
        r = client.post("/api/render", json={"camera": cam, "states": {"door": v}})
        assert r.status_code == 200
        imgs.append(decode(r.content))
    diff = np.abs(imgs[0] - imgs[1]).max(-1)
    view = View(np.asarray(cam["c2w"]).reshape(4, 4), w, h, cam["fov_y"], {})
    intr = view.intrinsics()
    _, _, idx0 = ToyScene(1).render(view.c2w, [0.0], intr)
    _, _, idx1 = ToyScene(1).render(view.c2w, [1.0], intr)
    door = (idx0 == 1) | (idx1 == 1)
    assert door.mean() > 0.03  # the door is in view
    from livescene.render import render_view

    probs = [render_view(run, view.c2w, intr, {"door": v})["probs"][..., 0] for v in (0.0, 1.0)]
    static = ~door & (probs[0] < 0.5) & (probs[1] < 0.5)
    assert static.mean() > 0.5
    assert diff[door].mean() > 0.05, diff[door].mean()  # the door moves
    assert np.percentile(diff[static], 95) < 0.02, np.percentile(diff[static], 95)  # nothing else does
    # the object layer shows the door where the model puts it
    r = client.post("/api/render", json={"camera": cam, "states": {"door": 1.0}, "layer": "objects"})
    objects = decode(r.content).max(-1)
    assert objects[probs[1] > 0.5].mean() > 0.4 and objects[static].mean() < 0.1


def test_latest_request_wins():
    """While one render runs, of the requests that wait only the newest is rendered; the others return None."""
    sched = LatestWins()
    release, started, order, results = threading.Event(), threading.Event(), [], {}

    def first():
        started.set()
        release.wait(10)
        order.append(1)
        return 1

    def submit(k, fn):
        results[k] = sched.latest(fn)

    t1 = threading.Thread(target=submit, args=(1, first))
    t1.start()
    assert started.wait(10)
    waiting = []
    for k in (2, 3, 4):
        t = threading.Thread(target=submit, args=(k, lambda k=k: order.append(k) or k))
        t.start()
        waiting.append(t)
        while sched._latest < k:  # noqa: SLF001 - wait until this request has taken its ticket
            time.sleep(0.001)
    release.set()
    for t in [t1, *waiting]:
        t.join(10)
    assert results == {1: 1, 2: None, 3: None, 4: 4} and order == [1, 4] and sched.dropped == 2
    assert sched.always(lambda: 5) == 5


# ----------------------------------------------------------------------------------------------------------------
# Save, sweep, command, CLI
# ----------------------------------------------------------------------------------------------------------------
def test_save_writes_a_png_and_a_camera_file_render_reads_back(client, session):
    from livescene.render import read_camera_path

    data = body(session, states={"door": 0.25})
    r = client.post("/api/save", json={**data, "camera": {**data["camera"], "w": 48, "h": 36}})
    assert r.status_code == 200, r.text
    out = r.json()
    png, cams = Path(out["png"]), Path(out["json"])
    assert png.parent == session.run.run_dir / "views" and png.name.startswith("view_")
    import cv2

    assert cv2.imread(str(png)).shape == (36, 48, 3)
    cam = read_camera_path(cams, session.run.views.intrinsics[0])[0]
    assert np.allclose(cam["c2w"].reshape(-1), data["camera"]["c2w"]) and cam["states"] == {"door": 0.25}
    assert (cam["intrinsics"].w, cam["intrinsics"].h) == (48, 36)
    again = client.post("/api/save", json=data).json()
    assert again["png"] != out["png"]  # numbered, never overwritten


def test_sweep_writes_a_video(client, session):
    import cv2

    r = client.post("/api/sweep", json={**body(session, w=32, h=24), "object": "door", "count": 3, "fps": 5})
    assert r.status_code == 200 and r.json()["started"], r.text
    t0 = time.time()
    while (status := client.get("/api/sweep").json())["state"] == "running":
        assert time.time() - t0 < 120, status
        time.sleep(0.1)
    assert status["state"] == "done", status
    path = Path(status["path"])
    assert path.exists() and path.suffix == ".mp4" and path.parent == session.run.run_dir / "views"
    cap = cv2.VideoCapture(str(path))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 3
    cap.release()


@pytest.mark.slow
def test_command_sets_the_object_it_names(client):
    pytest.importorskip("sentence_transformers", reason="the 'language' extra")
    r = client.post("/api/command", json={"text": "open the door"})
    assert r.status_code == 200, r.text
    assert r.json()["states"] == {"door": 1.0}
    r = client.post("/api/command", json={"text": "dance with the door"})
    assert r.status_code == 400 and "open the fridge" in r.json()["error"]


def test_cli_help_and_a_missing_run():
    exe = [sys.executable, "-m", "livescene"]
    r = subprocess.run(exe + ["view", "--help"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "examples:" in r.stdout and "--port" in r.stdout
    r = subprocess.run(exe + ["view", "/nonexistent/run"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.strip().startswith("livescene view: error:") and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert "view" in subprocess.run(exe + ["--help"], capture_output=True, text=True, timeout=120).stdout


def test_unseen_states_come_back_in_a_header(client, session):
    """X-Unseen carries `livescene.render.unseen_states` for the view (the page shows it as a warning)."""
    from livescene.render import unseen_states

    data = body(session)
    c2w = np.asarray(data["camera"]["c2w"]).reshape(4, 4)
    for v in (0.0, 0.5, 1.0):
        r = client.post("/api/render", json={**data, "states": {"door": v}})
        expected = unseen_states(session.run, session.learned, c2w, {"door": v})
        assert json.loads(r.headers["x-unseen"]) == pytest.approx(expected)


def test_bench_reports_the_viewer_speed(session):
    from livescene.viewer.session import measure

    out = measure(session, drags=2)
    assert out["low"] == [40, 30] and out["sharp"] == [80, 60]
    assert 0 < out["first_low_s"] and 0 < out["sharp_s"] and out["drag_fps"] > 0
    assert out["drag_fps"] == pytest.approx(1 / out["drag_s_per_frame"], rel=1e-2)
    assert 0 < out["sharp_after_slider_s"]


def test_opens_on_the_farthest_camera_facing_the_scene():
    from livescene.viewer.session import start_camera

    def looking(pos, target):
        back = np.asarray(pos, float) - target
        back /= np.linalg.norm(back)
        right = np.cross([0, 0, 1.0], back)
        right /= np.linalg.norm(right)
        m = np.eye(4)
        m[:3, :3] = np.stack([right, np.cross(back, right), back], 1)
        m[:3, 3] = pos
        return m

    centre = np.zeros(3)
    cams = np.stack([looking([1, 0, 0], centre), looking([3, 0, 0], centre), looking([5, 0, 0], [9, 0, 0]),
                     looking([4, 1, 0], centre)])
    assert start_camera(cams, [0, 1, 2], centre) == 1  # camera 2 is farther but looks away
    assert start_camera(cams, [0, 1, 2, 3], centre) == 3
    assert start_camera(cams, [2], centre) == 2 and start_camera(cams, [], centre) == 0
