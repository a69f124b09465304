"""Round trip with the official LiveScene reader (issue 28.2).

`official_reader` below re-implements, from its published behaviour (../shared/reference/livescene-official.md),
what the official dataparser and `atrb_utils.read_attributes` do with a folder: nerfstudio's frame order and split,
`np.load(masks/<fid>.npy)` per frame, zero-filled labels min-max normalised per object over each split. It is kept
apart from `interreal.official` on purpose: the export is checked against the rules, not against itself.
A small simulated capture (40 frames) with its truth dataset (80x60) stands in for `interreal process` output.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from interreal import dataset as D
from interreal.cli import main as cli
from interreal.conventions import UNANNOTATED, frame_name, onehot_to_index


# ------------------------------------------------------------------------------------ the official reader, again
def official_reader(root: Path) -> dict[str, dict]:
    """{"train": ..., "eval": ...}: each with fids, raw (N, M), given (N, M), norm (N, M), masks [(H, W, C)],
    image sizes [(W, H)]. Raises what the official code would raise (a missing mask file, an unknown name)."""
    meta = json.loads((root / "transforms.json").read_text())
    frames = sorted(meta["frames"], key=lambda f: f["file_path"])  # nerfstudio sorts by file path
    paths = [f["file_path"] for f in frames]
    n = len(frames)
    if "train_filenames" in meta:
        splits = {"train": [i for i, p in enumerate(paths) if p in set(meta["train_filenames"])],
                  "eval": [i for i, p in enumerate(paths) if p in set(meta["test_filenames"])]}
    else:
        train = np.linspace(0, n - 1, math.ceil(0.9 * n), dtype=int)
        splits = {"train": list(train), "eval": list(np.setdiff1d(np.arange(n), train))}
    id2cls = yaml.safe_load((root / "mapping.yaml").read_text())
    cls2id = {v: k for k, v in id2cls.items()}
    kfv = yaml.safe_load((root / "key_frame_value.yaml").read_text()) or {}
    by_fid = {int(str(k).split("_")[-1]): v for k, v in kfv.items()}
    out = {}
    for split, idx in splits.items():
        fids = [Path(paths[i]).stem.split("_")[-1] for i in idx]
        raw = np.zeros((len(fids), len(cls2id)))
        given = np.zeros_like(raw, bool)
        for r, fid in enumerate(fids):
            for name, value in (by_fid.get(int(fid)) or {}).items():
                raw[r, cls2id[name]] = value
                given[r, cls2id[name]] = True
        with np.errstate(invalid="ignore", divide="ignore"):
            norm = (raw - raw.min(0)) / (raw.max(0) - raw.min(0))
        masks = [np.load(root / "masks" / f"{fid}.npy") for fid in fids]
        sizes = [Image.open(root / paths[i]).size for i in idx]
        out[split] = {"fids": fids, "raw": raw, "given": given, "norm": norm, "masks": masks, "sizes": sizes}
    return out


def assert_official_safe(root: Path) -> dict[str, dict]:
    read = official_reader(root)
    n_obj = len(yaml.safe_load((root / "mapping.yaml").read_text()))
    for split, r in read.items():
        assert r["fids"], f"{split} split is empty"
        assert np.isfinite(r["norm"]).all(), f"{split}: NaN after the official normalisation"
        np.testing.assert_allclose(r["norm"][r["given"]], r["raw"][r["given"]], atol=1e-6,
                                   err_msg=f"{split}: a label is rescaled by the official normalisation")
        for m, (w, h), fid in zip(r["masks"], r["sizes"], r["fids"]):
            assert m.shape == (h, w, n_obj + 1), (fid, m.shape, (w, h))
            assert (m.astype(bool).sum(-1) == 1).all(), f"mask {fid} is not one-hot"
    return read


# ------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def sim_ds(tmp_path_factory) -> Path:
    from interreal.synth import SynthConfig, truth_dataset, write_capture

    root = tmp_path_factory.mktemp("official")
    cap = write_capture(SynthConfig(frames=40, width=160, height=120, seed=0, label_fraction=0.25), root / "cap",
                        progress=False)
    return truth_dataset(cap, root / "ds", size=(80, 60))


@pytest.fixture
def ds_copy(sim_ds, tmp_path) -> Path:
    return Path(shutil.copytree(sim_ds, tmp_path / "ds"))


def set_labels(ds: Path, fn) -> None:
    labels = D.read_labels(ds)
    fn(labels)
    D.write_labels(ds, labels)


# ------------------------------------------------------------------------------------ export
def test_export_of_a_simulated_dataset_passes_the_official_reader(sim_ds, tmp_path, capsys):
    out = tmp_path / "off"
    assert cli(["export-official", str(sim_ds), str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"ns-train livescene --data {out} --pipeline.use-gt-val False livescene-real-data" in printed
    assert "--scene-scale" in printed and "each split" in printed
    read = assert_official_safe(out)
    assert len(read["train"]["fids"]) + len(read["eval"]["fids"]) == 40
    assert "train_filenames" not in json.loads((out / "transforms.json").read_text())  # the paper's split kept
    assert cli(["export-official", "--check", str(out)]) == 0


def test_fraction_split_that_would_give_nan_gets_explicit_lists(ds_copy, tmp_path, capsys):
    """No label on the fraction split's eval frames: the official reader gives NaN on the source; the export moves
    frames at 0 and 1 into eval and lists the split, and then reads with no NaN and no rescaled label."""
    before = official_reader(ds_copy)
    eval_keys = {frame_name(int(f)) for f in before["eval"]["fids"]}
    def drop(lab):
        for k in [k for k in lab if k in eval_keys]:
            del lab[k]
        lab.setdefault("frame_00010", {})["top drawer"] = 1.0  # open from frame 9 to 13 (truth): a second 1.0
    set_labels(ds_copy, drop)
    assert not np.isfinite(official_reader(ds_copy)["eval"]["norm"]).all()  # the problem the export must fix
    assert cli(["export-official", "--check", str(ds_copy)]) == 1
    assert "NaN" in capsys.readouterr().out
    out = tmp_path / "off"
    assert cli(["export-official", str(ds_copy), str(out)]) == 0
    meta = json.loads((out / "transforms.json").read_text())
    assert meta["val_filenames"] == meta["test_filenames"]
    assert not set(meta["train_filenames"]) & set(meta["test_filenames"])
    assert_official_safe(out)


def test_labels_that_no_split_keeps_are_refused_by_name(ds_copy, tmp_path, capsys):
    """'top drawer' never labelled above 0.8: the official reader would read 0.8 as 1.0, whatever the split."""
    def cap(lab):
        for entry in lab.values():
            if "top drawer" in entry:
                entry["top drawer"] = min(entry["top drawer"], 0.8)
    set_labels(ds_copy, cap)
    out = tmp_path / "off"
    assert cli(["export-official", str(ds_copy), str(out)]) == 2
    err = capsys.readouterr().err
    assert "'top drawer'" in err and "0.8" in err and "\n" in err.strip() and "Traceback" not in err
    assert not out.exists() and not list(tmp_path.glob(".off*"))


def test_check_names_a_missing_mask_and_a_wrong_size(ds_copy, capsys):
    (ds_copy / "masks" / "00003.npy").unlink()
    m = np.load(ds_copy / "masks" / "00005.npy")
    np.save(ds_copy / "masks" / "00005.npy", m[:-2])
    assert cli(["export-official", "--check", str(ds_copy)]) == 1
    out = capsys.readouterr().out
    assert "masks/00003.npy is missing" in out and "masks/00005.npy has shape (58, 80, 3)" in out


def test_export_refuses_what_it_cannot_write_safely(sim_ds, ds_copy, tmp_path, capsys):
    """A non-empty OUT, an OUT inside the dataset, a dataset that does not validate, --check with two folders: one
    line (or the problem list) naming the cause, exit 2, nothing written."""
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "x.txt").write_text("mine")
    cases = [(["export-official", str(sim_ds), str(busy)], "is not empty"),
             (["export-official", str(ds_copy), str(ds_copy / "off")], "inside the dataset"),
             (["export-official", "--check", str(sim_ds), str(tmp_path / "o")], "takes one folder")]
    for argv, needle in cases:
        assert cli(argv) == 2, argv
        err = capsys.readouterr().err
        assert needle in err and "Traceback" not in err, err
    (ds_copy / "masks" / "00001.npy").unlink()
    assert cli(["export-official", str(ds_copy), str(tmp_path / "o")]) == 2
    assert "missing-mask" in capsys.readouterr().err
    assert not (tmp_path / "o").exists() and not (ds_copy / "off").exists() and (busy / "x.txt").read_text() == "mine"


# ------------------------------------------------------------------------------------ reading official data
def polycam_dataset(root: Path, n: int = 10, size=(32, 24)) -> Path:
    """An official-looking real capture: per-frame intrinsics (Polycam), ply_file_path, no reports/, raw values
    in degrees and metres, and mask pixels with no channel set."""
    from conftest import make_tiny_dataset

    make_tiny_dataset(root, n_frames=n, size=size)
    meta = json.loads((root / "transforms.json").read_text())
    shared = {k: meta.pop(k) for k in ("w", "h", "fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2", "camera_model")}
    for f in meta["frames"]:
        f.update(shared)
    trimesh = pytest.importorskip("trimesh")
    trimesh.PointCloud(np.random.default_rng(0).uniform(-1, 1, (50, 3))).export(root / "points.ply")
    meta["ply_file_path"] = "points.ply"
    (root / "transforms.json").write_text(json.dumps(meta))
    (root / "key_frame_value.yaml").write_text(yaml.safe_dump(
        {"frame_00000": {"door": 10.0, "drawer": 0.3}, "frame_00020": {"door": 90.0},
         "frame_00050": {"door": 50.0, "drawer": -0.2}}))
    m = np.load(root / "masks" / "00010.npy")
    m[0, :5] = False  # five pixels with no channel
    np.save(root / "masks" / "00010.npy", m)
    return root


def test_official_data_loads_with_raw_values_normalised_and_empty_pixels_unknown(tmp_path, capsys):
    ds = polycam_dataset(tmp_path / "poly")
    assert cli(["validate", str(ds)]) == 0, capsys.readouterr().out
    data = D.load_dataset(ds)
    err = capsys.readouterr().err
    assert "normalised" in err and "'door' [0, 90]" in err and "not clipped" in err
    # the official rule over the whole sequence: unlabelled frames count as 0, so door 10 -> 10/90, not 0
    assert data.labels["frame_00000"]["door"] == pytest.approx(10 / 90)
    assert data.labels["frame_00020"]["door"] == pytest.approx(1.0)
    assert data.labels["frame_00050"]["drawer"] == pytest.approx(0.0)  # drawer spans [-0.2, 0.3]
    assert data.labels["frame_00000"]["drawer"] == pytest.approx(1.0)
    assert data.frame_intrinsics(data.frames[0]).fl_x == 30.0 and data.intrinsics is None
    assert D.read_point_cloud(ds, data.extra).shape == (50, 3)
    index = onehot_to_index(data.load_mask(data.frames[1]))
    assert (index[0, :5] == UNANNOTATED).all() and (index[0, 5:] != UNANNOTATED).all()


def test_official_data_trains_with_empty_pixels_as_unknown(tmp_path):
    import torch

    from livescene.config import TrainConfig
    from livescene.data import UNKNOWN, RayData, load_views

    ds = polycam_dataset(tmp_path / "poly")
    views = load_views(ds, TrainConfig(holdout_every=0))
    assert views.box_source == "sparse_pc.ply"  # the point cloud that ply_file_path names was read
    rays = RayData(views, torch.device("cpu"))
    assert (rays.mask[1, 0, :5] == UNKNOWN).all() and (rays.mask[1, 0, 5:] != UNKNOWN).all()
    assert np.all((views.labels >= 0) & (views.labels <= 1))


def test_what_counts_as_official_data(tmp_path, tiny_dataset):
    from interreal.official import is_official_data

    ds = polycam_dataset(tmp_path / "poly")
    assert is_official_data(ds) and not is_official_data(tiny_dataset)  # shared intrinsics: our layout
    (ds / "reports").mkdir()
    (ds / "reports" / "motions.json").write_text("{}")  # `interreal motions` on official data: still official
    assert is_official_data(ds)
    (ds / "reports" / "labels.json").write_text("{}")  # our labels stage wrote the states: strict again
    assert not is_official_data(ds)


def test_our_dataset_still_refuses_a_label_outside_0_1(tiny_dataset, capsys):
    D.write_labels(tiny_dataset, {"frame_00000": {"door": 5.0}})
    assert cli(["validate", str(tiny_dataset)]) == 1
    assert "outside [0, 1]" in capsys.readouterr().out


def test_official_split_for_training_and_eval(tmp_path):
    from livescene.config import TrainConfig
    from livescene.data import load_views
    from livescene.official_split import use_split

    ds = polycam_dataset(tmp_path / "poly", n=12)
    views = load_views(ds, TrainConfig(split="official"))
    left_out = sorted(set(range(12)) - set(np.linspace(0, 11, math.ceil(0.9 * 12), dtype=int).tolist()))
    assert views.held_out == left_out == [10]  # nerfstudio's fraction split of 12 frames sorted by file path
    assert not views.given[10].any() and sorted(views.train + views.held_out) == list(range(12))
    ours = load_views(ds, TrainConfig())

    class Run:
        pass
    run = Run()
    run.views = ours
    with pytest.raises(Exception, match="trained on 1 of the 1 official eval frames"):
        use_split(run, "official")
    run.views = views
    assert use_split(run, "official")["held_out_frames"] == 1


def test_synthetic_layout_official_split_is_every_second_frame():
    from interreal.official import official_positions

    paths = [f"images/r_{i:05d}.png" for i in (4, 1, 3, 0, 2)]  # Blender order is as listed, not sorted
    train, held = official_positions("blender", {}, paths)
    assert held == [0, 2, 4] and train == [1, 3]


def test_scene_scale_follows_nerfstudio_pose_normalisation():
    """nerfstudio centres the cameras, turns their mean up (y) to +z and scales the largest coordinate to 1."""
    from scipy.spatial.transform import Rotation

    from interreal.official import nerfstudio_transform

    rng = np.random.default_rng(3)
    tilt = Rotation.from_rotvec([0.4, -0.2, 0.1]).as_matrix()
    c2w = np.tile(np.eye(4), (20, 1, 1))
    c2w[:, :3, :3] = tilt @ Rotation.from_rotvec(np.c_[np.zeros(20), rng.uniform(-3, 3, 20), np.zeros(20)]).as_matrix()
    c2w[:, :3, 3] = rng.normal(size=(20, 3)) * 4 + 10
    tf, s = nerfstudio_transform(c2w)
    moved = (c2w[:, :3, 3] @ tf[:, :3].T + tf[:, 3]) * s
    assert np.abs(moved).max() == pytest.approx(1.0) and np.abs(moved.mean(0)).max() < 1e-9
    up = tf[:, :3] @ c2w[:, :3, 1].mean(0)
    np.testing.assert_allclose(up / np.linalg.norm(up), [0, 0, 1], atol=1e-9)


def test_eval_split_official_on_a_run_trained_with_it(tmp_path, one_thread, capsys):
    """`livescene train --set split=official` holds out the official eval frame; `eval --split official` scores
    exactly that frame and says so in its JSON."""
    from livescene.cli import main as livescene

    ds = polycam_dataset(tmp_path / "poly", n=12)
    run, out = tmp_path / "run", tmp_path / "eval.json"
    assert livescene(["train", str(ds), "--out", str(run), "--preset", "tiny", "--steps", "2", "--device", "cpu",
                      "--threads", "1", "--no-progress", "--set", "split=official"]) == 0
    assert livescene(["eval", str(run), "--out", str(out), "--split", "official", "--device", "cpu",
                      "--novel", "0"]) == 0, capsys.readouterr().err
    res = json.loads(out.read_text())
    assert res["split"]["split"] == "official" and res["held_out_frames"] == 1
    assert [f["frame"] for f in res["frames"]] == ["00100"]  # position 10 of 12 (frames 0, 10, ..., 110)


def test_export_refuses_official_data_with_raw_values(tmp_path, capsys):
    ds = polycam_dataset(tmp_path / "poly")
    assert cli(["export-official", str(ds), str(tmp_path / "off")]) == 2
    err = capsys.readouterr().err
    assert "raw values outside [0, 1]" in err and "'door' = 10" in err and not (tmp_path / "off").exists()
