"""The annotation app's click tool (`POST /api/keyframe/{fid}/click`): the mask follows the clicks, is stored as the
keyframe's pixels of that object (as polygons and boxes are), survives a restart, and undoes like a stroke; bad
clicks are a 400 naming them."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("fastapi", reason="the 'web' extra is part of the dev environment")
from fastapi.testclient import TestClient  # noqa: E402
from test_clicks import click_frame, iou, scene  # noqa: E402  (the scene: a red ellipse, a look-alike box)

from interreal.annotate.server import create_app  # noqa: E402
from interreal.annotate.store import _read_index_png  # noqa: E402
from interreal.atomic import write_image, write_npy  # noqa: E402
from interreal.conventions import index_to_onehot  # noqa: E402
from interreal.transients import IGNORE  # noqa: E402

TOKEN, PORT = "click-token", 8766
ON, OFF = [60, 60, True], [115, 60, False]  # on the ellipse; on the look-alike box


@pytest.fixture
def scene_ds(tmp_path):
    root = tmp_path / "ds"
    for i in (0, 1):  # frame 0 with the look-alike box, frame 1 without
        write_image(root / "images" / f"frame_{i:05d}.png", scene(i, distractor=i == 0)[0])
    return root


def app_client(ds) -> TestClient:
    c = TestClient(create_app(ds, TOKEN, PORT), base_url=f"http://127.0.0.1:{PORT}")
    c.headers.update({"X-Interreal-Token": TOKEN})
    return c


@pytest.fixture
def app(scene_ds):
    c = app_client(scene_ds)
    assert c.post("/api/objects", json={"name": "door"}).status_code == 200
    assert c.post("/api/objects", json={"name": "lid"}).status_code == 200
    return c


def click(c, fid, clicks, versions=None, oid=0, name="door"):
    return c.post(f"/api/keyframe/{fid}/click", json={"object": oid, "name": name, "clicks": clicks,
                                                       "versions": versions or {}})


def test_clicks_segment_store_and_survive_a_restart(app, scene_ds):
    _, obj, box = scene(0, distractor=True)
    r = click(app, "00000", [ON])
    assert r.status_code == 200 and r.json()["exists"] and r.json()["keyframes"] == ["00000"]
    first = _read_index_png(scene_ds / "keyframes" / "00000.png") == 1
    assert (first & box).sum() > 0.3 * box.sum()  # the touching look-alike is taken by the first click ...
    r = click(app, "00000", [ON, OFF], r.json()["versions"])
    assert r.status_code == 200
    index = _read_index_png(scene_ds / "keyframes" / "00000.png")
    assert iou(index == 1, obj) >= 0.9 and (index[box] == 1).mean() < 0.05  # ... and the negative click removes it
    again = app_client(scene_ds).get("/api/keyframe/00000").json()  # a new server on the same dataset
    assert again["exists"] and again["versions"] == r.json()["versions"]
    assert np.array_equal(_read_index_png(scene_ds / "keyframes" / "00000.png"), index)


def test_the_app_answers_the_benchmarks_simulated_user_as_the_benchmark_does(app, scene_ds):
    """`bench_masks.py --clicks` measures what the app does: the same clicks, one request each, give the same mask."""
    img, obj, _ = scene(0, distractor=True)
    sim = click_frame(img, obj, max_clicks=4, stop_at=0.99)
    assert len(sim["clicks"]) >= 2
    versions: dict = {}
    for n in range(1, len(sim["clicks"]) + 1):
        r = click(app, "00000", [[c.x, c.y, c.positive] for c in sim["clicks"][:n]], versions)
        assert r.status_code == 200
        versions = r.json()["versions"]
    assert np.array_equal(_read_index_png(scene_ds / "keyframes" / "00000.png") == 1, sim["mask"])


def test_clicks_leave_other_objects_alone_and_undo_like_a_stroke(app, scene_ds):
    box = {"object": 1, "name": "lid", "shape": "box", "points": [[40, 40], [60, 80]], "mode": "paint", "versions": {}}
    v = app.post("/api/keyframe/00000", json=box).json()["versions"]
    r = click(app, "00000", [ON], v)
    assert r.status_code == 200
    index = _read_index_png(scene_ds / "keyframes" / "00000.png")
    assert (index[40:80, 40:60] == 2).all()  # the lid drawn over half the ellipse stays the lid
    assert (index == 1).sum() > 500
    r = app.post("/api/keyframe/00000/undo", json={"versions": r.json()["versions"]})
    assert r.status_code == 200 and r.json()["versions"] == v
    assert (_read_index_png(scene_ds / "keyframes" / "00000.png") == 1).sum() == 0


def test_the_ignore_class_is_clicked_too(app, scene_ds):
    _, obj, _ = scene(0, distractor=True)
    r = click(app, "00000", [ON], oid=-1, name=None)
    r = click(app, "00000", [ON, OFF], r.json()["versions"], oid=-1, name=None)  # one click after the other
    assert r.status_code == 200
    index = _read_index_png(scene_ds / "keyframes" / "00000.png")
    assert iou(index == IGNORE, obj) >= 0.85


def test_a_negative_click_alone_writes_nothing(app, scene_ds):
    r = click(app, "00001", [OFF])
    assert r.status_code == 200 and r.json()["exists"] is False
    assert not (scene_ds / "keyframes" / "00001.png").exists()


def test_the_propagated_mask_is_the_prior(app, scene_ds):
    _, obj, _ = scene(1)
    prior = obj.copy()
    prior[:52] = False  # propagation lost the top of the ellipse; a click there brings it back
    write_npy(scene_ds / "masks" / "00001.npy", index_to_onehot(prior.astype(np.uint8), 2))
    r = click(app, "00001", [[60, 45, True]])
    assert r.status_code == 200
    index = _read_index_png(scene_ds / "keyframes" / "00001.png")
    assert iou(index == 1, obj) >= 0.8 and (index == 1)[prior].mean() > 0.95


@pytest.mark.parametrize("body, words", [
    ({"object": 0, "clicks": [[160, 10, True]]}, "outside the 160x120 image"),
    ({"object": 0, "clicks": [[5, -3, False]]}, "outside"),
    ({"object": 7, "clicks": [ON]}, "object id 7 does not exist"),
    ({"object": 0, "clicks": []}, "no clicks given"),
    ({"object": 0, "clicks": "here"}, "'clicks' must be a list"),
    ({"object": 0, "clicks": [[1, 2]]}, "[x, y, positive]"),
    ({"object": 0, "clicks": [[1, 2, "yes"]]}, "[x, y, positive]"),
    ({"object": "door", "clicks": [ON]}, "'object' must be an integer"),
    ({"clicks": [ON]}, "'object' is missing"),
])
def test_bad_clicks_are_400_naming_them(app, scene_ds, body, words):
    r = app.post("/api/keyframe/00000/click", json=body)
    assert r.status_code == 400 and words in r.json()["error"], r.text
    assert not (scene_ds / "keyframes" / "00000.png").exists()


def test_a_frame_without_an_image_is_400_and_an_unknown_frame_404(app, scene_ds):
    (scene_ds / "images" / "frame_00001.png").unlink()
    r = click(app, "00001", [ON])
    assert r.status_code == 400 and "frame 00001 has no image" in r.json()["error"]
    r = click(app, "00042", [ON])
    assert r.status_code == 404 and "no frame" in r.json()["error"]
