"""The simulated capture: its truth is self-consistent, it is deterministic, and its folders are valid."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from interreal.errors import InputError
from interreal.synth import Capture, SynthConfig, build_scene, list_presets, load_preset, truth_dataset, write_capture
from interreal.synth.consistency import reprojection_error, unproject
from interreal.synth.render import NEAR, RayCaster

SMALL = dict(frames=30, width=320, height=240, seed=0)


@pytest.fixture(scope="module")
def scene():
    return build_scene(SynthConfig(**SMALL))


def test_intrinsics_are_phone_like(scene):
    intr = scene.intrinsics
    hfov = np.degrees(2 * np.arctan(intr.w / 2 / intr.fl_x))
    assert 60 <= hfov <= 70
    assert -0.08 <= intr.k1 <= -0.02 and abs(intr.k2) < 0.05
    # the caster's rays are exactly the pixel centres of the OpenCV model
    caster = RayCaster(intr)
    pts = np.stack([caster.xn.ravel(), caster.yn.ravel(), np.ones(caster.xn.size)], 1)
    px, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), intr.K(), intr.dist())
    u, v = np.meshgrid(np.arange(intr.w) + 0.5, np.arange(intr.h) + 0.5)
    err = np.abs(px.reshape(-1, 2) - np.stack([u.ravel(), v.ravel()], 1)).max()
    assert err < 1e-3


def test_a_rounded_box_is_drawn_as_its_inscribed_ellipsoid():
    """A sphere (a rounded cube) seen face-on covers its tangent cone's disc, not the cube's square, its depth is
    nearest at the centre, and its shading falls off toward the rim (its own normal, not one per face)."""
    from interreal.dataset import Intrinsics
    from interreal.synth.render import Lighting, Prims

    intr = Intrinsics(w=200, h=200, fl_x=400.0, fl_y=400.0, cx=100.0, cy=100.0)
    caster = RayCaster(intr)
    room = dict(R=np.eye(3)[None], c=np.zeros((1, 3)), h=np.full((1, 3), 50.0), inst=np.zeros(1, np.uint8),
                tile=np.zeros((1, 6), np.int64), scale=np.ones((1, 6)), offset=np.zeros((1, 6, 2)),
                inverted=np.ones(1, bool))
    cover = {}
    for rounded in (False, True):
        prims = Prims(**{k: np.concatenate([v, v[:1]]) for k, v in room.items()})
        prims.c[1], prims.h[1], prims.inst[1], prims.inverted[1] = (0, 0, 4.0), (0.5, 0.5, 0.5), 1, False
        prims.rounded = np.array([False, rounded])
        t, pid = caster.cast(np.eye(4), prims)
        cover[rounded] = (pid == 1).sum()
        if rounded:
            z = np.where(pid == 1, t, np.inf)
            assert np.unravel_index(np.argmin(z), z.shape) in {(99, 99), (99, 100), (100, 99), (100, 100)}
            assert abs(z.min() - 3.5) < 0.01
            atlas = np.ones((8, 8, 3), np.float32)
            lin = caster.shade(np.eye(4), prims, t, pid, atlas, np.zeros(1, np.float32), np.full(1, 8, np.float32),
                               Lighting(sun_dir=(0.0, 0.0, -1.0), point_gain=0.0))
            assert lin[100, 100, 0] > lin[100, 100 + 45, 0] + 0.1  # face-on at the centre, grazing at the rim
    r, d, f = 0.5, 4.0, 400.0  # the silhouettes in perspective: the cube's front face, the sphere's tangent cone
    assert abs(cover[False] / (2 * f * r / (d - r)) ** 2 - 1) < 0.02
    assert abs(cover[True] / (np.pi * (f * r / np.sqrt(d * d - r * r)) ** 2) - 1) < 0.02


def test_camera_path_and_schedule(scene):
    poses = scene.camera_path()
    states = scene.states()
    assert poses.shape == (30, 4, 4) and states.shape == (30, 2)
    R = poses[:, :3, :3]
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(R), 1.0)
    # arc around the furniture: wide baseline, 1-3 m from the furniture group
    centre = np.array([-0.15, 2.05])
    angles = np.degrees(np.arctan2(poses[:, 1, 3] - 1.45, poses[:, 0, 3]))
    assert np.ptp(angles) > 110
    dist = np.linalg.norm(poses[:, :2, 3] - centre, axis=1)
    assert dist.min() > 1.0 and dist.max() < 3.2
    # every part opens fully and closes; parts move at different times
    assert np.all(states.min(0) == 0.0) and np.all(states.max(0) > 0.99)
    moving = np.abs(np.diff(states, axis=0)) > 1e-6
    assert (moving[:, 0] != moving[:, 1]).mean() > 0.2
    # the parts are in view, and big enough for the mask and training stages, in most frames
    cover = np.array([[(scene.render(poses[i], states[i]).instance == k + 1).mean() for k in range(2)]
                      for i in range(0, 30, 3)])
    assert np.all(np.median(cover, axis=0) > 0.03) and np.all(np.mean(cover > 0.01, axis=0) >= 0.7)


def test_reprojection_of_static_pixels(scene):
    """Static pixels of frame i, moved into frame j with gt depth / poses / distorted intrinsics, keep their colour."""
    res = [reprojection_error(scene, i, j) for i, j in [(3, 4), (10, 12), (20, 21)]]
    for r in res:
        assert r["overlap"] > 0.3
    mae = np.mean([r["colour_mae"] for r in res])
    depth_rel = np.median([r["depth_rel"] for r in res])
    print(f"reprojection colour error {mae:.2f} / 255, depth {depth_rel:.2e}")
    assert mae < 3.0  # bilinear resampling of textured surfaces; a wrong convention gives > 15
    assert depth_rel < 2e-3
    # the check has teeth: warping with a camera model without the distortion, or with the principal point half a
    # pixel off, puts the static points at depths frame j does not see (colour alone hides it: textures are smooth)
    from dataclasses import replace

    intr = scene.intrinsics
    true_rel = reprojection_error(scene, 10, 12)["depth_rel"]
    for wrong in (replace(intr, k1=0.0, k2=0.0), replace(intr, cx=intr.cx + 0.5, cy=intr.cy + 0.5)):
        assert true_rel < 0.01 * reprojection_error(scene, 10, 12, assumed=wrong)["depth_rel"]


def _box_distance(points: np.ndarray, R: np.ndarray, c: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Distance of points to the surface of a box (0 on it)."""
    local = (points - c) @ R
    q = np.abs(local) - h
    outside = np.linalg.norm(np.maximum(q, 0), axis=-1)
    inside = np.minimum(q.max(-1), 0)
    return np.abs(outside + inside)


def test_instance_masks_agree_with_geometry(scene):
    """Every pixel labelled k lies on a surface of part k at its state; static pixels on static surfaces."""
    poses, states = scene.camera_path(), scene.states()
    for i in (4, 14, 24):
        r = scene.render(poses[i], states[i])
        pts = unproject(poses[i], r.depth, scene.intrinsics)
        prims = scene.primitives(states[i])
        for k in range(len(scene.object_names) + 1):
            sel = r.instance == k
            if sel.sum() < 20:  # a part hidden by another one in this view
                continue
            boxes = np.nonzero(prims.inst == k)[0]
            d = np.min([_box_distance(pts[sel], prims.R[b], prims.c[b], prims.h[b]) for b in boxes], axis=0)
            assert np.quantile(d, 0.999) < 2e-3 * np.quantile(r.depth[sel], 0.999)
        # part boundaries are depth edges or surface creases, never inside a flat surface: the instance changes
        # only where the (unprojected) point jumps between surfaces
        assert r.depth.min() > NEAR


def test_changing_one_part_changes_only_its_pixels(scene):
    poses = scene.camera_path()
    base = np.array([0.2, 0.3])
    for k in range(2):
        moved = base.copy()
        moved[k] = 0.9
        a = scene.render(poses[15], base)
        b = scene.render(poses[15], moved)
        changed = np.any(a.rgb != b.rgb, axis=-1) | (a.depth != b.depth) | (a.instance != b.instance)
        part = (a.instance == k + 1) | (b.instance == k + 1)
        assert changed.sum() > 200
        assert not np.any(changed & ~part), f"moving part {k} changed {np.sum(changed & ~part)} other pixels"
        uncovered = part & (b.instance != k + 1)
        assert np.all(b.instance[uncovered] != k + 1)


def test_determinism():
    cfg = SynthConfig(frames=20, width=160, height=120, seed=5, noise=3.0, exposure_drift=0.2, occluder=0.5)
    a, b = build_scene(cfg), build_scene(cfg)
    for i in (0, 9, 19):
        ra, rb = a.render_frame(i), b.render_frame(i)
        assert np.array_equal(ra.rgb, rb.rgb) and np.array_equal(ra.depth, rb.depth)
        assert np.array_equal(ra.instance, rb.instance)
    assert np.array_equal(a.camera_path(), b.camera_path()) and np.array_equal(a.states(), b.states())
    c = build_scene(SynthConfig(frames=20, width=160, height=120, seed=6, noise=3.0, exposure_drift=0.2, occluder=0.5))
    assert not np.array_equal(a.render_frame(9).rgb, c.render_frame(9).rgb)
    assert not np.allclose(a.camera_path(), c.camera_path())


def test_stress_options_change_the_video():
    base = dict(frames=40, width=160, height=120, seed=1)
    clean = build_scene(SynthConfig(**base))
    i = 10  # the camera moves fastest here at speed 2
    ref = clean.render_frame(i)
    blur = build_scene(SynthConfig(**base, motion_blur=0.8, speed=2.0)).render_frame(i)
    noisy = build_scene(SynthConfig(**base, noise=5.0)).render_frame(i)
    assert np.array_equal(blur.depth, build_scene(SynthConfig(**base, speed=2.0)).render_frame(i).depth)
    lap = lambda im: cv2.Laplacian(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY), cv2.CV_32F).var()  # noqa: E731
    assert lap(blur.rgb) < 0.8 * lap(build_scene(SynthConfig(**base, speed=2.0)).render_frame(i).rgb)
    diff = noisy.rgb.astype(float) - ref.rgb.astype(float)
    assert 3.5 < diff.std() < 6.5
    occ = build_scene(SynthConfig(**base, occluder=0.6))
    covered = [float((occ.render_frame(f).instance == 255).mean()) for f in range(0, 40, 4)]
    assert 0.2 <= np.mean(np.array(covered) > 0.01) <= 0.9 and max(covered) > 0.05
    drift = build_scene(SynthConfig(**base, exposure_drift=0.3))
    ratios = [drift.render_frame(f).rgb.mean() / clean.render_frame(f).rgb.mean() for f in (0, 13, 26, 39)]
    assert np.ptp(ratios) > 0.1
    step = lambda sc: np.linalg.norm(np.diff(sc.camera_path()[:, :3, 3], axis=0), axis=1).mean()  # noqa: E731
    assert step(build_scene(SynthConfig(**base, speed=3.0))) > 2.0 * step(clean)
    wide = build_scene(SynthConfig(**base, articulation=1.4))
    assert wide.parts[0].max_motion == pytest.approx(1.4 * clean.parts[0].max_motion)
    many = build_scene(SynthConfig(**base, parts=10))
    assert len(set(many.object_names)) == 10 and all(many.descriptions[n] for n in many.object_names)
    for tex in ("low", "none"):
        flat = build_scene(SynthConfig(**base, texture=tex)).render(clean.camera_path()[i], clean.states()[i])
        wall = flat.instance == 0
        assert lap(flat.rgb) < lap(ref.rgb) and flat.rgb[wall].std() < ref.rgb[ref.instance == 0].std() * 1.5


def test_presets_and_config_checks():
    names = list_presets()
    assert {"default", "small", "stress-blur", "stress-occluder", "stress-parts"} <= set(names)
    for name in names:
        SynthConfig.from_dict(load_preset(name)).check()
    with pytest.raises(InputError):
        SynthConfig(parts=11).check()
    with pytest.raises(InputError):
        SynthConfig(width=161).check()
    with pytest.raises(InputError):
        SynthConfig.from_dict({"framez": 3})
    with pytest.raises(InputError):
        load_preset("no-such-preset")


def test_write_capture_and_truth_dataset(tmp_path: Path):
    from interreal.dataset import load_dataset, validate

    cfg = SynthConfig(frames=24, width=160, height=120, seed=2, keyframe_every=10, label_fraction=0.25, occluder=0.3)
    out = write_capture(cfg, tmp_path / "cap", progress=False)
    for rel in ("video.mp4", "gt/cameras.json", "gt/states.json", "gt/mapping.yaml", "gt/prompts.yaml",
                "gt/meta.json", "annotations/states.yaml", "annotations/prompts.yaml",
                "annotations/keyframes/mapping.yaml"):
        assert (out / rel).is_file(), rel
    assert len(list((out / "gt" / "depth").glob("*.png"))) == 24
    assert len(list((out / "gt" / "instance").glob("*.png"))) == 24
    assert sorted(p.stem for p in (out / "annotations" / "keyframes").glob("*.png")) == ["00000", "00010", "00020",
                                                                                          "00023"]
    assert not list(out.glob(".synth-partial*"))
    meta = json.loads((out / "gt" / "meta.json").read_text())
    assert meta["config"]["frames"] == 24 and meta["timings"]["total_s"] > 0
    labels = yaml.safe_load((out / "annotations" / "states.yaml").read_text())
    assert {"frame_00000", "frame_00023"} <= set(labels) and 6 <= len(labels) <= 10

    cap = Capture.open(out)
    scene = cap.scene()
    assert cap.names == scene.object_names == ["fridge door", "top drawer"]
    assert np.allclose(cap.poses, scene.camera_path()) and np.allclose(cap.states, scene.states())
    for key, entry in labels.items():
        i = int(key.split("_")[-1])
        assert [entry[n] for n in cap.names] == pytest.approx(cap.states[i].tolist(), abs=0)
    truth = scene.render_frame(7)
    assert np.abs(cap.depth(7) - truth.depth).max() < 1.0 / 4000 and np.array_equal(cap.instance(7), truth.instance)
    frames = list(cap.frames())
    assert len(frames) == 24
    mse = np.mean((frames[7][1].astype(float) - truth.rgb.astype(float)) ** 2)
    assert 10 * np.log10(255 ** 2 / mse) > 30  # H.264 at crf 17 is close to the render
    # a second run into the same folder replaces the capture
    write_capture(cfg, out, progress=False)

    ds = truth_dataset(out, tmp_path / "ds", size=(80, 60), every=3)
    result = validate(ds)
    assert result.ok, [str(p) for p in result.problems]
    loaded = load_dataset(ds)
    assert loaded.object_names == cap.names and loaded.intrinsics.w == 80
    assert loaded.intrinsics.fl_x == pytest.approx(scene.intrinsics.fl_x / 2)
    kept = {f.index for f in loaded.frames}
    assert set(range(0, 24, 3)) <= kept and {int(k.split("_")[-1]) for k in loaded.labels} <= kept
    mask = loaded.load_mask(loaded.frames[0])
    assert mask.shape == (60, 80, 3) and np.all(mask.sum(-1) == 1)
    # the dataset's images, poses and scaled intrinsics are the renderer's: re-render a frame from them
    fr = loaded.frames[2]
    states = [loaded.labels.get(fr.key, {}).get(n, cap.states[fr.index, k]) for k, n in enumerate(cap.names)]
    again = scene.render(fr.c2w, states, intrinsics=loaded.intrinsics, frame=fr.index, supersample=2)
    mse = np.mean((loaded.load_image(fr).astype(float) - again.rgb.astype(float)) ** 2)
    assert 10 * np.log10(255 ** 2 / mse) > 30
    index = np.where(again.instance == 255, 0, again.instance)
    assert (np.argmax(loaded.load_mask(fr), -1) + 1) % 3 == pytest.approx(index, abs=0)


def test_write_capture_refuses_foreign_folder(tmp_path: Path):
    (tmp_path / "gt").mkdir()
    with pytest.raises(InputError):
        write_capture(SynthConfig(frames=2, width=32, height=24), tmp_path, progress=False)


def test_cli_writes_capture_and_truth_dataset(tmp_path: Path, capsys):
    from interreal.cli import main
    from interreal.dataset import validate

    out, ds = tmp_path / "cap", tmp_path / "ds"
    rc = main(["synth", str(out), "--preset", "small", "--frames", "6", "--size", "64x48", "--parts", "3",
               "--noise", "2", "--quiet", "--truth-dataset", str(ds)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "frames/s" in text and "video.mp4" in text and "microwave door" in text
    meta = json.loads((out / "gt" / "meta.json").read_text())
    assert meta["config"]["noise"] == 2.0 and meta["config"]["keyframe_every"] == 30 and meta["size"] == [64, 48]
    assert validate(ds).ok and "64x48" in validate(ds).summary["size"]
    assert main(["synth", str(tmp_path / "bad"), "--size", "65x48"]) == 2


def test_textures_are_the_skimage_photographs():
    import skimage.data

    from interreal.synth.textures import _FILES, _load

    for name in ("astronaut", "rocket", "page", "brick"):
        assert name in _FILES and np.array_equal(_load(name), np.asarray(getattr(skimage.data, name)()))


def test_room_scale_resizes_the_room_and_leaves_the_default_unchanged():
    base = dict(frames=20, width=160, height=120, seed=3, parts=10)
    default, explicit = build_scene(SynthConfig(**base)), build_scene(SynthConfig(**base, room_scale=1.0))
    for i in (0, 10, 19):
        a, b = default.render_frame(i), explicit.render_frame(i)
        assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth) and np.array_equal(a.instance, b.instance)
    # figures of this render measured before room_scale existed: the default room must not have moved
    r = default.render_frame(10)
    assert float(r.depth.astype(np.float64).sum()) == pytest.approx(52793.94, abs=0.01)
    assert float(r.rgb.mean()) == pytest.approx(83.057, abs=1e-3)
    np.testing.assert_allclose(default.camera_path()[5][:3, 3], [-1.405362, 0.067313, 1.406202], atol=1e-6)

    def far_depth(s: float) -> float:
        sc = build_scene(SynthConfig(frames=20, width=80, height=60, seed=0, room_scale=s))
        return float(np.mean([np.percentile(sc.render_frame(i).depth, 95) for i in (0, 10, 19)]))

    small, medium, large = far_depth(0.7), far_depth(1.0), far_depth(1.6)
    assert small < 0.9 * medium and large > 1.3 * medium
    big = build_scene(SynthConfig(**base, room_scale=1.6))
    assert big.object_names == default.object_names  # all ten parts still fit, moved with their walls
    cam = np.linalg.norm(big.camera_path()[:, :2, 3] - [0.0, 1.45], axis=1).mean()
    assert cam == pytest.approx(1.6 * np.linalg.norm(default.camera_path()[:, :2, 3] - [0.0, 1.45], axis=1).mean(), rel=0.05)
    with pytest.raises(InputError, match="chest lid"):  # side-wall furniture does not fit a small room
        build_scene(SynthConfig(**base, room_scale=0.7))
    assert len(build_scene(SynthConfig(**{**base, "parts": 6}, room_scale=0.7)).object_names) == 6
    for bad in (0.0, -1.0, 0.5, 3.0):
        with pytest.raises(InputError, match="room_scale"):
            SynthConfig(room_scale=bad).check()
    assert load_preset("room-small")["room_scale"] == 0.7 and load_preset("room-large")["room_scale"] == 1.6
    import argparse

    from interreal.synth.cli import add_arguments, config_from_args

    p = argparse.ArgumentParser()
    add_arguments(p)
    assert config_from_args(p.parse_args(["out", "--preset", "room-small"])).room_scale == 0.7
    assert config_from_args(p.parse_args(["out", "--preset", "room-small", "--room-scale", "1.2"])).room_scale == 1.2


def test_every_part_gets_a_keyframe():
    """A part that no regular keyframe shows is annotated where it shows most (a person would draw it somewhere)."""
    from interreal.synth.capture import extra_keyframes

    px = np.zeros((30, 3), np.int64)
    px[:, 0] = 100          # always visible
    px[12:18, 1] = [5, 40, 90, 60, 10, 2]  # only between the keyframes 10 and 20
    # part 2 never visible: nothing to annotate
    assert extra_keyframes(px, [0, 10, 20, 29]) == [14]
    assert extra_keyframes(px, [0, 14, 29]) == []
    # part 2 (id 3) never shows, so it is not named: ids after it move down; the occluding person is background
    from interreal.synth.capture import annotation_index

    lut = np.zeros(256, np.uint8)
    lut[[1, 2, 4]] = [1, 2, 3]
    assert annotation_index(np.array([[0, 1, 2, 4, 255]], np.uint8), lut).tolist() == [[0, 1, 2, 3, 0]]
    # a careful user paints the person and the arm as the ignore class (what the masks stage propagates as transient)
    assert annotation_index(np.array([[0, 1, 2, 4, 255]], np.uint8), lut, paint_occluders=True).tolist() == [
        [0, 1, 2, 3, 254]]


def test_ten_parts_annotations_name_only_what_the_video_shows(tmp_path):
    """With many parts some stay out of view: the simulated person names only parts the video shows, draws each of
    them on some keyframe (consecutive ids), and the truth keeps every part."""
    import cv2
    import yaml

    from interreal.synth import SynthConfig, write_capture

    cap = write_capture(SynthConfig(frames=12, width=64, height=48, parts=10, keyframe_every=6), tmp_path / "cap",
                        progress=False)
    gt_names = list(yaml.safe_load((cap / "gt" / "mapping.yaml").read_text()).values())
    ann = yaml.safe_load((cap / "annotations" / "mapping.yaml").read_text())
    assert len(gt_names) == 10 and sorted(ann) == list(range(len(ann)))
    inst = np.stack([cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in sorted((cap / "gt" / "instance").glob("*.png"))])
    seen = {gt_names[k] for k in range(10) if (inst == k + 1).any()}
    assert set(ann.values()) == seen
    keys = np.stack([cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in (cap / "annotations" / "keyframes").glob("*.png")])
    assert set(np.unique(keys)) - {0} == set(range(1, len(ann) + 1))  # every named part is drawn somewhere
    states = yaml.safe_load((cap / "annotations" / "states.yaml").read_text())
    assert all(set(v) == seen for v in states.values())


def test_plain_furniture_paints_the_parts_and_keeps_the_rest_of_the_capture():
    """`furniture="plain"`: every furniture and part surface one flat colour (a painted cabinet door), the room's
    texture, the camera path and the states as the photo version draws them."""
    cfg = dict(frames=30, width=160, height=120, seed=4, threads=1)
    photo, plain = build_scene(SynthConfig(**cfg)), build_scene(SynthConfig(**cfg, furniture="plain"))
    assert np.allclose(photo.camera_path(), plain.camera_path()) and np.allclose(photo.states(), plain.states())
    poses, states = photo.camera_path(), photo.states()
    a, b = photo.render(poses[15], states[15], frame=15), plain.render(poses[15], states[15], frame=15)
    assert np.array_equal(a.instance, b.instance)
    door = a.instance == 1
    inside = cv2.erode(door.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0

    def grey(r):
        return cv2.cvtColor(np.asarray(r.rgb, np.float32), cv2.COLOR_RGB2GRAY)

    def edges(r):
        return np.abs(cv2.Laplacian(grey(r), cv2.CV_32F))[inside]

    assert door.sum() > 200 and edges(b).mean() < 0.2 * edges(a).mean()  # no texture on the painted door
    room = a.instance == 0
    assert np.abs(grey(a)[room] - grey(b)[room]).mean() < 0.5 * np.abs(grey(a)[room]).mean()  # the room stays
    with pytest.raises(InputError, match="furniture"):
        SynthConfig(furniture="chrome").check()


def test_an_arm_holds_each_part_while_it_moves():
    """`arm`: a skin hand at the moving part and a sleeve of another colour from the image edge, in the occluder
    class (255) of the truth, only while a part moves; the clean render and every capture without it unchanged."""
    base = dict(frames=60, width=160, height=120, seed=4, parts=1)
    plain, arm = build_scene(SynthConfig(**base)), build_scene(SynthConfig(**base, arm=True))
    moving = [t for t in range(60) if arm.moving(t)]
    still = [t for t in range(60) if not arm.moving(t)]
    assert moving and still
    for t in moving[:: max(1, len(moving) // 4)]:
        r = arm.render_frame(t)
        occ = r.instance == 255
        assert 0.005 < occ.mean() < 0.4
        ys, xs = np.nonzero(occ)
        assert ys.max() >= 118 or xs.max() >= 158  # it enters from the image edge
        colours = r.rgb[occ].astype(float)
        green = colours[:, 1] > colours[:, 0] + 20  # the sleeve
        skin = (colours[:, 0] > colours[:, 1] + 20) & (colours[:, 0] > 120)  # the hand
        assert green.mean() > 0.5 and skin.sum() > 0
    for t in still[:3]:
        assert not (arm.render_frame(t).instance == 255).any()
        assert np.array_equal(arm.render_frame(t).rgb, plain.render_frame(t).rgb)
    i = moving[len(moving) // 2]
    assert np.array_equal(arm.render(arm.camera_path()[i], arm.states()[i]).rgb,
                          plain.render(plain.camera_path()[i], plain.states()[i]).rgb)  # clean: no arm
