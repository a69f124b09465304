"""`interreal masks`: propagation accuracy (DAVIS clip, toy scene, simulated capture), layout, inputs, bad inputs."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from interreal import atomic
from interreal.conventions import fid_of_index, frame_name
from interreal.errors import InputError
from interreal.masks import MasksConfig, propagate
from interreal.paths import require_shared

cv2.setNumThreads(2)


# ---------------------------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------------------------
def toy_sequence(n: int = 16, w: int = 128, h: int = 96, seed: int = 0) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """A textured background with a red disk moving right and a blue square moving down; truth index maps."""
    rng = np.random.default_rng(seed)
    bg = cv2.GaussianBlur(rng.integers(0, 255, (h + 40, w + 40, 3), dtype=np.uint8), (0, 0), 2.0)
    bg = cv2.normalize(bg, None, 60, 200, cv2.NORM_MINMAX)
    tex = cv2.GaussianBlur(rng.integers(0, 255, (h, w), dtype=np.uint8), (0, 0), 1.5)
    images, truths = [], []
    for t in range(n):
        img = bg[t // 2:t // 2 + h, 10:10 + w].copy()  # the camera pans slowly
        lab = np.zeros((h, w), np.uint8)
        disk = np.zeros((h, w), np.uint8)
        cv2.circle(disk, (24 + 3 * t, 40), 14, 1, -1)
        square = np.zeros((h, w), np.uint8)
        square[10 + 2 * t:34 + 2 * t, 80:104] = 1
        img[disk > 0] = np.stack([200 + tex // 8, 40 + tex // 6, 40 + tex // 6], -1)[disk > 0]
        img[square > 0] = np.stack([40 + tex // 6, 60 + tex // 6, 190 + tex // 8], -1)[square > 0]
        lab[disk > 0] = 1
        lab[(square > 0) & (disk == 0)] = 2
        images.append(img)
        truths.append(lab)
    return images, truths


def make_ds(root: Path, images: list[np.ndarray]) -> Path:
    ds = root / "ds"
    for i, img in enumerate(images):
        atomic.write_image(ds / "images" / f"{frame_name(i)}.png", img)
    return ds


def iou(a: np.ndarray, b: np.ndarray) -> float:
    u = (a | b).sum()
    return float((a & b).sum() / u) if u else 1.0


def write_keys(folder: Path, truths: list[np.ndarray], keys: list[int], names: list[str]) -> Path:
    for k in keys:
        atomic.write_image(folder / f"{fid_of_index(k)}.png", truths[k])
    atomic.write_yaml(folder / "mapping.yaml", dict(enumerate(names)))
    return folder


def mean_iou(ds: Path, truths: list[np.ndarray], skip: list[int], n_obj: int) -> list[float]:
    out = []
    for k in range(n_obj):
        vals = [iou(np.load(ds / "masks" / f"{fid_of_index(i)}.npy")[..., k], truths[i] == k + 1)
                for i in range(len(truths)) if i not in skip]
        out.append(float(np.mean(vals)))
    return out


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    root = tmp_path_factory.mktemp("toy")
    images, truths = toy_sequence()
    ds = make_ds(root, images)
    keys = write_keys(root / "keys", truths, [0, 15], ["red disk", "blue square"])
    fig = propagate(ds, keys, preview="both", suggest=3, progress=False)
    return ds, truths, fig


# ---------------------------------------------------------------------------------------------------------------
# accuracy and outputs
# ---------------------------------------------------------------------------------------------------------------
def test_toy_two_objects_iou_and_layout(toy):
    ds, truths, fig = toy
    ious = mean_iou(ds, truths, [0, 15], 2)
    assert min(ious) > 0.85, ious
    for i in range(len(truths)):
        m = np.load(ds / "masks" / f"{fid_of_index(i)}.npy")
        assert m.dtype == bool and m.shape == (96, 128, 3)
        assert (m.sum(-1) == 1).all()  # exclusive, background last
        assert np.array_equal(m[..., 2], ~(m[..., 0] | m[..., 1]))
    key = np.load(ds / "masks" / "00000.npy")
    assert np.array_equal(key[..., 0], truths[0] == 1)  # keyframes are exactly the annotation


def test_toy_report_sfm_masks_previews(toy):
    ds, truths, fig = toy
    rep = json.loads((ds / "reports" / "masks.json").read_text())
    assert rep["status"] == "ok"
    conf = rep["figures"]["confidence"]
    assert set(conf) == {"red disk", "blue square"} and len(conf["red disk"]) == 16
    assert all(0.0 <= v <= 1.0 for v in conf["red disk"].values())
    assert conf["red disk"]["00000"] == 1.0
    sugg = rep["figures"]["suggested_frames"]
    assert len(sugg) == 3 and not {"00000", "00015"} & set(sugg)
    assert yaml.safe_load((ds / "mapping.yaml").read_text()) == {0: "red disk", 1: "blue square"}
    sfm = cv2.imread(str(ds / "sfm_masks" / "frame_00007.png.png"), cv2.IMREAD_UNCHANGED)
    assert sfm.shape == (96, 128) and set(np.unique(sfm)) == {0, 255}
    obj = truths[7] > 0
    assert (sfm[obj] == 0).mean() > 0.97 and (sfm == 0).sum() > obj.sum()  # objects black, dilated
    assert (ds / "previews" / "masks_sheet.png").stat().st_size > 1000
    assert (ds / "previews" / "masks_overlay.mp4").stat().st_size > 1000


def test_davis_clip_iou(tmp_path):
    src = require_shared("davis2016", "blackswan")
    jpgs = sorted((src / "images").glob("*.jpg"))[:12]
    gts = sorted((src / "masks").glob("*.png"))[:12]
    size = (427, 240)
    images = [cv2.resize(cv2.imread(str(p))[..., ::-1], size, interpolation=cv2.INTER_AREA) for p in jpgs]
    truths = [(cv2.resize(cv2.imread(str(p), 0), size, interpolation=cv2.INTER_NEAREST) > 127).astype(np.uint8)
              for p in gts]
    ds = make_ds(tmp_path, images)
    write_keys(tmp_path / "keys", truths, [0], ["blackswan"])
    propagate(ds, tmp_path / "keys", preview="none", progress=False)
    first_only = mean_iou(ds, truths, [0], 1)[0]
    assert first_only > 0.88, first_only
    write_keys(tmp_path / "keys", truths, [0, 11], ["blackswan"])
    propagate(ds, tmp_path / "keys", preview="none", progress=False)
    two = mean_iou(ds, truths, [0, 11], 1)[0]
    assert two > 0.90 and two >= first_only - 0.01, (first_only, two)


def test_object_leaves_and_reenters(tmp_path):
    """The disk is out of view at frame 8 (annotated absent) and comes back: the masks follow."""
    images, truths = toy_sequence(n=16)
    for t in range(6, 11):  # hide the disk: paint the background over it
        m = truths[t] == 1
        images[t][m] = images[t][~m].mean(0).astype(np.uint8)
        truths[t][m] = 0
    ds = make_ds(tmp_path, images)
    write_keys(tmp_path / "keys", truths, [0, 8, 15], ["red disk", "blue square"])
    propagate(ds, tmp_path / "keys", preview="none", progress=False)
    for t in (7, 9):
        pred = np.load(ds / "masks" / f"{fid_of_index(t)}.npy")[..., 0]
        assert pred.sum() < 60, (t, pred.sum())
    # frames two or more away from the (abrupt) disappearance keep the disk
    ious = mean_iou(ds, truths, [0, 4, 5, 6, 7, 8, 9, 10, 11, 12, 15], 2)
    assert min(ious) > 0.8, ious


def pan_out_and_back(n: int = 24, w: int = 128, h: int = 96, seed: int = 3):
    """The camera pans right until a red box (fixed in the world) leaves the view over the left border, then back:
    the keyframes at both ends show it."""
    rng = np.random.default_rng(seed)
    world_w = w + 160
    bg = cv2.GaussianBlur(rng.integers(0, 255, (h, world_w, 3), dtype=np.uint8), (0, 0), 2.0)
    bg = cv2.normalize(bg, None, 60, 200, cv2.NORM_MINMAX)
    tex = cv2.GaussianBlur(rng.integers(0, 255, (40, 40), dtype=np.uint8), (0, 0), 1.5)
    world = bg.copy()
    world[30:70, 20:60] = np.stack([200 + tex // 8, 40 + tex // 6, 40 + tex // 6], -1)
    lab_world = np.zeros((h, world_w), np.uint8)
    lab_world[30:70, 20:60] = 1
    images, truths = [], []
    for t in range(n):
        x = int(round(150 * (1 - abs(2 * t / (n - 1) - 1))))  # 0 -> 150 -> 0
        images.append(world[:, x:x + w].copy())
        truths.append(lab_world[:, x:x + w].copy())
    return images, truths


def test_an_object_that_leaves_the_view_is_not_lost(tmp_path, capsys):
    """Both keyframes show the box; between them the camera turned away and it is out of the view: no 'object
    lost' warning, no keyframe suggested there, the stretch named as out of the view."""
    import argparse

    from interreal.masks import main as masks_main
    from interreal.report import read_report

    images, truths = pan_out_and_back()
    assert not truths[12].any() and truths[0].any() and truths[-1].any()
    ds = make_ds(tmp_path, images)
    write_keys(tmp_path / "keys", truths, [0, len(images) - 1], ["red box"])
    masks_main(argparse.Namespace(dataset=ds, keyframes=tmp_path / "keys", quiet=True,
                                  **{**dataclasses.asdict(MasksConfig()), "preview": "none", "suggest": 3}))
    rep = read_report(ds, "masks")
    assert not [w for w in rep["warnings"] if w.get("cause") == "object-lost"], rep["warnings"]
    left = rep["figures"]["left_view"]
    assert list(left) == ["red box"] and fid_of_index(12) in _frames_in(left["red box"])
    assert "red box: out of the view at frames" in capsys.readouterr().out
    for t in (10, 12, 14):
        assert np.load(ds / "masks" / f"{fid_of_index(t)}.npy")[..., 0].sum() == 0


def _frames_in(text: str) -> set[str]:
    """Frame ids in a stretch text like '00008-00015, 00020'."""
    out = set()
    for part in text.split(", "):
        a, _, b = part.partition("-")
        out |= {fid_of_index(i) for i in range(int(a), int(b or a) + 1)}
    return out


@pytest.mark.slow
def test_synth_capture_iou(tmp_path):
    import av

    from interreal.synth import Capture, SynthConfig, write_capture

    # half the default capture's length at a quarter of its pixels: per-frame motion stays realistic
    n = 150
    cap_dir = write_capture(SynthConfig(frames=n, width=320, height=240, keyframe_every=60), tmp_path / "cap",
                            progress=False)
    cap = Capture.open(cap_dir)
    ds = tmp_path / "ds"
    with av.open(str(cap_dir / "video.mp4")) as c:
        for i, fr in enumerate(c.decode(video=0)):
            atomic.write_image(ds / "images" / f"{frame_name(i)}.png", fr.to_ndarray(format="rgb24"))
    truths = [cv2.imread(str(cap_dir / "gt" / "instance" / f"{fid_of_index(i)}.png"), 0) for i in range(n)]
    propagate(ds, cap_dir / "annotations" / "keyframes", preview="none", progress=False)
    for k, name in enumerate(cap.names):
        vals = [iou(np.load(ds / "masks" / f"{fid_of_index(i)}.npy")[..., k] & (truths[i] != 255),
                    truths[i] == k + 1) for i in range(n) if i not in cap.keyframes]
        assert np.mean(vals) > 0.80, (name, np.mean(vals))  # measured 0.84 (door) at this size; 0.91-0.93 at 640x480


# ---------------------------------------------------------------------------------------------------------------
# LabelMe input
# ---------------------------------------------------------------------------------------------------------------
def labelme(shapes: list[dict], w: int = 128, h: int = 96) -> dict:
    return {"version": "5.4.1", "flags": {}, "shapes": shapes, "imagePath": "frame.png", "imageData": None,
            "imageHeight": h, "imageWidth": w}


def disk_polygon(cx: float, cy: float, r: float, n: int = 24) -> list[list[float]]:
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([cx + r * np.cos(a), cy + r * np.sin(a)], 1).tolist()


def test_labelme_polygon_and_rectangle(tmp_path):
    images, truths = toy_sequence(n=10)
    ds = make_ds(tmp_path, images)
    keys = tmp_path / "keys"
    shapes = [{"label": "red disk", "points": disk_polygon(24, 40, 14.5), "shape_type": "polygon"},
              {"label": "blue square", "points": [[76, 6], [108, 38]], "shape_type": "rectangle"}]
    atomic.write_json(keys / "00000.json", labelme(shapes))
    propagate(ds, keys, preview="none", progress=False)  # no mapping anywhere: names come from the labels
    assert yaml.safe_load((ds / "mapping.yaml").read_text()) == {0: "red disk", 1: "blue square"}
    key = np.load(ds / "masks" / "00000.npy")
    assert iou(key[..., 0], truths[0] == 1) > 0.85  # polygon vs cv2.circle rasterisation
    assert iou(key[..., 1], truths[0] == 2) > 0.85  # GrabCut cut the square out of its box
    ious = mean_iou(ds, truths, [0], 2)
    assert min(ious) > 0.8, ious


# ---------------------------------------------------------------------------------------------------------------
# bad input: clear InputError, nothing written
# ---------------------------------------------------------------------------------------------------------------
@pytest.fixture()
def small(tmp_path):
    images, truths = toy_sequence(n=6)
    ds = make_ds(tmp_path, images)
    keys = tmp_path / "keys"
    atomic.write_yaml(keys / "mapping.yaml", {0: "red disk", 1: "blue square"})
    return ds, keys, truths


def expect_error(ds: Path, keys: Path, *fragments: str) -> str:
    with pytest.raises(InputError) as exc:
        propagate(ds, keys, preview="none", progress=False)
    msg = str(exc.value)
    for f in fragments:
        assert f in msg, msg
    assert not (ds / "masks").exists() and not (ds / "reports").exists() and not (ds / "mapping.yaml").exists()
    return msg


def test_bad_wrong_size(small):
    ds, keys, truths = small
    atomic.write_image(keys / "00000.png", np.zeros((50, 60), np.uint8))
    expect_error(ds, keys, "60x50", "128x96")


def test_bad_empty_mask(small):
    ds, keys, truths = small
    atomic.write_image(keys / "00000.png", np.full((96, 128), 255, np.uint8))
    expect_error(ds, keys, "empty")
    (keys / "00000.png").unlink()
    atomic.write_json(keys / "00000.json", labelme([]))
    expect_error(ds, keys, "empty")


def test_bad_object_on_no_keyframe(small):
    ds, keys, truths = small
    only_disk = truths[0].copy()
    only_disk[only_disk == 2] = 0
    atomic.write_image(keys / "00000.png", only_disk)
    expect_error(ds, keys, "blue square", "no keyframe")


def test_bad_unknown_names(small):
    ds, keys, truths = small
    bad = truths[0].copy()
    bad[0:5, 0:5] = 7
    atomic.write_image(keys / "00000.png", bad)
    expect_error(ds, keys, "[7]")
    (keys / "00000.png").unlink()
    atomic.write_json(keys / "00000.json", labelme([{"label": "fridge", "points": disk_polygon(20, 20, 5),
                                                     "shape_type": "polygon"}]))
    expect_error(ds, keys, "'fridge'")


def test_bad_keyframe_not_a_frame(small):
    ds, keys, truths = small
    atomic.write_image(keys / "00042.png", truths[0])
    expect_error(ds, keys, "00042", "not among")


def test_bad_overlapping_polygons(small):
    ds, keys, truths = small
    shapes = [{"label": "red disk", "points": [[10, 10], [50, 10], [50, 50], [10, 50]], "shape_type": "polygon"},
              {"label": "blue square", "points": [[40, 40], [80, 40], [80, 80], [40, 80]], "shape_type": "polygon"}]
    atomic.write_json(keys / "00000.json", labelme(shapes))
    msg = expect_error(ds, keys, "overlap", "121 pixels", "x 40..50, y 40..50")
    assert "red disk" in msg and "blue square" in msg


def test_bad_corrupt_files(small):
    ds, keys, truths = small
    atomic.write_bytes(keys / "00000.png", b"\x89PNG\r\n\x1a\nnot really")
    expect_error(ds, keys, "cannot decode")
    (keys / "00000.png").unlink()
    atomic.write_text(keys / "00000.json", "{ not json")
    expect_error(ds, keys, "not valid LabelMe JSON")


def test_bad_no_frames(tmp_path):
    with pytest.raises(InputError, match="interreal frames"):
        propagate(tmp_path, tmp_path, preview="none", progress=False)


def test_crash_midway_leaves_failed_report(small, monkeypatch):
    ds, keys, truths = small
    atomic.write_image(keys / "00000.png", truths[0])
    import interreal.masks.stage as stage

    calls = {"n": 0}
    real = stage.write_mask

    def flaky(*a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("disk full")
        return real(*a, **k)

    monkeypatch.setattr(stage, "write_mask", flaky)
    with pytest.raises(RuntimeError):
        propagate(ds, keys, preview="none", progress=False)
    rep = json.loads((ds / "reports" / "masks.json").read_text())
    assert rep["status"] == "failed" and "disk full" in rep["error"]


def test_cli_suggest(small, capsys):
    from interreal.cli import main

    ds, keys, truths = small
    atomic.write_image(keys / "00000.png", truths[0])
    assert main(["masks", str(ds), "--keyframes", str(keys), "--suggest", "2", "--quiet", "--preview", "sheet"]) == 0
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if ln.startswith("annotate next:"))
    first = line.split(":")[1].split(",")[0].strip()
    assert int(first) >= 3, line  # far from the only keyframe (00000), where the chain is least checked
    assert main(["masks", str(ds), "--keyframes", str(ds / "nope")]) == 2
    assert "does not exist" in capsys.readouterr().err


@pytest.mark.parametrize("flow", ["rlof", "farneback"])
def test_other_flow_methods(tmp_path, flow):
    images, truths = toy_sequence(n=8)
    ds = make_ds(tmp_path, images)
    write_keys(tmp_path / "keys", truths, [0, 7], ["red disk", "blue square"])
    propagate(ds, tmp_path / "keys", flow=flow, preview="none", progress=False)
    assert min(mean_iou(ds, truths, [0, 7], 2)) > 0.8


def jump_clip(n: int = 11, w: int = 128, h: int = 96, jump_at: int = 7) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """A red disk on static grey texture that jumps 56 px between frames jump_at-1 and jump_at.

    Flow cannot follow the jump, so each chain is right on its own side of it and confidently wrong (flow is
    consistent: the background just stays put) on the other side, where it keeps the disk at its old place.
    """
    rng = np.random.default_rng(0)
    bg = cv2.resize(rng.integers(60, 200, (h // 4, w // 4), np.uint8), (w, h), interpolation=cv2.INTER_NEAREST)
    bg = np.repeat(cv2.GaussianBlur(bg, (3, 3), 0)[..., None], 3, -1)
    images, truths = [], []
    for t in range(n):
        m = np.zeros((h, w), np.uint8)
        cv2.circle(m, (round(28 + 1.5 * t + (56 if t >= jump_at else 0)), 48), 14, 1, -1)
        im = bg.copy()
        im[m > 0] = (220, 30, 30)
        images.append(im)
        truths.append(m)
    return images, truths


def test_fusion_colour_vote_settles_disagreeing_chains():
    """Two confident chains that disagree: the one whose labels fit the keyframes' colours wins the region."""
    from interreal.masks.track import Propagator, TrackConfig

    images, truths = jump_clip()

    def fused(vote: float) -> dict[int, float]:
        p = Propagator(lambda i: images[i], len(images), (128, 96), 1, TrackConfig(vote=vote))
        out = {r.pos: r for r in p.run({0: truths[0], 10: truths[10]})}
        return {t: iou(out[t].labels == 1, truths[t] > 0) for t in range(1, 10)}

    with_vote, without = fused(8.0), fused(0.0)
    # frame 6: the backward chain (4 frames away, outweighing the forward chain's 6) keeps the disk where it
    # lands after the jump; without the vote it wins, with the vote the red disk's colours win
    assert without[6] < 0.3 and without[5] < 0.8, without
    assert min(with_vote.values()) > 0.9, with_vote


def test_the_vote_reads_only_the_box_around_the_disagreement_and_matches_the_whole_frame():
    """`_vote` works on the box around the pixels the chains disagree on. The reference: the same frame with a
    lone disagreeing pixel in two opposite corners (too small to vote), so that its box is the whole frame; the
    same disagreement inside a larger frame, or at its corner, must get the same weights, and nothing else may
    change."""
    from interreal.masks.track import Propagator, TrackConfig

    rng = np.random.default_rng(3)
    h, w, k = 40, 50, 2
    lf = np.full((h, w), k, np.uint8)  # both chains: background ...
    lb = lf.copy()
    cv2.circle(lf, (20, 18), 9, 0, -1)  # ... but for a disk the forward chain calls object 0
    cv2.rectangle(lb, (30, 5), (45, 30), 1, -1)  # and a box the backward one calls object 1
    bins = rng.integers(0, 16, (h, w))
    table = (np.array([3.0, 3.0, 0.0]) + rng.normal(0, 0.3, (16, k + 1))).astype(np.float32)  # objects' colours
    wf, wb = rng.random((h, w)).astype(np.float32), rng.random((h, w)).astype(np.float32)
    p = Propagator(lambda i: np.zeros((h, w, 3), np.uint8), 2, (w, h), k, TrackConfig(vote=8.0, vote_min_px=10))
    framed = lf.copy()
    framed[0, 0] = framed[-1, -1] = 0
    want = p._vote(framed, lb, wf, wb, bins, table)
    assert not np.allclose(want[0], wf) and not np.allclose(want[1], wb)  # the vote changed both chains' weights
    for y, x in ((0, 0), (37, 61)):  # at the big frame's corner, then inside it
        big = [np.full((120, 140), fill, a.dtype) for a, fill in ((lf, k), (lb, k), (bins, 0))]
        bw = [np.full((120, 140), 0.5, np.float32) for _ in range(2)]
        for a, b in zip(big + bw, (lf, lb, bins, wf, wb)):
            a[y: y + h, x: x + w] = b
        got = p._vote(big[0], big[1], bw[0], bw[1], big[2], table)
        for g, ref, b in zip(got, want, bw):
            np.testing.assert_allclose(g[y: y + h, x: x + w], ref, rtol=1e-6)
            outside = np.ones(g.shape, bool)
            outside[y: y + h, x: x + w] = False
            assert (g[outside] == b[outside]).all()


# ---------------------------------------------------------------------------------------------------------------
# speed paths must not change the result
# ---------------------------------------------------------------------------------------------------------------
def test_prefetch_thread_gives_identical_masks(tmp_path):
    """Flow and decoding on the worker thread (prefetch), each gap's forward chain on its own thread while the
    previous gap is fused, and the one-sided chains' full-size labels made a frame behind them on a thread of their
    own, produce exactly the inline result (one-sided chains at both ends, two gaps between)."""
    from interreal.masks.stage import make_config

    images, truths = toy_sequence(n=14)
    ds = make_ds(tmp_path, images)
    keys = write_keys(tmp_path / "keys", truths, [2, 6, 10], ["red disk", "blue square"])
    out = {}
    for prefetch in (0, 3):
        shutil.rmtree(ds / "masks", ignore_errors=True)
        cfg = dataclasses.replace(make_config(), prefetch=prefetch)
        propagate(ds, keys, config=cfg, preview="none", suggest=0, progress=False)
        out[prefetch] = [np.load(ds / "masks" / f"{fid_of_index(i)}.npy") for i in range(len(images))]
    for a, b in zip(out[0], out[3]):
        assert np.array_equal(a, b)


def test_steps_made_ahead_on_the_flow_worker_are_the_inline_ones():
    """The worker makes each planned direction's Step beside the flows; `step` takes that one (once) and it equals
    the Step made on the chain's thread; a direction not planned is made there."""
    from interreal.masks.track import Propagator, TrackConfig

    images, _ = toy_sequence(n=4)
    prop = Propagator(lambda i: images[i], 4, (images[0].shape[1], images[0].shape[0]), 2, TrackConfig(prefetch=2))
    inline = Propagator(lambda i: images[i], 4, (images[0].shape[1], images[0].shape[0]), 2, TrackConfig(prefetch=0))
    try:
        prop.plan([0, 1], {0: ((0, 1),), 1: ((2, 1),)})
        prop.pair(0), prop.pair(1)
        assert set(prop._steps) == {(0, 1), (2, 1)}
        for src, dst in ((0, 1), (2, 1), (1, 0)):
            got, want = prop.step(src, dst), inline.step(src, dst)
            for name in ("map_x", "map_y", "trust"):
                assert np.array_equal(getattr(got, name), getattr(want, name)), (src, dst, name)
        assert not prop._steps  # each taken once
        prop.release(pair=0)
        assert 0 not in prop._flows
    finally:
        prop.close()
        inline.close()


def test_each_keyframes_colour_model_is_fit_once_for_all_its_chains(tmp_path, monkeypatch):
    """The chain that ends a gap at a keyframe and the one that starts the next gap from it (on another thread) share
    one fit of its colour model (the same inputs: test_prefetch_thread_gives_identical_masks checks the masks)."""
    from interreal.masks import appearance
    from interreal.masks.stage import make_config

    images, truths = toy_sequence(n=14)
    ds = make_ds(tmp_path, images)
    keys = write_keys(tmp_path / "keys", truths, [2, 6, 10], ["red disk", "blue square"])
    fit = appearance.ColourModel.fit.__func__
    seen: list[tuple[int, int]] = []
    alive: list = []  # the arrays kept alive: a freed array's id may be reused by the next one (a false "twice")

    def counting(cls, image, soft, known, cfg):
        seen.append((id(soft), id(known)))  # a chain's start passes its keyframe's anchor arrays themselves
        alive.append((soft, known))
        return fit(cls, image, soft, known, cfg)

    monkeypatch.setattr(appearance.ColourModel, "fit", classmethod(counting))
    propagate(ds, keys, config=dataclasses.replace(make_config(), prefetch=3), preview="none", suggest=0,
              progress=False)
    # 6 chain starts (before 2, 2->6 both ways, 6->10 both ways, after 10) on 3 keyframes: 3 fits; health's
    # references and the one-sided chains' held-out folds fit on arrays of their own
    assert len(seen) == len(set(seen)), "a keyframe's model was fit twice"
    assert len(set(seen)) >= 3


def test_a_long_gap_makes_only_its_forward_steps_ahead(monkeypatch):
    """Backward Steps of a gap wait in memory for its backward chain: past LONG_GAP frames only the forward ones
    are made on the worker (the rest on the chain's thread), and the masks are the same either way."""
    from interreal.masks import track
    from interreal.masks.track import Propagator, TrackConfig

    n = track.LONG_GAP + 6
    rng = np.random.default_rng(0)
    base = rng.integers(0, 255, (30, 40, 3), np.uint8)
    images = [np.roll(base, i // 4, axis=1) for i in range(n)]
    anchor = np.zeros((30, 40), np.uint8)
    anchor[10:20, 10:20] = 1
    plans: list[dict] = []
    plan = Propagator.plan

    def recording(self, pairs, dirs=None):
        plans.append(dirs)
        return plan(self, pairs, dirs)

    monkeypatch.setattr(Propagator, "plan", recording)
    out = []
    for long_gap in (track.LONG_GAP, n):  # the gap of n - 3 frames: long, then (the limit raised) short
        monkeypatch.setattr(track, "LONG_GAP", long_gap)
        prop = Propagator(lambda i: images[i], n, (40, 30), 1, TrackConfig(prefetch=3))
        out.append([r.labels for r in sorted(prop.run({1: anchor, n - 2: anchor}), key=lambda r: r.pos)])
    long_dirs, short_dirs = [d for d in plans if d]  # close() plans nothing
    assert long_dirs[5] == ((5, 6),) and short_dirs[5] == ((5, 6), (6, 5))
    assert long_dirs[0] == short_dirs[0] == ((1, 0),)  # before the first keyframe: backward only
    for a, b in zip(*out):
        assert np.array_equal(a, b)


def test_filter_objects_and_argmax_match_the_plain_versions():
    from interreal.masks.soft import argmax_channels as _argmax_channels, argmax_labels as _argmax_labels
    from interreal.masks.track import filter_objects

    rng = np.random.default_rng(0)
    for k in (1, 3):
        soft = rng.random((40, 50, k + 1)).astype(np.float32)
        soft /= soft.sum(-1, keepdims=True)
        guide = rng.random((40, 50, 3)).astype(np.float32)
        plain = cv2.ximgproc.guidedFilter(guide, soft, 3, 0.02).reshape(40, 50, -1)
        fast = filter_objects(lambda x: cv2.ximgproc.guidedFilter(guide, x, 3, 0.02), soft)
        assert np.abs(plain - fast).max() < 1e-4
        idx = np.argmax(soft, -1) + 1
        idx[idx == k + 1] = 0
        assert np.array_equal(_argmax_labels(soft), idx)
        assert np.array_equal(_argmax_channels(soft), np.argmax(soft, -1))


def test_keyframe_reach_counts_view_motion_from_the_nearest_keyframe():
    from interreal.masks.confidence import keyframe_reach, reach_suggestion

    motion = np.full(19, 0.01)  # 20 frames, the view moves 1 % of its width per frame
    motion[10:15] = 0.05        # ... and fast between frames 10 and 15
    reach = keyframe_reach(motion, [5, 15])
    assert [(a, b) for a, b, _ in reach] == [(0, 4), (6, 14), (16, 19)]
    assert np.allclose([r for _, _, r in reach], [0.05, (5 * 0.01 + 5 * 0.05) / 2, 0.04])  # one-sided ends: whole
    assert reach_suggestion(motion, 6, 14, [5, 15]) in (11, 12)  # halfway by motion, not by frame count (10)
    # one-sided stretches: two thirds of their motion away from their keyframe (both new worst reaches equal)
    assert reach_suggestion(motion, 0, 4, [5, 15]) == 2 and reach_suggestion(motion, 16, 19, [5, 15]) == 18
    fast_start = np.r_[np.full(3, 0.1), np.full(9, 0.01)]  # 13 frames, keyframe 0: most motion in frames 0-3
    assert reach_suggestion(fast_start, 1, 12, [0]) == 3  # by motion (0.3 of 0.39), not by frame count (8)
    assert reach_suggestion(fast_start, 0, 11, [12]) == 1  # before the first keyframe: walked back from it (0.29)
    assert keyframe_reach(motion, list(range(20))) == []


def panning_sequence(n: int, speed: int, w: int = 128, h: int = 96) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """A camera panning `speed` px per frame over a textured wall with a red disk painted on it."""
    rng = np.random.default_rng(3)
    wall = cv2.GaussianBlur(rng.integers(0, 255, (h, w + n * speed, 3), dtype=np.uint8), (0, 0), 2.0)
    lab = np.zeros(wall.shape[:2], np.uint8)
    cv2.circle(lab, (w // 2 + n * speed // 2, h // 2), 18, 1, -1)
    wall[lab > 0] = (210, 40, 40)
    return ([wall[:, t * speed:t * speed + w].copy() for t in range(n)],
            [lab[:, t * speed:t * speed + w].copy() for t in range(n)])


def test_fast_view_motion_between_keyframes_is_reported(tmp_path):
    from interreal.masks.stage import MAX_REACH

    images, truths = panning_sequence(16, 4)  # 3 % of the width per frame
    ds = make_ds(tmp_path, images)
    out = {}
    for name, keys in (("sparse", [0, 15]), ("dense", [0, 3, 6, 9, 12, 15])):
        propagate(ds, write_keys(tmp_path / name, truths, keys, ["disk"]), preview="none", suggest=0, progress=False)
        out[name] = json.loads((ds / "reports" / "masks.json").read_text())
    sparse, dense = out["sparse"]["figures"], out["dense"]["figures"]
    assert 0.2 < sparse["max_keyframe_reach"] < 0.26  # 15 frames x 3.1 %, halved: reached from both ends
    assert dense["max_keyframe_reach"] < MAX_REACH
    # the reach is measured, but a warning says the masks are poor: here the painted disk is tracked well
    assert mean_iou(ds, truths, [0, 3, 6, 9, 12, 15], 1)[0] > 0.8
    for name in out:
        assert not [w for w in out[name]["warnings"] if w["cause"] == "masks-unreliable"], out[name]["warnings"]


def test_cli_prints_the_reports_warnings(tmp_path, capsys):
    from interreal.cli import main

    images, truths = panning_sequence(16, 2)
    for t in range(6, 10):  # the disk is painted over: gone, though both keyframes show it
        images[t][truths[t] > 0] = images[t][truths[t] == 0].mean(0).astype(np.uint8)
    ds = make_ds(tmp_path, images)
    keys = write_keys(tmp_path / "keys", truths, [0, 15], ["disk"])
    assert main(["masks", str(ds), "--keyframes", str(keys), "--quiet", "--preview", "none"]) == 0
    out = capsys.readouterr().out
    assert "warning (masks): 'disk': object lost at frames 6-9" in out, out


def test_unchanged_rerun_reuses_the_masks(tmp_path):
    """Same frames, keyframes and settings: nothing is rewritten (so SfM's features stay valid); a changed
    keyframe or setting runs the stage again."""
    import os

    images, truths = toy_sequence(n=8)
    ds = make_ds(tmp_path, images)
    write_keys(tmp_path / "keys", truths, [0, 7], ["red disk", "blue square"])
    fig = propagate(ds, tmp_path / "keys", preview="none", progress=False)
    files = sorted((ds / "masks").glob("*.npy")) + sorted((ds / "sfm_masks").glob("*.png"))
    stamps = [p.stat().st_mtime_ns for p in files]
    again = propagate(ds, tmp_path / "keys", preview="none", progress=False)
    assert again == fig and [p.stat().st_mtime_ns for p in files] == stamps
    propagate(ds, tmp_path / "keys", preview="none", suggest=2, progress=False)  # another setting: runs
    assert [p.stat().st_mtime_ns for p in files] != stamps
    stamps = [p.stat().st_mtime_ns for p in files]
    key = sorted((tmp_path / "keys").iterdir())[0]
    os.utime(key, ns=(key.stat().st_atime_ns, key.stat().st_mtime_ns + 10 ** 9))  # keyframe edited
    propagate(ds, tmp_path / "keys", preview="none", suggest=2, progress=False)
    assert [p.stat().st_mtime_ns for p in files] != stamps


def test_masks_flags_come_from_the_config_fields():
    """`interreal masks` flags are generated from `MasksConfig`: the historic names, each field's default when not
    given, the typed value when given, and the same settings reach `propagate`'s TrackConfig."""
    import argparse

    from interreal.masks import MasksConfig, add_arguments, masks_options
    from interreal.masks.stage import make_config

    p = argparse.ArgumentParser()
    add_arguments(p)
    flags = {s for a in p._actions for s in a.option_strings} - {"-h", "--help"}
    assert flags == {"--keyframes", "--quiet", "--work-size", "--flow", "--preset", "--appearance", "--rigid", "--cut",
                     "--no-fusion", "--no-refine", "--suggest", "--preview", "--transients", "--no-reuse"}
    opts = masks_options(p.parse_args(["ds", "--keyframes", "kf"]))
    defaults = dataclasses.asdict(MasksConfig())
    assert opts == {k: defaults[k] for k in opts} and len(opts) == len(flags) - 2
    opts = masks_options(p.parse_args(["ds", "--keyframes", "kf", "--work-size", "0", "--no-fusion", "--no-refine",
                                       "--appearance", "0.5", "--flow", "farneback", "--no-reuse"]))
    assert opts["work_long_side"] == 0 and opts["fusion"] is False and opts["refine"] is False
    assert opts["reuse"] is False
    cfg = make_config(**opts)
    assert cfg.work_long_side == 0 and not cfg.fusion and cfg.refine_radius == 0 and cfg.out_radius == 0
    assert cfg.appearance.weight == 0.5 and cfg.flow.method == "farneback"
    with pytest.raises(SystemExit):
        p.parse_args(["ds", "--keyframes", "kf", "--preview", "gif"])
    with pytest.raises(InputError, match="unknown masks options"):
        make_config(work_size=0)
    assert make_config(cut=0.0).cut == 0.0 and make_config().cut == 0.5
    for name, bad in (("cut", 1.5), ("cut", float("nan")), ("rigid", -0.1), ("appearance", -1.0)):
        with pytest.raises(InputError, match=f"--{name}"):
            make_config(**{name: bad})
