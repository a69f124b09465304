"""A camera that barely moved (turned in place, stood still) is refused in seconds, before any mapping, with that
cause and what to do; a normal capture passes the check; stray files in an image folder are left out with a
warning that names them."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from interreal import atomic, cli
from interreal.errors import LowParallaxError
from interreal.frames import extract_frames
from interreal.paths import require_shared
from interreal.sfm import estimate_poses
from interreal.sfm import stage as sfm_stage
from interreal.sfm.parallax import MIN_ANGLE_DEG, fit_focal, pinhole, rotation_deviation

from test_bad_inputs_interreal import photos
from test_sfm import render_capture

N = 16  # frames of each simulated capture (320x240)


def _rot(axis: int, a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    R = np.eye(3)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> dict[str, Path]:
    """Three datasets of the same simulated room: the phone's arc ("normal"), the phone turned in place from one
    spot (a 40 deg pan with some tilt, "rotation"), and the phone held still (sensor noise only, "static")."""
    from interreal.synth import SynthConfig
    from interreal.synth.scene import Scene

    root = tmp_path_factory.mktemp("parallax")
    cap = render_capture(root / "cap", frames=N)
    extract_frames(cap / "video.mp4", root / "normal", target=N)
    scene = Scene(SynthConfig(frames=N, width=320, height=240, seed=0))
    mid = N // 2
    pose, states = scene.camera_path()[mid], scene.states_at(mid)
    rng = np.random.default_rng(0)
    for k in range(N):
        turned = pose.copy()
        turned[:3, :3] = pose[:3, :3] @ _rot(1, np.radians(-20 + 40 * k / (N - 1))) @ _rot(0, np.radians(3 * np.sin(k)))
        atomic.write_image(root / "rotation" / "images" / f"frame_{k:05d}.png", scene.render(turned, states).rgb)
        still = scene.render(pose, states).rgb + rng.normal(0, 2, (240, 320, 3))
        atomic.write_image(root / "static" / "images" / f"frame_{k:05d}.png", np.clip(still, 0, 255).astype(np.uint8))
    return {"normal": root / "normal", "rotation": root / "rotation", "static": root / "static"}


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


class _Mapped(Exception):
    """Raised where the retry ladder would start: the check let the capture through."""


@pytest.fixture
def stop_before_mapping(monkeypatch):
    def run_ladder(*a, **k):
        raise _Mapped()

    monkeypatch.setattr(sfm_stage, "run_ladder", run_ladder)


# ------------------------------------------------------------------------------------------------ the geometry
def test_a_rotation_homography_reads_zero_and_a_plane_seen_from_a_baseline_reads_its_angle():
    w, h = 640, 480
    K = pinhole(520.0, (w, h))
    turns = [_rot(1, np.radians(25)) @ _rot(0, np.radians(5)), _rot(1, np.radians(-10)), _rot(0, np.radians(8))]
    hs = [K @ R @ np.linalg.inv(K) for R in turns]
    assert max(rotation_deviation(H, K) for H in hs) < 1e-9
    f = fit_focal(hs, (w, h))  # f unknown: the one focal length under which the pairs are rotations
    assert f == pytest.approx(520.0, rel=1e-3)
    assert max(rotation_deviation(H, pinhole(f, (w, h))) for H in hs) < 1e-3
    # a wall 3 m away seen from spots 0.3 m apart: R + t n^T / d deviates by |t| / d = 0.1 rad, whatever the turn
    n, d = np.array([0, 0, 1.0]), 3.0
    steps = [np.array([0.3, 0, 0]), np.array([0, 0.3, 0]), np.array([0, 0, 0.3])]
    hp = [K @ (R + np.outer(t, n) / d) @ np.linalg.inv(K) for R, t in zip(turns, steps)]
    assert [rotation_deviation(H, K) for H in hp] == pytest.approx([0.1] * 3, rel=0.02)
    # f unknown: a sideways step plus a pan can pass for a turn under some focal length (the first pair reads 0.039
    # rad at f = 560 px), but no one focal length makes steps in three directions rotations: the capture's figure,
    # its largest pair, keeps the baseline (measured 0.039, 0.096, 0.102 rad)
    fp = pinhole(fit_focal(hp, (w, h)), (w, h))
    assert max(rotation_deviation(H, fp) for H in hp) > 0.09


# ------------------------------------------------------------------------------------------------ the stage
@pytest.mark.parametrize("kind", ["rotation", "static"])
def test_a_camera_that_barely_moved_is_refused_in_seconds(captures, kind, tmp_path):
    ds = _copy(captures[kind], tmp_path / kind)
    with pytest.raises(LowParallaxError) as err:
        estimate_poses(ds)
    msg = str(err.value)
    assert "barely moved" in msg and "turned in place or stood still" in msg
    assert "walking around the object" in msg and "--allow-low-parallax" in msg and "deg" in msg
    rep = json.loads((ds / "reports" / "poses.json").read_text())
    assert rep["status"] == "failed" and "LowParallaxError" in rep["error"]
    assert not any(s.startswith(("map:", "match:")) for s in rep["steps"])  # refused before any matching / mapping
    px = rep["steps"]["parallax"]
    # measured: turned 0.27 deg at most over 17 pairs, still 0.045 deg; the check itself 0.2-0.5 s
    assert px["pairs_judged"] >= 8 and px["parallax_deg_max"] < MIN_ANGLE_DEG / 2, px
    assert px["wall_s"] > 0  # timed and reported (~0.2-0.5 s after ~2 s of features: recipes/bench_poses.py)


def test_a_normal_capture_passes_the_check(captures, tmp_path, stop_before_mapping):
    ds = _copy(captures["normal"], tmp_path / "normal")
    with pytest.raises(_Mapped):
        estimate_poses(ds)
    px = json.loads((ds / "reports" / "poses.json").read_text())["steps"]["parallax"]
    # measured: up to 52 deg, median 10 deg over 12 pairs of the arc's 16 frames
    assert px["parallax_deg_max"] > 5 * MIN_ANGLE_DEG and px["parallax_deg_median"] > MIN_ANGLE_DEG, px
    assert px["focal_source"] == "prior" and px["wall_s"] > 0


def test_the_shared_phone_capture_passes_the_check(tmp_path, stop_before_mapping):
    """fox: a real handheld orbit with reference poses (every 2nd photo, SIFT at 600 px to keep it quick)."""
    src = require_shared("fox", "images")
    for p in sorted(src.glob("*.jpg"))[::2]:
        (tmp_path / "fox" / "images").mkdir(parents=True, exist_ok=True)
        shutil.copy(p, tmp_path / "fox" / "images" / p.name)
    with pytest.raises(_Mapped):
        estimate_poses(tmp_path / "fox", sfm_long_side=600, use_masks=False)
    px = json.loads((tmp_path / "fox" / "reports" / "poses.json").read_text())["steps"]["parallax"]
    # measured: 38 deg at most, 21 deg median here (43 and 23 deg on all 50 photos at 1000 px)
    assert px["parallax_deg_max"] > 5 * MIN_ANGLE_DEG and px["pairs_judged"] >= 8, px


def test_allow_low_parallax_maps_anyway_with_a_warning(captures, tmp_path, stop_before_mapping):
    ds = _copy(captures["rotation"], tmp_path / "rotation")
    with pytest.raises(_Mapped):
        estimate_poses(ds, allow_low_parallax=True)
    rep = json.loads((ds / "reports" / "poses.json").read_text())
    assert any(w.get("cause") == "low-parallax" and "barely moved" in w["message"] for w in rep["warnings"])


def test_the_command_says_why_and_what_to_do(captures, tmp_path, capsys):
    ds = _copy(captures["static"], tmp_path / "static")
    assert cli.main(["poses", str(ds)]) == 2  # an input error, no traceback
    err = capsys.readouterr().err
    assert "barely moved" in err and "Traceback" not in err


# ------------------------------------------------------------------------------------------------ image folders
def test_stray_and_hidden_files_in_an_image_folder_are_left_out_with_a_warning(tmp_path):
    folder = photos(tmp_path / "benchmark", 4)  # a classic benchmark layout: images, K.txt, a sidecar, OS litter
    (folder / "K.txt").write_text("500 0 320\n0 500 240\n0 0 1\n")
    (folder / "cameras.json").write_text("{}")
    (folder / ".DS_Store").write_bytes(b"\x00\x00\x00\x01Bud1")
    paths = extract_frames(folder, tmp_path / "ds")
    assert len(paths) == 4
    rep = json.loads((tmp_path / "ds" / "reports" / "frames.json").read_text())
    assert rep["status"] == "ok"
    warned = [w for w in rep["warnings"] if w.get("cause") == "not-an-image"]
    assert len(warned) == 1 and set(warned[0]["files"]) == {"K.txt", "cameras.json", ".DS_Store"}
    assert "K.txt" in warned[0]["message"]
