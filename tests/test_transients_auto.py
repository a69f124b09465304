"""`--transients auto`: the hand model finds the hand on real frames, the layer grows it to the arm, the masks stage
writes it (objects win), and a missing model is one line, not a failure."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from interreal import atomic
from interreal.conventions import fid_of_index, frame_name
from interreal.masks import propagate, transient_line
from interreal.paths import require_shared
from interreal.transients import read_transient
from interreal.transients import auto as A
from interreal.transients import hands as Hd

FIXTURE = Path(__file__).parent / "fixtures" / "laptop" / "transients.json"


def needs_model() -> None:
    problem = Hd.model_problem()
    if problem:
        pytest.fail(f"{problem} (bash .ci/setup installs it)")


def sim_dataset(root: Path, frames: int, size: tuple[int, int], keyframe_every: int, seed: int,
                keys: dict[int, np.ndarray] | None = None):
    """A small simulated capture as a dataset (its video's frames in DS/images) and a keyframe folder: the capture's
    own keyframes, or `keys` (position -> index map). Returns (capture, DS, keyframe folder)."""
    from interreal.synth import Capture, SynthConfig, write_capture

    cap = Capture.open(write_capture(SynthConfig(frames=frames, width=size[0], height=size[1],
                                                 keyframe_every=keyframe_every, seed=seed), root / "cap",
                                     progress=False))
    ds, kf = root / "ds", root / "keys"
    for i, rgb in cap.frames():
        atomic.write_image(ds / "images" / f"{frame_name(i)}.png", rgb)
    for k, index in (keys if keys is not None else {k: cap.instance(k) for k in cap.keyframes}).items():
        atomic.write_image(kf / f"{fid_of_index(k)}.png", index)
    atomic.write_yaml(kf / "mapping.yaml", dict(enumerate(cap.names)))
    return cap, ds, kf


def truth_of(fid: str, kinds=("hand", "person"), size: tuple[int, int] | None = None) -> np.ndarray:
    fx = json.loads(FIXTURE.read_text())
    w, h = fx["size"]
    sx, sy = (1.0, 1.0) if size is None else (size[0] / w, size[1] / h)
    m = np.zeros((h, w) if size is None else (size[1], size[0]), np.uint8)
    polys = [np.round(np.array(p, float) * [sx, sy]).astype(np.int32) for k in kinds for p in fx["frames"][fid].get(k, [])]
    cv2.fillPoly(m, polys, 1)
    return m > 0


@pytest.fixture(scope="module")
def clip() -> list[np.ndarray]:
    """Frames 60-80 of the shared laptop video (RGB, 1072x608): a hand reaches in from the top to hold the lid."""
    cap = cv2.VideoCapture(str(require_shared("laptop/laptop_orbit.mp4")))
    cap.set(cv2.CAP_PROP_POS_FRAMES, 60)
    out = []
    for _ in range(21):
        ok, bgr = cap.read()
        assert ok
        out.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    return out


def test_the_hand_model_finds_the_hand_on_a_real_frame(clip):
    needs_model()
    track = Hd.find_hands(lambda p: clip[p], len(clip))
    assert track.found_share() >= 0.7  # 16 of 21 here (the whole video: 72 %, its first frames have no hand)
    hand = track.hands[10]  # source frame 70
    assert len(hand) >= 1
    truth = truth_of("00070", ("hand",))
    xs, ys = np.round(hand[0]).astype(int).T
    inside = truth[np.clip(ys, 0, 607), np.clip(xs, 0, 1071)].mean()
    assert inside >= 0.8  # its landmarks are on the hand that holds the lid
    assert set(track.how) <= {"tracked", "static", "filled", ""} and track.how[10] in ("tracked", "static")


def test_the_hand_model_finds_the_simulated_hand():
    """The simulator's arm (`--arm`) ends in a hand the hand model finds, so the layer is measured on simulated
    captures too; its landmarks lie on the hand's pixels."""
    from interreal.synth import SynthConfig
    from interreal.synth.scene import build_scene

    needs_model()
    scene = build_scene(SynthConfig(frames=90, width=960, height=720, seed=1, furniture="plain", arm=True))
    moving = [t for t in range(90) if scene.moving(t)][::4]
    frames = [scene.render_frame(t) for t in moving]
    track = Hd.find_hands(lambda p: frames[p].rgb, len(frames))
    assert track.found_share() >= 0.4  # every 4th frame: tracking holds less than over the whole video (0.82)
    on_arm = []
    for f, hands in zip(frames, track.hands):
        near = cv2.dilate((f.instance == 255).astype(np.uint8), np.ones((15, 15), np.uint8))
        for hand in hands:
            centre = np.round(hand.mean(0)).astype(int).clip(0, [959, 719])
            assert near[centre[1], centre[0]]  # each hand found is on the simulator's hand and arm
            xy = np.round(hand).astype(int).clip(0, [959, 719])
            on_arm.append(near[xy[:, 1], xy[:, 0]].mean())
    assert np.mean(on_arm) > 0.8  # most landmarks on it (a cartoon thumb's may be guessed off it)


def test_the_auto_layer_grows_the_hand_to_the_arm_on_real_video(clip):
    needs_model()
    layer = A.propose(lambda p: clip[p], len(clip), (1072, 608))
    got = layer.full(10, (1072, 608))
    truth = truth_of("00070")
    iou = (got & truth).sum() / (got | truth).sum()
    hull = np.zeros_like(truth, np.uint8)
    pts = layer.track.hands[10][0] * 1072 / layer.work_size[0]  # landmarks in work pixels -> full size
    cv2.fillConvexPoly(hull, cv2.convexHull(np.round(pts).astype(np.int32)), 1)
    hull_iou = (hull.astype(bool) & truth).sum() / (hull.astype(bool) | truth).sum()
    assert iou >= 0.7 and iou > hull_iou + 0.2  # the forearm to the image edge, not the landmarks' hull
    static = ~truth
    assert (got & static).sum() / static.sum() <= 0.01
    assert set(layer.seconds) >= {"tracking", "static", "grow"}


def test_no_person_gives_an_empty_layer(tmp_path):
    """A simulated room with nobody in it: no hand found, nothing proposed (not noise)."""
    needs_model()
    from interreal.synth import Capture, SynthConfig, write_capture

    cap = Capture.open(write_capture(SynthConfig(frames=6, width=320, height=240, seed=3), tmp_path / "cap",
                                     progress=False))
    frames = [rgb for _, rgb in cap.frames()]
    layer = A.propose(lambda p: frames[p], len(frames), (320, 240))
    assert layer.masks == {} and layer.track.found_share() == 0.0


def _hand(wrist: tuple[float, float], up: tuple[float, float], length: float) -> np.ndarray:
    """21 landmarks of a straight hand: wrist at `wrist`, fingers along `up`, `length` px wrist to middle knuckle."""
    u = np.array(up, float) / np.linalg.norm(up)
    n = np.array([-u[1], u[0]])
    pts = np.zeros((21, 2))
    pts[0] = wrist
    for finger, off in zip(range(5), (-0.5, -0.25, 0.0, 0.25, 0.5)):
        for j in range(4):
            pts[1 + 4 * finger + j] = np.array(wrist) + u * length * (0.9 + 0.35 * j) + n * length * off
    pts[Hd.MIDDLE_MCP] = np.array(wrist) + u * length
    pts[Hd.INDEX_MCP] = np.array(wrist) + u * length + n * -0.35 * length
    pts[Hd.PINKY_MCP] = np.array(wrist) + u * length + n * 0.35 * length
    return pts


def test_seeds_put_the_forearm_away_from_the_fingers_and_to_the_edge():
    hand = _hand((100, 60), (0, 1), 20)  # fingers point down: the forearm goes up, to the top edge
    core, reach = A.seeds(hand[None], (200, 200))
    assert core[90:110, 95:105].any() and core.sum() < reach.sum()
    assert reach[0:40, 100].all() and not reach[150:, :].any()


def test_the_forearm_follows_a_bent_wrist_where_the_image_shows_the_sleeve():
    """Fingers point down, but the sleeve leaves the wrist 45 deg off the knuckles' line (a bent wrist, or landmarks
    guessed on a hand seen side-on): with the frame the reach takes the sleeve and the layer grows onto it; without
    it, straight on, it misses most of the sleeve."""
    rng = np.random.default_rng(1)
    img = rng.integers(95, 135, (240, 320, 3)).astype(np.uint8)
    sleeve = np.zeros((240, 320), np.uint8)
    wrist = np.array([160.0, 140.0])
    cv2.line(sleeve, (160, 140), (160 + 200, 140 - 200), 1, 22)  # up and to the right, 45 deg off straight up
    img[sleeve > 0] = (40, 150, 60)
    cv2.circle(img, (160, 160), 20, (225, 180, 160), -1)
    hand = _hand(tuple(wrist), (0, 1), 20)
    lab = cv2.cvtColor(cv2.GaussianBlur(img, (5, 5), 0), cv2.COLOR_RGB2LAB).astype(np.float32)
    d = A.forearm_direction(lab, hand)
    assert abs(np.degrees(np.arctan2(-d[1], d[0])) - 45) <= 15  # the sleeve's own direction (image y is down)
    truth = (sleeve > 0) | (np.hypot(*np.mgrid[0:240, 0:320][::-1] - np.array([160, 160])[:, None, None]) <= 20)
    for with_img, least, most in ((True, 0.6, 1.0), (False, 0.0, 0.4)):
        core, reach = A.seeds(hand[None], truth.shape, img if with_img else None)
        got = A.grow_rounds(img, core, reach)
        assert least <= (got & truth).sum() / (got | truth).sum() <= most
    flat = np.full_like(img, 110)  # nothing in view says which way: straight on
    d = A.forearm_direction(cv2.cvtColor(flat, cv2.COLOR_RGB2LAB).astype(np.float32), hand)
    assert np.allclose(d, [0, -1])


def test_grow_follows_a_sleeve_of_another_colour_to_the_image_edge():
    """A skin-coloured hand, a green sleeve from its wrist to the top edge, a textured scene with a skin-coloured
    shelf elsewhere: the layer is hand and sleeve, not the shelf."""
    rng = np.random.default_rng(0)
    img = rng.integers(90, 140, (240, 320, 3)).astype(np.uint8)  # grey, textured
    img[180:230, 20:300] = (205, 160, 120)  # a wooden shelf of the skin's colour, away from the hand
    truth = np.zeros((240, 320), bool)
    cv2.circle(img, (160, 120), 18, (225, 180, 160), -1)
    cv2.rectangle(img, (150, 0), (170, 105), (40, 160, 60), -1)
    cv2.circle(truth.view(np.uint8), (160, 120), 18, 1, -1)
    truth[0:106, 150:171] = True
    hand = _hand((160, 105), (0, 1), 18)
    core, reach = A.seeds(hand[None], truth.shape)
    got = A.grow_rounds(img, core, reach)
    iou = (got & truth).sum() / (got | truth).sum()
    assert iou >= 0.75
    assert not got[180:230].any()  # not the shelf


def test_growth_is_the_same_on_any_thread_in_any_order():
    """`propose` grows frames on `GROW_THREADS` threads: GrabCut's k-means start is seeded, so a frame grows alike
    whichever thread takes it and whatever it cut before (OpenCV's random state is per thread)."""
    from concurrent.futures import ThreadPoolExecutor

    rng = np.random.default_rng(1)
    frames = []
    for k in range(4):
        img = rng.integers(60, 200, (120, 160, 3)).astype(np.uint8)
        cv2.circle(img, (80 + 5 * k, 60), 12, (225, 180, 160), -1)
        cv2.rectangle(img, (75 + 5 * k, 0), (85 + 5 * k, 50), (40, 160, 60), -1)
        frames.append(img)
    hands = [_hand((80 + 5 * k, 50), (0, 1), 12)[None] for k in range(4)]

    def one(k: int) -> np.ndarray:
        core, reach = A.seeds(hands[k], (120, 160))
        return A.grow_rounds(frames[k], core, reach)

    alone = [one(k) for k in range(4)]
    assert all(m.any() for m in alone)
    with ThreadPoolExecutor(2) as pool:
        threaded = list(pool.map(one, [3, 1, 2, 0, 3, 1]))
    assert all(np.array_equal(m, alone[k]) for m, k in zip(threaded, [3, 1, 2, 0, 3, 1]))


def test_fill_gaps_interpolates_short_gaps_only():
    a, b = _hand((10, 10), (0, 1), 10)[None], _hand((30, 10), (0, 1), 10)[None]
    empty = np.zeros((0, 21, 2))
    hands = [a, empty, empty, empty, b] + [empty] * 6 + [a]
    how = ["tracked", "", "", "", "tracked"] + [""] * 6 + ["static"]
    out, how2 = Hd.fill_gaps(hands, how, max_gap=4)
    assert how2[1:4] == ["filled"] * 3 and np.allclose(out[2][0, 0], (20, 10))
    assert all(len(out[p]) == 0 for p in range(5, 11))  # 6 frames: too long to guess
    far = _hand((150, 10), (0, 1), 10)[None]  # the other hand, at another part: two hands, not one moving
    assert Hd.fill_gaps([a, empty, far], ["tracked", "", "tracked"])[1][1] == ""
    two = np.concatenate([a, b])
    out, how3 = Hd.fill_gaps([two, empty, a], ["tracked", "", "tracked"])
    assert how3[1] == ""  # two hands one side, one the other: not paired


def test_masks_stage_writes_the_auto_layer_objects_win(tmp_path, monkeypatch):
    """With a layer proposed (here a fixed one, a hand found on frame 2 only), DS/transients/ holds it less the
    object's pixels, carried to the frames around it, the SfM masks leave it out, the report and the printed line
    say so."""
    cap, ds, keys = sim_dataset(tmp_path, 8, (160, 120), keyframe_every=4, seed=1)
    obj0 = cap.instance(2) == 1
    block = np.zeros((120, 160), bool)
    block[10:60, 20:100] = True
    block |= obj0  # the proposal also covers an object: the object wins

    def fake(load, n, size, **kw):
        track = Hd.HandTrack([np.zeros((int(p == 2), 21, 2)) for p in range(n)],
                             ["tracked" if p == 2 else "" for p in range(n)])
        return A.AutoLayer({2: block}, size, track, [], {"tracking": 0.0, "static": 0.0, "grow": 0.0})

    monkeypatch.setattr("interreal.masks.stage.propose", fake)
    monkeypatch.setattr("interreal.masks.stage.model_problem", lambda: None)
    fig = propagate(ds, keys, preview="none", progress=False)
    layer = read_transient(ds, fid_of_index(2), (120, 160))
    assert layer is not None and layer[10:60, 20:100].sum() > 0
    masks = np.load(ds / "masks" / f"{fid_of_index(2)}.npy")
    assert not (layer & masks[..., :-1].any(-1)).any()  # never where an object is (background is last)
    sfm = cv2.imread(str(ds / "sfm_masks" / f"{frame_name(2)}.png.png"), 0)  # COLMAP: <image name>.png
    assert (sfm[layer] == 0).all()
    carried = read_transient(ds, fid_of_index(3), (120, 160))  # no hand found there: carried by the flow
    assert carried is not None and carried[10:60, 20:100].any()
    auto = fig["transients"]["auto"]
    assert auto["ran"] and auto["carried"] >= 1 and auto["frames"] == 1 + auto["carried"]
    assert fig["transients"]["frames"] == auto["frames"]
    assert f"auto: a hand found on 12 % of the frames, carried by the flow to {auto['carried']} more" in \
        transient_line(fig)
    off = propagate(ds, keys, preview="none", progress=False, transients="off")
    assert off["transients"]["frames"] == 0 and read_transient(ds, fid_of_index(2), (120, 160)) is None


def test_a_missing_hand_model_is_one_line_and_the_stage_runs(tmp_path, monkeypatch, capsys):
    from interreal.report import read_report

    cap, ds, keys = sim_dataset(tmp_path, 4, (96, 72), keyframe_every=3, seed=2, keys={})
    atomic.write_image(keys / f"{fid_of_index(0)}.png", cap.instance(0))
    monkeypatch.setattr("interreal.masks.stage.model_problem", lambda: "the hand model does not run here (No module "
                                                                        "named 'mediapipe'); install it with: pip ...")
    fig = propagate(ds, keys, preview="none", progress=True)
    out = capsys.readouterr().out
    assert [line for line in out.splitlines() if "no automatic transient layer" in line] == [
        "masks: no automatic transient layer: the hand model does not run here (No module named 'mediapipe'); "
        "install it with: pip ..."]
    assert fig["transients"]["auto"] == {"mode": "auto", "ran": False, "why_not": fig["transients"]["auto"]["why_not"]}
    causes = [w.get("cause") for w in read_report(ds, "masks")["warnings"]]
    assert "no-hand-model" in causes
    assert len(list((ds / "masks").glob("*.npy"))) == 4


def test_model_problem_names_the_install_when_mediapipe_is_broken(monkeypatch):
    import builtins

    real = builtins.__import__

    def broken(name, *a, **kw):
        if name == "mediapipe":
            raise ImportError("No module named 'mediapipe'")
        return real(name, *a, **kw)

    monkeypatch.setattr(builtins, "__import__", broken)
    problem = Hd.model_problem()
    assert problem and "No module named 'mediapipe'" in problem and "--no-deps mediapipe==0.10.21" in problem


def test_one_click_keeps_a_found_hand_as_painted_ignore(tmp_path):
    """The annotate app's Found tool: a click on a region of the transient layer paints that region (only) as the
    ignore class on the keyframe; erase takes it out again; a click elsewhere, or with an object selected, is refused
    with what to do."""
    from interreal.annotate.store import IGNORE_OBJECT, DatasetStore
    from interreal.errors import InputError
    from interreal.transients import IGNORE, write_transient

    ds = tmp_path / "ds"
    rng = np.random.default_rng(0)
    for i in range(3):
        atomic.write_image(ds / "images" / f"{frame_name(i)}.png", rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    atomic.write_yaml(ds / "mapping.yaml", {0: "door"})
    layer = np.zeros((48, 64), bool)
    layer[0:20, 40:50] = True  # an arm from the top edge
    layer[30:40, 5:15] = True  # another region (a second hand)
    write_transient(ds, fid_of_index(1), layer)
    store = DatasetStore(ds)
    index, versions = store.edit_keyframe("00001", {"object": IGNORE_OBJECT, "shape": "found", "points": [[44, 10]],
                                                    "mode": "paint", "versions": {}})
    assert (index == IGNORE).sum() == 200 and (index[0:20, 40:50] == IGNORE).all() and index[35, 10] == 0
    index, versions = store.edit_keyframe("00001", {"object": IGNORE_OBJECT, "shape": "found", "points": [[38, 10]],
                                                    "mode": "paint", "versions": versions})  # 2 px off: snaps
    assert (index == IGNORE).sum() == 200
    index, versions = store.edit_keyframe("00001", {"object": IGNORE_OBJECT, "shape": "found", "points": [[44, 10]],
                                                    "mode": "erase", "versions": versions})
    assert not (index == IGNORE).any()
    with pytest.raises(InputError, match="click inside a grey region"):
        store.edit_keyframe("00001", {"object": IGNORE_OBJECT, "shape": "found", "points": [[25, 44]],
                                      "mode": "paint", "versions": versions})
    with pytest.raises(InputError, match="select 'ignore'"):
        store.edit_keyframe("00001", {"object": 0, "shape": "found", "points": [[44, 10]], "mode": "paint",
                                      "versions": versions})
    with pytest.raises(InputError, match="run `interreal masks`"):
        store.edit_keyframe("00002", {"object": IGNORE_OBJECT, "shape": "found", "points": [[44, 10]],
                                      "mode": "paint", "versions": {}})


def test_a_keyframe_that_paints_ignore_gets_no_proposal(tmp_path, monkeypatch):
    """Where the user painted the ignore class on a keyframe, that painting is the layer there: a proposal the
    user took out does not come back on that keyframe."""
    from interreal.transients import IGNORE

    cap, ds, keys = sim_dataset(tmp_path, 6, (96, 72), keyframe_every=3, seed=2, keys={})
    key = cap.instance(0).copy()
    key[0:6, 0:6] = IGNORE  # a small painted patch far from the proposal
    atomic.write_image(keys / f"{fid_of_index(0)}.png", key)
    block = np.zeros((72, 96), bool)
    block[40:70, 60:90] = True

    def fake(load, n, size, **kw):
        track = Hd.HandTrack([np.zeros((1, 21, 2))] * n, ["tracked"] * n)
        return A.AutoLayer({p: block for p in range(n)}, size, track, [], {})

    monkeypatch.setattr("interreal.masks.stage.propose", fake)
    monkeypatch.setattr("interreal.masks.stage.model_problem", lambda: None)
    propagate(ds, keys, preview="none", progress=False)
    on_key = read_transient(ds, fid_of_index(0), (72, 96))
    assert on_key is not None and not on_key[40:70, 60:90].any() and on_key[0:6, 0:6].all()
    other = read_transient(ds, fid_of_index(4), (72, 96))
    assert other is not None and other[45:65, 65:85].mean() > 0.9


def test_the_found_tool_over_http(tmp_path):
    """The page's Found click goes through the server as shape 'found' with one point."""
    pytest.importorskip("fastapi")
    from fastapi.testclient import TestClient

    from interreal.annotate.server import create_app
    from interreal.transients import IGNORE, write_transient

    ds = tmp_path / "ds"
    rng = np.random.default_rng(1)
    atomic.write_image(ds / "images" / f"{frame_name(0)}.png", rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    atomic.write_yaml(ds / "mapping.yaml", {0: "door"})
    layer = np.zeros((48, 64), bool)
    layer[0:20, 40:50] = True
    write_transient(ds, fid_of_index(0), layer)
    c = TestClient(create_app(ds, "tok", 8765), base_url="http://127.0.0.1:8765")
    c.headers.update({"X-Interreal-Token": "tok"})
    r = c.post("/api/keyframe/00000", json={"object": -1, "shape": "found", "points": [[44.5, 3.2]], "mode": "paint",
                                            "versions": {}})
    assert r.status_code == 200, r.text
    written = cv2.imread(str(ds / "keyframes" / "00000.png"), cv2.IMREAD_UNCHANGED)
    assert (written == IGNORE).sum() == 200


def test_a_growth_over_half_the_frame_keeps_the_hand_and_is_warned(tmp_path, monkeypatch):
    """GrabCut that leaks onto a wall of the skin's colour: the frame keeps the hand's outline only, the report names
    the frame (cause transient-leak)."""
    from interreal.report import read_report

    hand = _hand((48, 40), (0, 1), 12)[None]

    def hands(load, n, **kw):
        return Hd.HandTrack([hand if p == 1 else np.zeros((0, 21, 2)) for p in range(n)],
                            ["tracked" if p == 1 else "" for p in range(n)], {"tracking": 0.0, "static": 0.0})

    monkeypatch.setattr(A, "find_hands", hands)
    monkeypatch.setattr(A, "grow_rounds", lambda img, core, reach: np.ones_like(core))  # everything: a leak
    frames = [np.zeros((72, 96, 3), np.uint8)] * 3
    layer = A.propose(lambda p: frames[p], 3, (96, 72))
    assert layer.leaked == [1] and 0 < layer.masks[1].mean() < 0.2

    cap, ds, keys = sim_dataset(tmp_path, 3, (96, 72), keyframe_every=2, seed=2, keys={})
    atomic.write_image(keys / f"{fid_of_index(0)}.png", cap.instance(0))
    monkeypatch.setattr("interreal.masks.stage.model_problem", lambda: None)
    fig = propagate(ds, keys, preview="none", progress=False)
    assert fig["transients"]["auto"]["leaked"] == [fid_of_index(1)]
    warned = [w for w in read_report(ds, "masks")["warnings"] if w.get("cause") == "transient-leak"]
    assert len(warned) == 1 and fid_of_index(1) in warned[0]["message"]
