"""The LiveScene layout: round trip, and one test per validation problem class."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from interreal import conventions as C
from interreal import dataset as D
from interreal.report import StageReport


def kinds(root: Path) -> set[str]:
    return D.validate(root).kinds()


def test_valid_dataset_round_trip(tiny_dataset: Path):
    res = D.validate(tiny_dataset)
    assert res.ok, D.format_problems(res)
    assert res.summary["frames"] == 4 and res.summary["objects"] == ["door", "drawer"]
    assert res.summary["labels_per_object"] == {"door": 2, "drawer": 0}
    ds = D.load_dataset(tiny_dataset)
    assert [f.fid for f in ds.frames] == ["00000", "00010", "00020", "00030"]
    assert ds.intrinsics.k1 == pytest.approx(-0.01)
    m = ds.load_mask(ds.frames[1])
    assert m.shape == (24, 32, 3) and m.dtype == bool and (m.sum(-1) == 1).all()
    values, given = ds.label_matrix()
    assert given.sum() == 2 and values[-1, 0] == 1.0
    # write -> read gives the same poses
    D.write_transforms(tiny_dataset, ds.intrinsics, ds.frames)
    ds2 = D.load_dataset(tiny_dataset)
    for a, b in zip(ds.frames, ds2.frames):
        np.testing.assert_allclose(a.c2w, b.c2w)


def test_conventions():
    assert C.frame_name(42) == "frame_00042"
    assert C.frame_id("images/frame_00042.png") == "00042"
    assert C.frame_id("frame_00042") == "00042"
    assert C.frame_index("seq_a_00107") == 107
    idx = np.array([[0, 1], [2, 0]], np.uint8)
    oh = C.index_to_onehot(idx, 2)
    assert oh[0, 0, 2] and oh[0, 1, 0] and oh[1, 0, 1]
    np.testing.assert_array_equal(C.onehot_to_index(oh), idx)
    m = np.eye(4); m[:3, 3] = [1, 2, 3]
    gl = C.opencv_to_opengl(m)
    np.testing.assert_allclose(gl[:3, 1], [0, -1, 0]) and np.testing.assert_allclose(C.opengl_to_opencv(gl), m)


def _edit_json(path: Path, fn) -> None:
    meta = json.loads(path.read_text())
    fn(meta)
    path.write_text(json.dumps(meta))


def test_missing_transforms(tiny_dataset):
    (tiny_dataset / "transforms.json").unlink()
    assert "no-transforms" in kinds(tiny_dataset)


def test_broken_json(tiny_dataset):
    (tiny_dataset / "transforms.json").write_text("{not json")
    assert "bad-json" in kinds(tiny_dataset)


def test_missing_intrinsics(tiny_dataset):
    _edit_json(tiny_dataset / "transforms.json", lambda m: m.pop("fl_x"))
    assert "missing-intrinsics" in kinds(tiny_dataset)


def test_bad_intrinsics(tiny_dataset):
    _edit_json(tiny_dataset / "transforms.json", lambda m: m.update(cx=-5))
    assert "bad-intrinsics" in kinds(tiny_dataset)


def test_non_orthonormal_rotation(tiny_dataset):
    def scale(m):
        m["frames"][1]["transform_matrix"][0][0] *= 1.5
    _edit_json(tiny_dataset / "transforms.json", scale)
    assert "bad-rotation" in kinds(tiny_dataset)


def test_reflection_rotation(tiny_dataset):
    def flip(m):
        t = np.array(m["frames"][0]["transform_matrix"]); t[:3, 0] *= -1
        m["frames"][0]["transform_matrix"] = t.tolist()
    _edit_json(tiny_dataset / "transforms.json", flip)
    assert "bad-rotation" in kinds(tiny_dataset)


def test_non_finite_translation(tiny_dataset):
    def nan(m):
        m["frames"][2]["transform_matrix"][1][3] = float("nan")
    _edit_json(tiny_dataset / "transforms.json", nan)
    assert "bad-pose" in kinds(tiny_dataset)


def test_frame_id_does_not_parse(tiny_dataset):
    def rename(m):
        m["frames"][0]["file_path"] = "images/frame_abc.png"
    _edit_json(tiny_dataset / "transforms.json", rename)
    assert "bad-frame-id" in kinds(tiny_dataset)


def test_duplicate_frame_id(tiny_dataset):
    src = tiny_dataset / "images" / "frame_00010.png"
    (tiny_dataset / "images" / "other_00010.png").write_bytes(src.read_bytes())
    _edit_json(tiny_dataset / "transforms.json", lambda m: m["frames"].append(
        {"file_path": "images/other_00010.png", "transform_matrix": m["frames"][1]["transform_matrix"]}))
    assert "duplicate-frame-id" in kinds(tiny_dataset)


def test_missing_image_and_non_image(tiny_dataset):
    (tiny_dataset / "images" / "frame_00010.png").unlink()
    (tiny_dataset / "images" / "frame_00020.png").write_bytes(b"this is not a png")
    k = kinds(tiny_dataset)
    assert {"missing-image", "bad-image"} <= k


def test_truncated_image(tiny_dataset):
    p = tiny_dataset / "images" / "frame_00020.png"
    p.write_bytes(p.read_bytes()[:60])
    assert "bad-image" in kinds(tiny_dataset)


def test_image_size_mismatch(tiny_dataset):
    _edit_json(tiny_dataset / "transforms.json", lambda m: m.update(w=64))
    assert "image-size" in kinds(tiny_dataset)


def test_missing_mask(tiny_dataset):
    (tiny_dataset / "masks" / "00020.npy").unlink()
    assert "missing-mask" in kinds(tiny_dataset)


def test_truncated_mask(tiny_dataset):
    p = tiny_dataset / "masks" / "00020.npy"
    p.write_bytes(p.read_bytes()[:100])
    assert "bad-mask" in kinds(tiny_dataset)


def test_mask_wrong_size(tiny_dataset):
    np.save(tiny_dataset / "masks" / "00020.npy", np.ones((10, 10, 3), bool))
    assert "mask-size" in kinds(tiny_dataset)


def test_mask_wrong_channels(tiny_dataset):
    m = np.zeros((24, 32, 2), bool); m[..., 1] = True
    np.save(tiny_dataset / "masks" / "00020.npy", m)
    assert "mask-channels" in kinds(tiny_dataset)


def test_mask_not_onehot(tiny_dataset):
    p = tiny_dataset / "masks" / "00010.npy"
    m = np.load(p); m[0, 0, :] = True
    np.save(p, m)
    res = D.validate(tiny_dataset)
    assert "mask-not-onehot" in res.kinds()
    assert "x=0, y=0" in str([p for p in res.problems if p.kind == "mask-not-onehot"][0])


def test_mapping_ids_not_contiguous(tiny_dataset):
    (tiny_dataset / "mapping.yaml").write_text(yaml.safe_dump({0: "door", 2: "drawer"}))
    assert "bad-mapping" in kinds(tiny_dataset)


def test_mapping_broken_yaml(tiny_dataset):
    (tiny_dataset / "mapping.yaml").write_text("0: [unclosed")
    assert "bad-yaml" in kinds(tiny_dataset)


def test_label_unknown_object(tiny_dataset):
    (tiny_dataset / "key_frame_value.yaml").write_text(yaml.safe_dump({"frame_00000": {"window": 0.5}}))
    assert "label-unknown-object" in kinds(tiny_dataset)


@pytest.mark.parametrize("value", [1.5, -0.1, ".nan", ".inf", "'open'"])
def test_label_bad_value(tiny_dataset, value):
    (tiny_dataset / "key_frame_value.yaml").write_text(f"frame_00000:\n  door: {value}\n")
    assert "label-bad-value" in kinds(tiny_dataset)


def test_label_unknown_frame(tiny_dataset):
    (tiny_dataset / "key_frame_value.yaml").write_text(yaml.safe_dump({"frame_00099": {"door": 0.5}}))
    assert "label-unknown-frame" in kinds(tiny_dataset)


def test_label_on_a_frame_sfm_left_out_is_a_warning(tiny_dataset):
    """A re-run of `poses` may drop a labelled frame: the dataset stays usable, the label unused, the user told."""
    image = sorted((tiny_dataset / "images").iterdir())[0]
    shutil.copy(image, image.with_name("frame_00099" + image.suffix))
    (tiny_dataset / "key_frame_value.yaml").write_text(yaml.safe_dump({"frame_00099": {"door": 0.5}}))
    res = D.validate(tiny_dataset)
    assert res.ok, D.format_problems(res)
    assert any("frame(s) 99 that have no camera pose" in w for w in res.warnings), res.warnings
    assert res.summary["labels_per_object"]["door"] == 0  # not counted: training cannot use it


def test_interrupted_stage_is_refused(tiny_dataset):
    with pytest.raises(RuntimeError):
        with StageReport(tiny_dataset, "masks"):
            raise RuntimeError("killed")
    res = D.validate(tiny_dataset)
    assert "stage-incomplete" in res.kinds()


def test_every_problem_is_listed(tiny_dataset):
    (tiny_dataset / "masks" / "00020.npy").unlink()
    (tiny_dataset / "mapping.yaml").write_text(yaml.safe_dump({0: "door", 5: "drawer"}))
    (tiny_dataset / "key_frame_value.yaml").write_text(yaml.safe_dump({"frame_00000": {"door": 7}}))
    assert {"missing-mask", "bad-mapping", "label-bad-value"} <= kinds(tiny_dataset)


def test_garbage_folder_never_crashes(tmp_path):
    root = tmp_path / "junk"
    (root / "images").mkdir(parents=True)
    (root / "images" / "frame_00001.png").write_bytes(b"\x00" * 10)
    (root / "transforms.json").write_text(json.dumps({"w": 4, "h": 4, "fl_x": 1, "fl_y": 1, "cx": 2, "cy": 2,
                                                     "frames": [{"file_path": "images/frame_00001.png",
                                                                 "transform_matrix": "garbage"}, 7]}))
    (root / "mapping.yaml").write_text("- a list\n- not a mapping\n")
    (root / "key_frame_value.yaml").write_text("\x00\x01 ::: [")
    res = D.validate(root)
    assert not res.ok and {"bad-pose", "bad-frame", "bad-mapping", "bad-yaml"} <= res.kinds()


def test_blender_layout_reader(tmp_path, tiny_dataset):
    """OmniSim layout: camera_angle_x and file_path without extension."""
    ds = D.load_dataset(tiny_dataset)
    meta = {"camera_angle_x": 1.0, "frames": [{"file_path": "./" + str(Path(f.file_path).with_suffix("")),
                                                "transform_matrix": f.c2w.tolist()} for f in ds.frames]}
    (tiny_dataset / "transforms.json").write_text(json.dumps(meta))
    sim = D.load_dataset(tiny_dataset)
    assert sim.layout == "blender" and len(sim.frames) == 4
    assert sim.frames[0].file_path == "images/frame_00000.png"
    assert sim.intrinsics.fl_x == pytest.approx(0.5 * 32 / np.tan(0.5))
    assert D.validate(tiny_dataset).ok


def test_validate_cli(tiny_dataset):
    ok = subprocess.run([sys.executable, "-m", "interreal", "validate", str(tiny_dataset)], capture_output=True, text=True)
    assert ok.returncode == 0 and "frames   4" in ok.stdout and "door: 2 labelled" in ok.stdout
    (tiny_dataset / "masks" / "00020.npy").unlink()
    (tiny_dataset / "mapping.yaml").write_text("0: door\n3: drawer\n")
    bad = subprocess.run([sys.executable, "-m", "interreal", "validate", str(tiny_dataset)], capture_output=True, text=True)
    assert bad.returncode == 1
    assert "missing-mask" in bad.stdout and "bad-mapping" in bad.stdout and "Traceback" not in bad.stderr


def test_atomic_write_leaves_old_file_on_crash(tmp_path):
    from interreal import atomic

    p = tmp_path / "a.json"
    atomic.write_json(p, {"v": 1})
    with pytest.raises(ZeroDivisionError):
        with atomic.atomic_open(p, "w") as fh:
            fh.write('{"v": 2')
            1 / 0
    assert json.loads(p.read_text()) == {"v": 1}
    assert list(tmp_path.iterdir()) == [p]


def test_atomic_write_gives_the_usual_file_mode(tmp_path):
    """Not mkstemp's 0600: a dataset written by one user stays readable by the others, as open() would leave it."""
    import os

    from interreal import atomic

    p = tmp_path / "b.json"
    atomic.write_json(p, {"v": 1})
    umask = os.umask(0)
    os.umask(umask)
    assert p.stat().st_mode & 0o777 == 0o666 & ~umask


def test_point_cloud_follows_ply_file_path(tiny_dataset: Path):
    """The point cloud is the file transforms.json's `ply_file_path` names (nerfstudio's key), `sparse_pc.ply`
    without it; a path leaving the dataset is not followed."""
    from interreal.sfm import write_ply

    rng = np.random.default_rng(0)
    near, far = rng.normal(0, 0.1, (20, 3)), rng.normal(5, 0.1, (30, 3))
    colours = np.zeros((50, 3), np.uint8)
    write_ply(tiny_dataset / "sparse_pc.ply", near, colours[:20])
    write_ply(tiny_dataset / "clouds" / "dense.ply", far, colours[:30])
    ds = D.load_dataset(tiny_dataset)
    np.testing.assert_allclose(D.read_point_cloud(ds.root, ds.extra), near, atol=1e-6)  # float32 on disk
    meta = json.loads((tiny_dataset / "transforms.json").read_text())
    for rel, expect in (("clouds/dense.ply", far), ("./clouds/dense.ply", far), ("../elsewhere.ply", near)):
        meta["ply_file_path"] = rel
        (tiny_dataset / "transforms.json").write_text(json.dumps(meta))
        ds = D.load_dataset(tiny_dataset)
        np.testing.assert_allclose(D.read_point_cloud(ds.root, ds.extra), expect, atol=1e-6)
    (tiny_dataset / "sparse_pc.ply").write_bytes(b"not a ply")
    assert D.read_point_cloud(tiny_dataset, {}) is None
