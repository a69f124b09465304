"""Poses: orientation and alignment maths, a small simulated capture end to end, resume, import, failures."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from interreal import atomic, cli
from interreal.conventions import frame_id
from interreal.dataset import load_dataset, validate
from interreal.errors import InputError, StageError
from interreal.frames import extract_frames
from interreal.scoring import compare_poses, umeyama
from interreal.sfm import (
    _rot_between,
    apply_similarity,
    estimate_poses,
    estimate_up,
    orientation_transform,
)
from interreal.sfm.geometry import level_up


# ------------------------------------------------------------------------------------------------ a simulated capture
def render_capture(out: Path, frames: int = 24, size=(320, 240), seed: int = 0) -> Path:
    """A simulated capture: video.mp4 + gt/cameras.json + gt/instance/ (+ depth, annotations)."""
    from interreal.synth import SynthConfig, write_capture

    write_capture(SynthConfig(frames=frames, width=size[0], height=size[1], seed=seed), out, progress=False)
    return out


def truth_masks_npy(capture: Path, ds: Path) -> None:
    """DS/masks/<fid>.npy one-hot (objects..., background last) from the simulator's instance maps."""
    for img in sorted((ds / "images").glob("*.png")):
        fid = frame_id(img)
        inst = cv2.imread(str(capture / "gt" / "instance" / f"{fid}.png"), cv2.IMREAD_UNCHANGED)
        onehot = np.stack([inst == 1, inst == 2, (inst != 1) & (inst != 2)], axis=2)
        atomic.write_npy(ds / "masks" / f"{fid}.npy", onehot)


def gt(capture: Path) -> dict[int, np.ndarray]:
    meta = json.loads((capture / "gt" / "cameras.json").read_text())
    return {f["index"]: np.asarray(f["transform_matrix"]) for f in meta["frames"]}


def errors(ds: Path, truth: dict[int, np.ndarray]) -> dict[str, float]:
    d = load_dataset(ds)
    return compare_poses(np.stack([f.c2w for f in d.frames]), np.stack([truth[f.index] for f in d.frames]))


ONE_THREAD = 1  # the shared model is built and refined on one thread: multithreaded COLMAP is not repeatable


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    return render_capture(tmp_path_factory.mktemp("cap"))


@pytest.fixture(scope="module")
def posed(capture, tmp_path_factory) -> tuple[Path, dict]:
    """The capture through frames + masks (truth) + poses, shared by several tests."""
    ds = tmp_path_factory.mktemp("ds") / "room"
    extract_frames(capture / "video.mp4", ds, target=24)
    truth_masks_npy(capture, ds)
    fig = estimate_poses(ds, num_threads=ONE_THREAD)
    return ds, fig


# ------------------------------------------------------------------------------------------------ maths
def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    R = _rot_between(np.array([1.0, 0, 0]), np.array([0.3, 0.4, 0.866]))
    dst = 2.5 * src @ R.T + [1, -2, 3]
    s, R2, t = umeyama(src, dst)
    assert s == pytest.approx(2.5) and np.allclose(R2, R) and np.allclose(t, [1, -2, 3])


def _handheld_poses(n: int, up_world: np.ndarray, pitch_deg: float, seed: int = 0,
                    roll_deg: float = 2.0) -> np.ndarray:
    """OpenCV c2w of a phone walked along an arc: x axes horizontal (+-`roll_deg` roll), all pitched down alike."""
    rng = np.random.default_rng(seed)
    to_world = _rot_between(np.array([0.0, 0, 1]), up_world)  # frame with z = up
    out = []
    for k in range(n):
        yaw = np.radians(k * 60.0 / n)
        fwd = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        pitch, roll = np.radians(-pitch_deg), np.radians(rng.normal(0, roll_deg))
        f = np.cos(pitch) * fwd + np.sin(pitch) * np.array([0, 0, 1.0])
        x = np.cross(f, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(f, x)
        c, s = np.cos(roll), np.sin(roll)
        x, y = c * x + s * y, -s * x + c * y
        m = np.eye(4)
        m[:3, :3] = to_world @ np.stack([x, y, f], axis=1)
        m[:3, 3] = to_world @ np.array([3 * np.cos(yaw), 3 * np.sin(yaw), 1.5])
        out.append(m)
    return np.asarray(out)


def test_vertical_up_is_unbiased_by_pitch_where_mean_up_is_not():
    up = np.array([0.2, -0.9, 0.3])
    up /= np.linalg.norm(up)
    c2w = _handheld_poses(30, up, pitch_deg=25)
    ang = lambda a: np.degrees(np.arccos(np.clip(np.dot(a, up), -1, 1)))  # noqa: E731
    assert ang(estimate_up(c2w, "vertical")) < 1.5
    assert ang(estimate_up(c2w, "up")) > 15  # nerfstudio's default is off by the pitch


def test_level_up_is_gravity_only_where_the_cameras_tell_it():
    up = np.array([0.2, -0.9, 0.3])
    up /= np.linalg.norm(up)
    ang = lambda a: np.degrees(np.arccos(np.clip(np.dot(a, up), -1, 1)))  # noqa: E731
    assert ang(level_up(_handheld_poses(30, up, pitch_deg=25))) < 1.5
    assert level_up(_handheld_poses(30, up, pitch_deg=25, roll_deg=30)) is None  # a camera rolled about freely
    still = np.repeat(_handheld_poses(1, up, pitch_deg=10), 20, axis=0)  # it never turned: only its pitched mean up
    assert ang(estimate_up(still, "vertical")) > 5 and level_up(still) is None


def test_orientation_transform_centres_scales_and_puts_up_on_z():
    up = np.array([0.0, -1.0, 0.0])
    c2w = _handheld_poses(20, up, pitch_deg=10)
    T = orientation_transform(c2w, "vertical", True)
    out = apply_similarity(T, c2w)
    assert np.allclose(out[:, :3, 3].mean(0), 0, atol=1e-9)
    assert np.abs(out[:, :3, 3]).max() == pytest.approx(1.0)
    assert np.allclose(np.einsum("nij,njk->nik", out[:, :3, :3].transpose(0, 2, 1), out[:, :3, :3]), np.eye(3))
    assert np.degrees(np.arccos(T[:3, :3] @ up / np.linalg.norm(T[:3, :3] @ up) @ [0, 0, 1])) < 1.5


# ------------------------------------------------------------------------------------------------ end to end
@pytest.mark.slow
def test_small_capture_end_to_end_with_masks(posed, capture):
    ds, fig = posed
    assert fig["registered"] == fig["total"] == 24
    err = errors(ds, gt(capture))
    assert err["rot_err_deg_median"] < 0.5, err  # 320x240, 24 frames over the whole arc: measured 0.27-0.32
    assert err["center_err_pct_median"] < 0.3, err  # measured 0.08-0.10
    meta = json.loads((ds / "transforms.json").read_text())
    assert meta["camera_model"] == "OPENCV" and meta["w"] == 320 and abs(meta["fl_x"] - 251.15) < 2.5
    assert meta["k1"] < -0.02  # the simulated barrel distortion is found
    assert np.asarray(meta["applied_transform"]).shape == (3, 4)
    assert (ds / "sparse_pc.ply").read_bytes().startswith(b"ply\nformat binary_little_endian")
    assert (ds / "colmap" / "sparse" / "0" / "images.bin").exists()
    rep = json.loads((ds / "reports" / "poses.json").read_text())
    assert rep["status"] == "ok" and rep["inputs"]["masks"]["source"] == "masks.npy"
    assert rep["figures"]["mean_reproj_error_px"] < 1.0 and rep["figures"]["mean_track_length"] > 3
    c = np.stack([np.asarray(f["transform_matrix"])[:3, 3] for f in meta["frames"]])
    assert np.abs(c).max() == pytest.approx(1.0) and np.allclose(c.mean(0), 0, atol=1e-6)
    assert validate(ds, check_masks=False).kinds() <= {"no-mapping", "no-labels"}


def test_track_refinement_pulls_perturbed_keypoints_back(posed):
    """Every track's observations are aligned to its reference view: moved off by up to 0.6 px, they come back."""
    import pycolmap

    from interreal.keypoints import _observations, refine_tracks

    ds, _ = posed
    rep = json.loads((ds / "reports" / "poses.json").read_text())
    assert rep["figures"]["track_refinement"] is False  # auto: 24 frames at 320x240 are not where it helps
    rec = pycolmap.Reconstruction(str(ds / "colmap" / "sparse" / "0"))
    refine_tracks(rec, ds / "images")  # the aligned positions: what a second pass must come back to
    obs = _observations(rec)
    before = np.array([rec.images[int(i)].points2D[int(k)].xy for i, k in obs[:, 2:]])
    noise = np.random.default_rng(0).uniform(-0.6, 0.6, before.shape)
    for (i, k), q in zip(obs[:, 2:], before + noise):
        rec.images[int(i)].points2D[int(k)].xy = q
    info = refine_tracks(rec, ds / "images")
    after = np.array([rec.images[int(i)].points2D[int(k)].xy for i, k in obs[:, 2:]])
    back = np.linalg.norm(after - before, axis=1)
    assert info["observations"] == len(obs) and info["refined_frac"] > 0.6
    assert np.median(back) < 0.1 < np.median(np.linalg.norm(noise, axis=1)), np.median(back)


def test_track_extension_finds_removed_observations(posed):
    """Observations taken out of their tracks come back where they were (Lucas-Kanade from the projection onto the
    track's reference patch), and nothing is added on the object masks or to views a point does not project into."""
    import pycolmap

    from interreal.keypoints import _sorted_tracks, extend_tracks, refine_tracks

    ds, _ = posed
    rec = pycolmap.Reconstruction(str(ds / "colmap" / "sparse" / "0"))
    refine_tracks(rec, ds / "images")  # observations that agree: what the extension's alignment reproduces
    rng = np.random.default_rng(0)
    dropped = []  # (point3D id, image id, xy): one non-reference view of every other track of >= 5 views
    for pid, els in _sorted_tracks(rec)[1].items():
        if len(els) >= 5 and rng.random() < 0.5:
            _, iid, idx = els[int(rng.choice([0, len(els) - 1]))]  # an end: the track's range shrinks
            dropped.append((pid, iid, np.array(rec.images[iid].points2D[idx].xy)))
            rec.delete_observation(iid, idx)
    assert len(dropped) > 100
    before = rec.compute_num_observations()
    sizes = {iid: len(im.points2D) for iid, im in rec.images.items()}
    masks = ds / "colmap" / "masks"  # the SfM masks the poses stage derived from DS/masks (255 = usable)
    info = extend_tracks(rec, ds / "images", masks, window=24)
    assert info["observations_before"] == before and info["added"] == rec.compute_num_observations() - before
    assert info["track_length_after"] > info["track_length_before"]
    found = []
    for pid, iid, xy in dropped:
        back = [rec.images[e.image_id].points2D[e.point2D_idx].xy for e in rec.points3D[pid].track.elements
                if e.image_id == iid]
        if back:
            found.append(np.linalg.norm(np.asarray(back[0]) - xy))
    assert len(found) > 0.6 * len(dropped), (len(found), len(dropped))  # 0.70: the rest sit at an image edge or
    # changed too much from the reference view (tracks end where they stop matching)
    # the 90th percentile was 0.5006 px on one clean clone and below 0.5 in other runs: sub-pixel is the bar
    assert np.median(found) < 0.1 and np.percentile(found, 90) < 1.0, (np.median(found), np.percentile(found, 90))
    # an added observation is a new 2-D point of its view, on background pixels, near its point's projection
    n_new = 0
    for pid, p in rec.points3D.items():
        for e in p.track.elements:
            if e.point2D_idx < sizes[e.image_id]:
                continue
            n_new += 1
            im = rec.images[e.image_id]
            xy = np.asarray(im.points2D[e.point2D_idx].xy)
            proj = rec.cameras[im.camera_id].img_from_cam((im.cam_from_world().matrix() @ np.r_[p.xyz, 1])[None])
            assert np.linalg.norm(proj[0] - xy) < 1.6, (pid, e.image_id)
            mask = cv2.imread(str(masks / f"{im.name}.png"), cv2.IMREAD_GRAYSCALE)
            assert mask[int(xy[1]), int(xy[0])] > 0, (pid, im.name)
    assert n_new == info["added"]
    batched = pycolmap.Reconstruction(str(ds / "colmap" / "sparse" / "0"))  # the same, aligned ~400 at a time
    refine_tracks(batched, ds / "images")
    for pid, iid, _ in dropped:
        batched.delete_observation(iid, next(e.point2D_idx for e in batched.points3D[pid].track.elements
                                             if e.image_id == iid))
    again = extend_tracks(batched, ds / "images", masks, window=24, batch=400)
    assert again["candidates"] == info["candidates"]  # the alignment reads its tiles' neighbours at the margin:
    assert abs(again["added"] - info["added"]) <= 0.01 * info["added"], (again, info)  # 2648 vs 2652 measured
    narrow = extend_tracks(pycolmap.Reconstruction(str(ds / "colmap" / "sparse" / "0")), ds / "images", window=0)
    assert narrow["candidates"] < info["candidates"]  # a narrower window looks in fewer views
    assert extend_tracks(pycolmap.Reconstruction(), ds / "images")["added"] == 0  # no model, nothing to do


def test_robust_final_ba_resists_bad_observations(posed, capture):
    """The final BA's soft-L1 loss (the default) keeps poses where a few observations are 3-6 px off; the squared
    loss lets them pull every camera."""
    import pycolmap

    from interreal.conventions import frame_index, opencv_to_opengl
    from interreal.sfm import SfMConfig, rec_poses, refine_intrinsics

    ds, _ = posed
    truth = gt(capture)
    rec = pycolmap.Reconstruction(str(ds / "colmap" / "sparse" / "0"))
    rng = np.random.default_rng(0)
    for image in rec.images.values():
        for p in image.points2D:
            if p.has_point3D() and rng.random() < 0.08:
                p.xy = p.xy + rng.uniform(3.0, 6.0) * np.array([1.0, 0.0]) * rng.choice([-1, 1])

    def rot_err(loss: str) -> float:
        r = pycolmap.Reconstruction(rec)
        refine_intrinsics(pycolmap, r, SfMConfig(ba_loss=loss, num_threads=ONE_THREAD), "fixed")
        names, c2w, _ = rec_poses(r)
        ids = [frame_index(n) for n in names]
        return compare_poses(opencv_to_opengl(c2w), np.stack([truth[i] for i in ids]))["rot_err_deg_median"]

    robust, squared = rot_err("soft_l1"), rot_err("trivial")
    assert SfMConfig().ba_loss == "soft_l1"
    with pytest.raises(InputError, match="ba_loss must be one of"):  # checked before anything is written
        estimate_poses(ds, ba_loss="l2")
    assert robust < 0.8 * squared, (robust, squared)  # measured 0.35 vs 0.50 deg on one thread


@pytest.mark.slow
def test_rerun_reuses_the_finished_model(posed):
    ds, fig = posed
    before = (ds / "transforms.json").read_text()
    fig2 = estimate_poses(ds, num_threads=ONE_THREAD)
    rep = json.loads((ds / "reports" / "poses.json").read_text())
    assert rep["steps"]["features"]["reused"] and rep["steps"]["reuse"]["reused"]
    assert fig2["registered"] == fig["registered"]
    assert json.loads(before)["frames"] == json.loads((ds / "transforms.json").read_text())["frames"]


@pytest.mark.slow
def test_import_transforms_and_colmap_model(posed, tmp_path):
    ds, _ = posed
    for kind, src in (("json", ds / "transforms.json"), ("colmap", ds / "colmap" / "sparse")):
        other = tmp_path / kind
        shutil.copytree(ds / "images", other / "images")
        fig = estimate_poses(other, poses=src)
        assert fig["registered"] == 24 and fig["imported"] == str(src)
        a = load_dataset(ds)
        b = load_dataset(other)
        err = compare_poses(np.stack([f.c2w for f in b.frames]), np.stack([f.c2w for f in a.frames]))
        assert err["rot_err_deg_max"] < 1e-3 and err["center_err_pct_max"] < 1e-3
        assert b.intrinsics.fl_x == pytest.approx(a.intrinsics.fl_x)


# ------------------------------------------------------------------------------------------------ failures
def test_unrelated_images_fail_cleanly_and_validate_refuses(tmp_path):
    ds = tmp_path / "ds"
    rng = np.random.default_rng(0)
    for i in range(6):  # independent noise textures: features, but no two images see the same scene
        img = cv2.resize(rng.integers(0, 256, (30, 40, 3), dtype=np.uint8), (160, 120), interpolation=cv2.INTER_CUBIC)
        atomic.write_image(ds / "images" / f"frame_{i:05d}.png", img)
    with pytest.raises(StageError, match="SfM"):
        estimate_poses(ds, matcher="exhaustive")
    rep = json.loads((ds / "reports" / "poses.json").read_text())
    assert rep["status"] == "failed" and len(rep["ladder"]) >= 2  # the retry ladder ran
    assert not (ds / "transforms.json").exists()
    assert "stage-incomplete" in validate(ds).kinds()
    assert cli.main(["poses", str(ds), "--matcher", "exhaustive"]) == 3


def test_mixed_sizes_and_too_few_images_are_input_errors(tmp_path):
    ds = tmp_path / "ds"
    atomic.write_image(ds / "images" / "frame_00000.png", np.zeros((20, 30, 3), np.uint8))
    with pytest.raises(InputError, match="at least 3"):
        estimate_poses(ds)
    atomic.write_image(ds / "images" / "frame_00001.png", np.zeros((20, 30, 3), np.uint8))
    atomic.write_image(ds / "images" / "frame_00002.png", np.zeros((24, 30, 3), np.uint8))
    with pytest.raises(InputError, match="share one size"):
        estimate_poses(ds)


def test_poses_help_has_examples(capsys):
    with pytest.raises(SystemExit):
        cli.main(["poses", "--help"])
    assert "examples:" in capsys.readouterr().out


@pytest.mark.slow
def test_strided_mapping_registers_every_frame(tmp_path):
    """Long captures map every 3rd frame first, then register the rest into that model: all frames get poses,
    as accurate as mapping them all at once, and the report says which mode ran."""
    from interreal.sfm import key_positions, strided_pairs

    assert key_positions(10, 3) == [0, 3, 6, 9] and key_positions(11, 3) == [0, 3, 6, 9, 10]
    pairs = set(strided_pairs(11, 3, 2, False))
    assert {(0, 3), (3, 6), (0, 6), (0, 1), (1, 3), (9, 10)} <= pairs and (1, 2) in pairs and (2, 6) not in pairs
    cap = render_capture(tmp_path / "cap", frames=45)
    ds = tmp_path / "ds"
    extract_frames(cap / "video.mp4", ds, target=45)
    truth_masks_npy(cap, ds)
    fig = estimate_poses(ds, key_stride=3)
    assert fig["registered"] == fig["total"] == 45
    err = errors(ds, gt(cap))
    assert err["rot_err_deg_median"] < 0.5 and err["center_err_pct_median"] < 0.3, err
    rep = json.loads((ds / "reports" / "poses.json").read_text())
    assert rep["ladder"][0]["stride"] == 3


@pytest.mark.slow
def test_upsampled_octave_on_every_third_frame(tmp_path):
    """Long captures at native size give SIFT's upsampled octave to every 3rd frame only (forced here on a short
    one): those frames carry more (finer) features, and every frame still registers accurately."""
    import pycolmap

    from interreal.sfm import SfMConfig, fine_frames, ladder

    assert fine_frames(SfMConfig(), 300, -1, 640) == list(range(0, 300, 3)) + [299]
    assert fine_frames(SfMConfig(), 300, 0, 640) == list(range(300))  # frames downscaled for SIFT: nothing to save
    assert fine_frames(SfMConfig(), 60, -1, 640) == list(range(60))  # short captures: every frame
    assert fine_frames(SfMConfig(), 300, -1, 320) == list(range(300))  # small frames: octave 0 finds too little
    # mixed octaves map every frame at once; uniform ones map every 3rd frame first (the strided test below)
    assert ladder(SfMConfig(), 300, mixed_octaves=True)[0].stride == 1 and ladder(SfMConfig(), 300)[0].stride == 3
    assert ladder(SfMConfig(), 300, mixed_octaves=True, extended=True)[0].stride == 3  # extension restores tracks
    cap = render_capture(tmp_path / "cap", frames=30, size=(640, 480))
    ds = tmp_path / "ds"
    extract_frames(cap / "video.mp4", ds, target=30)
    truth_masks_npy(cap, ds)
    fig = estimate_poses(ds, fine_octave_stride=3, matcher="sequential", refine_tracks="on", extend_tracks="on")
    assert fig["registered"] == fig["total"] == 30 and fig["track_refinement"] is True
    assert fig["track_extension"] is True
    rep = json.loads((ds / "reports" / "poses.json").read_text())
    assert rep["steps"]["refine_tracks"]["refined_frac"] > 0.6  # measured 0.84 on 300 frames at 640x480
    ext = rep["steps"]["extend_tracks"]
    assert ext["track_length_after"] > 1.3 * ext["track_length_before"], ext
    assert rep["steps"]["final_ba"]["rms_px"] < 1.0
    err = errors(ds, gt(cap))
    assert err["rot_err_deg_median"] < 0.35 and err["center_err_pct_median"] < 0.2, err  # measured 0.19, 0.067
    with pycolmap.Database.open(str(ds / "colmap" / "database.db")) as d:
        counts = {im.name: d.num_keypoints_for_image(im.image_id) for im in d.read_all_images()}
    names = sorted(counts)
    fine = [counts[n] for i, n in enumerate(names) if i % 3 == 0 or i == len(names) - 1]
    coarse = [counts[n] for i, n in enumerate(names) if not (i % 3 == 0 or i == len(names) - 1)]
    assert np.mean(fine) > 1.3 * np.mean(coarse), (np.mean(fine), np.mean(coarse))


def test_rotation_error_in_both_gauges():
    """compare_poses: the centre-fitted gauge carries centre noise into every rotation (a short path turns with its
    noise); the rotation-fitted gauge recovers the true offset, so exact rotations score zero in it."""
    from scipy.spatial.transform import Rotation

    from interreal.scoring import compare_poses, rotation_gauge

    rng = np.random.default_rng(0)
    n = 40
    ref = np.tile(np.eye(4), (n, 1, 1))
    ref[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.3, (n, 3))).as_matrix()
    ref[:, :3, 3] = np.stack([np.linspace(-1, 1, n), 0.1 * np.sin(np.linspace(0, 3, n)), np.zeros(n)], 1)
    G = Rotation.from_rotvec([0.2, -0.1, 0.3]).as_matrix()
    est = ref.copy()
    est[:, :3, :3] = np.einsum("ij,njk->nik", G.T, ref[:, :3, :3])  # the same rotations in another frame
    est[:, :3, 3] = 2.0 * ref[:, :3, 3] @ G + rng.normal(0, 0.002, (n, 3))  # scaled, rotated, noisy centres
    assert np.allclose(rotation_gauge(est[:, :3, :3], ref[:, :3, :3]), G, atol=1e-6)
    err = compare_poses(est, ref)
    assert err["rot_err_deg_median_rotation_gauge"] < 1e-4
    assert err["rot_err_deg_median"] > 0.01  # the centre fit tilts by what the noise turns the path
    assert err["gauge_gap_deg"] == pytest.approx(err["rot_err_deg_median"], rel=1e-3)  # exact rotations: all tilt
    assert err["scale"] == pytest.approx(0.5, rel=0.01)


def test_pose_flags_come_from_the_config_fields():
    """`interreal poses` / `process` flags are generated from `SfMConfig`: the historic names, each field's default
    when not given, the typed value when given."""
    import argparse
    from dataclasses import asdict

    from interreal.sfm import SfMConfig, add_sfm_options, sfm_options

    p = argparse.ArgumentParser()
    add_sfm_options(p)
    flags = {s for a in p._actions for s in a.option_strings} - {"-h", "--help"}
    assert flags == {"--sfm-long-side", "--matcher", "--mapper", "--camera-model", "--max-features", "--key-stride",
                     "--fine-octave-stride", "--principal-point", "--ba-loss", "--orientation", "--refine-tracks",
                     "--extend-tracks", "--no-masks", "--undistort", "--verbose", "--intrinsics",
                     "--intrinsics-refine", "--allow-low-parallax"}
    defaults = asdict(SfMConfig())
    opts = sfm_options(p.parse_args([]))
    assert opts == {k: defaults[k] for k in opts} and len(opts) == len(flags)
    opts = sfm_options(p.parse_args(["--no-masks", "--sfm-long-side", "800", "--matcher", "exhaustive", "--verbose"]))
    assert opts["use_masks"] is False and opts["sfm_long_side"] == 800 and opts["matcher"] == "exhaustive"
    assert opts["verbose"] is True and opts["undistort"] is False
    with pytest.raises(SystemExit):
        p.parse_args(["--ba-loss", "l2"])


def test_cropped_extraction_keeps_the_masked_features_in_frame_coordinates(tmp_path):
    """A part's SIFT from its mask's box alone: the same features the whole frame's extraction keeps under the mask
    (COLMAP drops the others after extracting), at the same frame pixels, in a database the matcher reads."""
    import pycolmap

    from interreal.sfm import colmap

    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (240, 320)).astype(np.uint8), (0, 0), 1.5)
    images, masks = tmp_path / "images", tmp_path / "masks"
    images.mkdir(), masks.mkdir()
    names = ["a.png", "b.png"]
    for k, name in enumerate(names):
        shifted = np.roll(texture, 6 * k, axis=1)  # the second view: the scene 6 px to the right
        cv2.imwrite(str(images / name), cv2.merge([shifted] * 3))
        mask = np.zeros((240, 320), np.uint8)
        mask[90:170, 120 + 6 * k:220 + 6 * k] = 255
        cv2.imwrite(str(masks / f"{name}.png"), mask)
    ex = colmap.Extraction("PINHOLE", 4096, 4000, camera_params="300,300,160,120", num_threads=1)
    whole, cropped = tmp_path / "whole.db", tmp_path / "cropped.db"
    colmap.extract_features(pycolmap, whole, images, [(-1, names)], ex, masks, chunk=None)
    colmap.extract_cropped(pycolmap, cropped, images, names, ex, masks, first_octave=-1)
    with pycolmap.Database.open(str(whole)) as a, pycolmap.Database.open(str(cropped)) as b:
        assert b.num_cameras() == 1 and b.num_images() == 2
        for name in names:
            kw = a.read_keypoints(a.read_image_with_name(name).image_id)[:, :2]
            kc = b.read_keypoints(b.read_image_with_name(name).image_id)[:, :2]
            assert len(kc) > 50 and abs(len(kc) - len(kw)) < 0.1 * len(kw), (len(kc), len(kw))
            x0 = 120 + 6 * names.index(name)
            assert (kc[:, 0] >= x0).all() and (kc[:, 0] < x0 + 100).all() and (kc[:, 1] >= 90).all()
            near = np.linalg.norm(kw[:, None] - kc[None], axis=2).min(1)
            assert np.mean(near < 0.05) > 0.9, np.mean(near < 0.05)  # the same keypoints, not shifted by the crop
    colmap.match_pairs(pycolmap, cropped, names, [(0, 1)], tmp_path / "pairs.txt", seed=0, num_threads=1, chunk=None)
    with pycolmap.Database.open(str(cropped)) as b:
        ids = [b.read_image_with_name(n).image_id for n in names]
        assert b.read_two_view_geometry(*ids).inlier_matches.shape[0] > 50
