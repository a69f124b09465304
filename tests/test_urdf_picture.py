"""`recipes/urdf_picture.py`: the toy door (hinge) and drawer (slide) of the export tests, exported as URDF, load in
pybullet with their joints read back (types, limits equal to the measured ranges), and the software renderer's
pictures at the two limits differ where the part moved. Skipped without pybullet (an optional extra of the recipe);
without it the recipe says how to install it in one line."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "recipes"))
import test_export  # noqa: E402
import urdf_picture as U  # noqa: E402

from interreal.dataset import read_articulation  # noqa: E402

export_run_dir = test_export.export_run_dir  # the export tests' toy run as this module's fixture (trained once here)


@pytest.fixture(scope="module")
def pybullet():
    return pytest.importorskip("pybullet")


@pytest.fixture(scope="module")
def urdf_dir(pybullet, export_run_dir, tmp_path_factory):
    """`livescene export RUN --format urdf` of the toy run (pybullet asked first: no training when it is missing)."""
    from livescene.cli import main

    run, _ = export_run_dir
    out = tmp_path_factory.mktemp("urdf")
    assert main(["export", str(run), "--format", "urdf", "--out", str(out), "--resolution", str(test_export.RESOLUTION),
                 "--no-progress"]) == 0
    return out


def test_pybullet_reads_the_joints_back_and_the_limits_look_different(pybullet, urdf_dir, export_run_dir):
    _, ds = export_run_dir
    motions = read_articulation(ds)
    lines: list[str] = []
    width = 120
    strip, joints, shares = U.picture(urdf_dir, states=(0.0, 1.0), width=width, pb=pybullet, log=lines.append)
    assert {j.name: j.kind for j in joints} == {"door_joint": "revolute", "drawer_joint": "prismatic"}
    for j in joints:
        assert j.lower == pytest.approx(0.0, abs=1e-6)
        assert j.upper == pytest.approx(motions[j.name.removesuffix("_joint")].range, rel=1e-5)
        assert any(line.strip().startswith(f"{j.name}: {j.kind}, limits") for line in lines)
    height = round(width * 3 / 4)
    assert strip.shape == (2 * height, 2 * width, 3) and strip.dtype == np.uint8
    for row, (joint, share) in enumerate(zip(joints, shares)):
        lo = strip[row * height + 24:(row + 1) * height, :width].astype(int)  # below the caption band
        hi = strip[row * height + 24:(row + 1) * height, width:].astype(int)
        changed = int((np.abs(lo - hi).max(axis=2) > 40).sum())
        assert changed >= 0.005 * lo.shape[0] * lo.shape[1], (joint.name, changed)  # the part moved in the picture
        assert share >= 0.005, (joint.name, share)  # and in the view search's own count


def test_the_command_writes_a_small_palette_png(pybullet, urdf_dir, tmp_path, capsys):
    from PIL import Image

    out = tmp_path / "urdf.png"
    assert U.main([str(urdf_dir), "--out", str(out), "--states", "0,1", "--width", "120"]) == 0
    with Image.open(out) as im:
        assert im.mode == "P" and im.size == (240, 180)
    assert out.stat().st_size < 150_000
    assert "door_joint: revolute, limits 0 .. 1.5708" in capsys.readouterr().out


def test_without_pybullet_one_line_says_how_to_install_it(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(U, "import_pybullet", lambda: None)
    assert U.main([str(tmp_path), "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pip install pybullet" in err and "Traceback" not in err
    assert not (tmp_path / "x.png").exists()


def test_a_folder_without_urdf_is_a_one_line_error(pybullet, tmp_path, capsys):
    assert U.main([str(tmp_path), "--out", str(tmp_path / "x.png")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("urdf_picture: no *.urdf in") and err.count("\n") == 1
