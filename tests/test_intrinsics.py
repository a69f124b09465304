"""`interreal poses DS --intrinsics FILE`: K as text or JSON, checked, scaled to the dataset's images, held fixed by
SfM; poses at least as good as with estimated intrinsics on a simulated capture."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from interreal import atomic, cli
from interreal.errors import InputError
from interreal.frames import extract_frames
from interreal.sfm import estimate_poses
from interreal.sfm.intrinsics import read_intrinsics, scaled_to

from test_sfm import errors, gt, render_capture, truth_masks_npy

K_TXT = "500.0 0 320.5\n0 502.0 240.25\n0 0 1\n"


def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


# ------------------------------------------------------------------------------------------------ reading
@pytest.mark.parametrize("name, text", [
    ("K.txt", K_TXT),
    ("K_comment.txt", "# camera matrix of the benchmark\n" + K_TXT),
    ("K_commas.txt", "[[500, 0, 320.5], [0, 502, 240.25], [0, 0, 1]]"),
    ("k.json", json.dumps({"fx": 500, "fy": 502, "cx": 320.5, "cy": 240.25})),
    ("transforms.json", json.dumps({"fl_x": 500, "fl_y": 502, "cx": 320.5, "cy": 240.25, "frames": []})),
    ("kmat.json", json.dumps({"K": [[500, 0, 320.5], [0, 502, 240.25], [0, 0, 1]]})),
    ("list.json", json.dumps([[500, 0, 320.5], [0, 502, 240.25], [0, 0, 1]])),
])
def test_k_is_read_from_text_and_json(tmp_path, name, text):
    k = read_intrinsics(_write(tmp_path, name, text))
    assert (k.fx, k.fy, k.cx, k.cy, k.dist, k.size) == (500, 502, 320.5, 240.25, (0, 0, 0, 0), None)


def test_distortion_and_size_come_from_json(tmp_path):
    k = read_intrinsics(_write(tmp_path, "k.json", json.dumps(
        {"fx": 500, "cx": 320, "cy": 240, "k1": -0.05, "k2": 0.01, "p1": 1e-4, "w": 640, "h": 480})))
    assert k.fy == 500 and k.dist == (-0.05, 0.01, 1e-4, 0.0) and k.size == (640, 480)
    assert k.colmap_params().split(",")[4] == "-0.05"


@pytest.mark.parametrize("text, says", [
    ("500 0 320 0 500 240 0 0", "found 8 numbers, a 3x3 K has 9"),
    ("fx=500 cx=320", "is not a number"),
    ("500 0 320 0 500 240 1 0 1", "not a camera matrix"),
    ("500 3 320 0 500 240 0 0 1", "skew"),
    ("-500 0 320 0 500 240 0 0 1", "focal lengths must be positive"),
    (json.dumps({"fx": 500, "cx": 320}), "JSON without cy"),
    (json.dumps({"fx": 500, "cx": 320, "cy": 240, "k3": 0.1}), "k3"),
    (json.dumps({"fx": "a lot", "cx": 320, "cy": 240}), "must be numbers"),
    (json.dumps({"fx": 500, "cx": 320, "cy": 240, "w": 640}), "\"w\" and \"h\""),
])
def test_a_malformed_file_is_named_with_the_expected_format(tmp_path, text, says):
    path = _write(tmp_path, "K.txt", text)
    with pytest.raises(InputError, match=says) as err:
        read_intrinsics(path)
    assert str(path) in str(err.value)


# ------------------------------------------------------------------------------------------------ scaling
def _dataset(tmp_path: Path, size: tuple[int, int], source: tuple[int, int] | None) -> Path:
    ds = tmp_path / "ds"
    if source is not None:  # what `interreal frames` records of the capture it resized
        atomic.write_json(ds / "reports" / "frames.json",
                          {"inputs": {"source_info": {"width": source[0], "height": source[1]}}})
    else:
        ds.mkdir(parents=True)
    return ds


def test_k_is_scaled_from_the_capture_size_frames_recorded(tmp_path):
    ds = _dataset(tmp_path, (320, 240), (640, 480))
    k, note = scaled_to(read_intrinsics(_write(tmp_path, "K.txt", K_TXT)), ds, (320, 240))
    assert (k.fx, k.fy, k.cx, k.cy, k.size) == (250.0, 251.0, 160.25, 120.125, (320, 240))
    assert "640x480" in note and "frames.json" in note


def test_the_json_size_wins_and_no_record_means_the_dataset_size(tmp_path):
    ds = _dataset(tmp_path, (320, 240), (1280, 960))
    given = json.dumps({"fx": 500, "cx": 320, "cy": 240, "w": 640, "h": 480})
    k, _ = scaled_to(read_intrinsics(_write(tmp_path, "k.json", given)), ds, (320, 240))
    assert (k.fx, k.cx) == (250.0, 160.0)
    k, note = scaled_to(read_intrinsics(_write(tmp_path, "K.txt", K_TXT)), _dataset(tmp_path / "b", (640, 480), None),
                        (640, 480))
    assert (k.fx, k.cx) == (500.0, 320.5) and "dataset's images" in note


def test_k_of_another_shape_or_size_is_refused(tmp_path):
    ds = _dataset(tmp_path, (320, 180), (640, 480))
    with pytest.raises(InputError, match="another aspect ratio"):
        scaled_to(read_intrinsics(_write(tmp_path, "K.txt", K_TXT)), ds, (320, 180))
    ds = _dataset(tmp_path / "b", (320, 240), None)  # no record: K of 640x480 would put (cx, cy) at the corner
    with pytest.raises(InputError, match="far from the centre"):
        scaled_to(read_intrinsics(_write(tmp_path, "K.txt", K_TXT)), ds, (320, 240))


# ------------------------------------------------------------------------------------------------ SfM with a known K
@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    return render_capture(tmp_path_factory.mktemp("cap"))  # 24 frames, 320x240


def _posed_dataset(capture: Path, ds: Path, long_side: int = 320) -> Path:
    """The capture's frames (at 240x180 with long_side 240: a K of the 320x240 capture must be scaled), truth
    masks."""
    extract_frames(capture / "video.mp4", ds, target=24, long_side=long_side)
    truth_masks_npy(capture, ds)
    return ds


def _truth_k(capture: Path) -> dict:
    return json.loads((capture / "gt" / "cameras.json").read_text())["intrinsics"]


def test_known_intrinsics_give_poses_as_good_as_estimated_ones(capture, tmp_path):
    truth = _truth_k(capture)
    auto = _posed_dataset(capture, tmp_path / "auto")
    estimate_poses(auto)
    given = _posed_dataset(capture, tmp_path / "given")
    k_file = _write(tmp_path, "k.json", json.dumps({k: truth[k] for k in ("fl_x", "fl_y", "cx", "cy", "k1", "k2",
                                                                          "w", "h")}))
    fig = estimate_poses(given, intrinsics=str(k_file))
    assert fig["registered"] == fig["total"] == 24
    e_auto, e_given = errors(auto, gt(capture)), errors(given, gt(capture))
    # measured (seeds 0, 1): rotation 0.29, 0.23 deg given vs 0.28, 0.28 estimated; centres 0.14, 0.11 % vs
    # 0.15, 0.14 %; one CI run 0.36 against 0.29 (the mapper's threads do not repeat a run exactly): as good within
    # that run-to-run spread (a ratio of two such medians is not a bound a busy machine keeps)
    assert e_given["rot_err_deg_median"] <= e_auto["rot_err_deg_median"] + 0.1, (e_given, e_auto)
    assert e_given["center_err_pct_median"] <= e_auto["center_err_pct_median"] + 0.05, (e_given, e_auto)
    meta = json.loads((given / "transforms.json").read_text())
    assert meta["fl_x"] == pytest.approx(truth["fl_x"], abs=1e-9) and meta["cy"] == pytest.approx(truth["cy"])
    assert (meta["k1"], meta["k2"]) == pytest.approx((truth["k1"], truth["k2"]), abs=1e-12)  # held, not refined
    rep = json.loads((given / "reports" / "poses.json").read_text())
    assert rep["figures"]["intrinsics_given"]["held"] and rep["figures"]["principal_point"] == "given"


def test_the_command_takes_k_txt(capture, tmp_path, capsys):
    ds = _posed_dataset(capture, tmp_path / "ds", long_side=240)
    t = _truth_k(capture)
    k_txt = _write(tmp_path, "K.txt", f"{t['fl_x']} 0 {t['cx']}\n0 {t['fl_y']} {t['cy']}\n0 0 1\n")
    assert cli.main(["poses", str(ds), "--intrinsics", str(k_txt)]) == 0
    out = capsys.readouterr().out
    assert f"intrinsics from {k_txt}" in out and "320x240" in out and "held fixed" in out
    meta = json.loads((ds / "transforms.json").read_text())
    assert np.allclose([meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"]],
                       [t["fl_x"] * 0.75, t["fl_y"] * 0.75, 120.0, 90.0], atol=1e-9)
    assert cli.main(["poses", str(ds), "--intrinsics", str(tmp_path / "missing.txt")]) == 2
    assert "missing.txt" in capsys.readouterr().err


def test_refined_intrinsics_start_from_the_file_and_poses_and_intrinsics_exclude_each_other(capture, tmp_path):
    truth = _truth_k(capture)
    ds = _posed_dataset(capture, tmp_path / "ds")
    k_file = _write(tmp_path, "k.json", json.dumps({"fx": truth["fl_x"] * 1.02, "cx": truth["cx"], "cy": truth["cy"]}))
    estimate_poses(ds, intrinsics=str(k_file), intrinsics_refine=True)
    meta = json.loads((ds / "transforms.json").read_text())
    # a start 2 % off is pulled back by bundle adjustment (measured: 252.2 px for the true 251.1 px)
    assert meta["fl_x"] != pytest.approx(truth["fl_x"] * 1.02, abs=1e-6)
    assert meta["fl_x"] == pytest.approx(truth["fl_x"], rel=0.015)
    rep = json.loads((ds / "reports" / "poses.json").read_text())
    assert rep["figures"]["intrinsics_given"]["held"] is False
    with pytest.raises(InputError, match="not both"):
        estimate_poses(ds, poses=str(ds / "transforms.json"), intrinsics=str(k_file))
