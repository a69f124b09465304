"""Bad-input corpus (interreal side, issue 25): every case runs the real CLI and must end in a clear one-line error
(or a correct result), never a traceback, never a wrong dataset that validates.

Cases build on the tiny hand-made dataset of conftest.py (4 frames, 32x24, 2 objects); reports are stamped with
the fingerprints the stages record (`stamp`), so staleness is checked as `interreal validate` sees it. The real
pipeline (a simulated capture through `interreal process`) is exercised once, shared by the staleness and kill tests.
"""

from __future__ import annotations

import errno
import json
import random
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pytest

from conftest import make_tiny_dataset
from interreal import atomic
from interreal import dataset as D
from interreal import provenance as P
from interreal.cli import main as cli
from interreal.report import StageReport
from test_ingest import textured, write_video


# ------------------------------------------------------------------------------------------------ helpers
def stamp(ds: Path, source: str = "capture-a") -> None:
    """Finished reports with the fingerprints each stage records, as if the stages had made this dataset."""
    with StageReport(ds, "frames", inputs={"fingerprints": {"source": {"files": source, "content": source}}}):
        pass
    for stage, kinds in (("masks", ["images"]), ("poses", ["images", "masks"]), ("labels", ["capture"]),
                         ("motions", ["transforms", "labels", "masks", "mapping"])):
        with StageReport(ds, stage, inputs={"fingerprints": P.fingerprints(ds, kinds)}):
            pass


def edit_json(path: Path, fn: Callable[[dict], None]) -> None:
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def set_frame0(key: str, value) -> Callable[[dict], None]:
    def fn(meta: dict) -> None:
        meta["frames"][0][key] = value
    return fn


def new_image(ds: Path, name: str = "frame_00000.png", seed: int = 7) -> None:
    rng = np.random.default_rng(seed)
    atomic.write_image(ds / "images" / name, rng.integers(0, 255, (24, 32, 3), dtype=np.uint8))


def run(argv: list[str], capsys) -> tuple[int, str]:
    code = cli(argv)
    cap = capsys.readouterr()
    text = cap.out + cap.err
    assert "Traceback" not in text, text
    return code, text


def photos(folder: Path, n: int, size=(128, 96)) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        cv2.imwrite(str(folder / f"{i:03d}.png"), textured(i, *size))
    return folder


# ------------------------------------------------------------------------------------------------ the corpus
@dataclass
class Case:
    id: str
    setup: Callable[[Path, Path], list[str]]  # (dataset, tmp) -> argv; mutates the dataset / writes inputs
    code: int
    says: tuple[str, ...]  # every one must appear in the output


def v(fn: Callable[[Path], None]) -> Callable[[Path, Path], list[str]]:
    """A dataset corruption checked by `interreal validate`."""
    def setup(ds: Path, tmp: Path) -> list[str]:
        fn(ds)
        return ["validate", str(ds)]
    return setup


def mask0(ds: Path) -> Path:
    return ds / "masks" / "00000.npy"


def _save_mask(ds: Path, arr: np.ndarray) -> None:
    np.save(mask0(ds), arr)


def _labels(entries: dict) -> Callable[[Path], None]:
    return lambda ds: atomic.write_yaml(ds / "key_frame_value.yaml", entries)


def _stamped(fn: Callable[[Path], None]) -> Callable[[Path], None]:
    def both(ds: Path) -> None:
        stamp(ds)
        time.sleep(0.01)
        fn(ds)
    return both


def _rewrite_masks(ds: Path) -> None:
    for p in sorted((ds / "masks").glob("*.npy")):
        m = np.load(p)
        m[:, :, :] = False
        m[..., -1] = True  # objects gone: every pixel background
        np.save(p, m)


def _copy_touch(ds: Path) -> None:
    """Same bytes, new modification times (what `cp -r` does): not stale."""
    for p in list(ds.rglob("*")):
        if p.is_file() and "reports" not in p.parts:
            data = p.read_bytes()
            p.unlink()
            p.write_bytes(data)


def _other_capture(ds: Path) -> None:
    with StageReport(ds, "frames", inputs={"fingerprints": {"source": {"files": "b", "content": "b"}}}):
        pass


def _keyframes_ds(ds: Path, mapping: dict) -> Path:
    atomic.write_yaml(ds / "mapping.yaml", mapping)
    kf = ds / "kf"
    index = np.zeros((24, 32), np.uint8)
    index[2:8, 3:9] = 1
    atomic.write_image(kf / "00000.png", index)
    return kf


def _masks_dup(ds: Path, tmp: Path) -> list[str]:
    kf = _keyframes_ds(ds, {0: "door", 1: "door"})
    return ["masks", str(ds), "--keyframes", str(kf), "--quiet", "--preview", "none"]


def _label_file(content: dict, *extra: str) -> Callable[[Path, Path], list[str]]:
    def setup(ds: Path, tmp: Path) -> list[str]:
        f = tmp / "labels.yaml"
        atomic.write_yaml(f, content)
        return ["label", str(ds), "--from", str(f), *extra]
    return setup


def _frames_from(make: Callable[[Path], Path], *extra: str) -> Callable[[Path, Path], list[str]]:
    def setup(ds: Path, tmp: Path) -> list[str]:
        return ["frames", str(make(tmp)), str(tmp / "out"), *extra]
    return setup


def _truncated_video(tmp: Path) -> Path:
    data = write_video(tmp / "v.mp4", [textured(i) for i in range(30)]).read_bytes()
    (tmp / "cut.mp4").write_bytes(data[: len(data) // 3])
    return tmp / "cut.mp4"


def _one_image(tmp: Path) -> Path:
    return photos(tmp / "one", 1)


def _garbage_png(tmp: Path) -> Path:
    folder = photos(tmp / "p", 3)
    (folder / "004.png").write_bytes(b"not a png at all")
    return folder


def _mixed(tmp: Path) -> Path:
    folder = photos(tmp / "p", 3)
    cv2.imwrite(str(folder / "003.png"), textured(3, 100, 80))
    return folder


def _turned(tmp: Path) -> Path:
    """Photos of one camera, one of them held the other way (portrait among landscape)."""
    folder = photos(tmp / "p", 3)
    h, w = cv2.imread(str(next(folder.iterdir()))).shape[:2]
    cv2.imwrite(str(folder / "003.png"), textured(3, h, w))  # w x h swapped
    return folder


def _bytes(name: str, data: bytes) -> Callable[[Path], Path]:
    def make(tmp: Path) -> Path:
        (tmp / name).write_bytes(data)
        return tmp / name
    return make


def _process_labels_broken(ds: Path, tmp: Path) -> list[str]:
    (tmp / "s.yaml").write_text("frame_00000: {door: [0.5\n")
    return ["process", str(_one_image(tmp)), str(tmp / "out"), "--labels", str(tmp / "s.yaml")]


def _poses_file_broken(ds: Path, tmp: Path) -> list[str]:
    (tmp / "t.json").write_text('{"frames": [')
    return ["poses", str(ds), "--poses", str(tmp / "t.json")]


CASES = [
    # masks
    Case("mask-float-half", v(lambda ds: _save_mask(ds, np.full((24, 32, 3), 0.5, np.float32))), 1,
         ("00000.npy", "stored as float32, not bool")),
    Case("mask-uint8", v(lambda ds: _save_mask(ds, np.load(mask0(ds)).astype(np.uint8))), 1, ("stored as uint8",)),
    Case("mask-2d", v(lambda ds: _save_mask(ds, np.ones((24, 32), bool))), 1, ("2-D array of shape (24, 32)",)),
    Case("mask-4d", v(lambda ds: _save_mask(ds, np.ones((1, 24, 32, 3), bool))), 1, ("4-D array",)),
    Case("mask-truncated", v(lambda ds: mask0(ds).write_bytes(mask0(ds).read_bytes()[:200])), 1,
         ("00000.npy", "truncated")),
    Case("mask-garbage", v(lambda ds: mask0(ds).write_bytes(b"garbage")), 1, ("unreadable .npy",)),
    Case("mask-pickle", v(lambda ds: np.save(mask0(ds), np.array([{"a": 1}], dtype=object), allow_pickle=True)), 1,
         ("00000.npy",)),
    Case("mask-wrong-size", v(lambda ds: _save_mask(ds, np.ones((12, 16, 3), bool))), 1, ("mask is 16x12",)),
    Case("mask-channels", v(lambda ds: atomic.write_yaml(ds / "mapping.yaml", {0: "door", 1: "drawer", 2: "lid"})),
         1, ("3 channels, expected 4", "re-run `interreal masks`")),
    Case("mask-not-onehot", v(lambda ds: _save_mask(ds, np.ones((24, 32, 3), bool))), 1, ("exactly one channel",)),
    Case("mask-missing", v(lambda ds: mask0(ds).unlink()), 1, ("no mask for images/frame_00000.png",)),
    # mapping
    Case("mapping-duplicate-names", v(lambda ds: atomic.write_yaml(ds / "mapping.yaml", {0: "door", 1: "door"})), 1,
         ("names used twice: ['door']",)),
    Case("mapping-ids-0-5", v(lambda ds: atomic.write_yaml(ds / "mapping.yaml", {0: "door", 5: "drawer"})), 1,
         ("object ids [0, 5] are not contiguous",)),
    Case("mapping-broken-yaml", v(lambda ds: (ds / "mapping.yaml").write_text("0: [door\n")), 1,
         ("mapping.yaml", "not valid YAML")),
    Case("mapping-string-id", v(lambda ds: atomic.write_yaml(ds / "mapping.yaml", {"a": "door", 1: "drawer"})), 1,
         ("object id 'a' is not an integer",)),
    Case("mapping-list", v(lambda ds: atomic.write_yaml(ds / "mapping.yaml", ["door", "drawer"])), 1,
         ("expected a non-empty mapping",)),
    # labels
    Case("label-5.0", v(_labels({"frame_00000": {"door": 5.0}})), 1, ("frame_00000", "door: 5.0 is outside [0, 1]")),
    Case("label-word", v(_labels({"frame_00000": {"door": "abc"}})), 1,
         ("key_frame_value.yaml[frame_00000]", "'abc' is not a number")),
    Case("label-nan", v(lambda ds: (ds / "key_frame_value.yaml").write_text("frame_00000: {door: .nan}\n")), 1,
         ("not a finite number",)),
    Case("label-negative", v(_labels({"frame_00010": {"door": -0.5}})), 1, ("outside [0, 1]",)),
    Case("label-list-value", v(_labels({"frame_00000": {"door": [0.5]}})), 1, ("is not a number",)),
    Case("label-entry-not-dict", v(_labels({"frame_00000": 0.5})), 1, ("expected {object name: value}",)),
    Case("label-bad-key", v(_labels({"door": {"door": 0.5}})), 1, ("does not end in a frame number",)),
    Case("label-unknown-frame", v(_labels({"frame_00099": {"door": 0.5}})), 1, ("frame 99 is not in transforms",)),
    Case("label-unknown-object", v(_labels({"frame_00000": {"fridge": 0.5}})), 1, ("'fridge' is not in mapping",)),
    Case("labels-broken-yaml", v(lambda ds: (ds / "key_frame_value.yaml").write_text("frame_00000: {door: 0.5\n")),
         1, ("key_frame_value.yaml", "not valid YAML")),
    Case("labels-top-list", v(_labels([1, 2])), 1, ("expected {frame_00042: {object name: value}}",)),
    # transforms.json
    Case("transforms-truncated", v(lambda ds: (ds / "transforms.json").write_text((ds / "transforms.json")
                                                                                  .read_text()[:100])), 1,
         ("transforms.json", "not valid JSON")),
    Case("transforms-missing", v(lambda ds: (ds / "transforms.json").unlink()), 1, ("run `interreal poses DS`",)),
    Case("pose-nan", v(lambda ds: edit_json(ds / "transforms.json", set_frame0(
        "transform_matrix", [[float("nan")] * 4] * 4))), 1, ("frames[0]", "non-finite")),
    Case("pose-string", v(lambda ds: edit_json(ds / "transforms.json", set_frame0("transform_matrix", "abc"))), 1,
         ("frames[0]", "transform_matrix unreadable")),
    Case("pose-3x3", v(lambda ds: edit_json(ds / "transforms.json", set_frame0(
        "transform_matrix", np.eye(3).tolist()))), 1, ("shape (3, 3)",)),
    Case("pose-scaled", v(lambda ds: edit_json(ds / "transforms.json", set_frame0(
        "transform_matrix", (2 * np.eye(4)).tolist()))), 1, ("not orthonormal",)),
    Case("intrinsics-string", v(lambda ds: edit_json(ds / "transforms.json", lambda m: m.update(fl_x="abc"))), 1,
         ("intrinsics must be numbers",)),
    Case("intrinsics-nan", v(lambda ds: edit_json(ds / "transforms.json", lambda m: m.update(fl_x=float("nan")))), 1,
         ("intrinsics must be finite",)),
    Case("frames-not-list", v(lambda ds: edit_json(ds / "transforms.json", lambda m: m.update(frames={}))), 1,
         ("'frames' is missing or empty",)),
    Case("file-path-absolute", v(lambda ds: edit_json(ds / "transforms.json", set_frame0(
        "file_path", str((ds / "images" / "frame_00000.png").resolve())))), 1, ("leaves the dataset folder",)),
    Case("file-path-escapes", v(lambda ds: edit_json(ds / "transforms.json", set_frame0(
        "file_path", "../elsewhere/frame_00000.png"))), 1, ("leaves the dataset folder",)),
    Case("image-truncated", v(lambda ds: (ds / "images" / "frame_00010.png").write_bytes(
        (ds / "images" / "frame_00010.png").read_bytes()[:40])), 1, ("frame_00010.png", "not a readable image")),
    Case("image-truncated-quick-mode", lambda ds, tmp: [(ds / "images" / "frame_00010.png").write_bytes(
        (ds / "images" / "frame_00010.png").read_bytes()[:-20]), ["validate", str(ds), "--no-masks"]][1], 1,
         ("frame_00010.png", "not a readable image")),
    Case("mask-float-quick-mode", lambda ds, tmp: [_save_mask(ds, np.full((24, 32, 3), 0.5)),
                                                   ["validate", str(ds), "--no-masks"]][1], 1, ("stored as float64",)),
    Case("image-resized", v(lambda ds: atomic.write_image(ds / "images" / "frame_00010.png",
                                                           np.zeros((12, 16, 3), np.uint8))), 1,
         ("image is 16x12 but transforms.json says 32x24",)),
    # articulation and reports
    Case("articulation-broken", v(lambda ds: (ds / "articulation.json").write_text("{")), 1,
         ("articulation.json", "not valid JSON")),
    Case("articulation-nan-axis", v(lambda ds: atomic.write_json(ds / "articulation.json", {"objects": {"door": {
        "type": "hinge", "axis": [float("nan"), 0, 1], "origin": [0, 0, 0], "range": 1.0}}})), 1, ("must be finite",)),
    Case("articulation-unknown-object", v(lambda ds: atomic.write_json(ds / "articulation.json", {"objects": {"oven": {
        "type": "slide", "axis": [0, 0, 1], "range": 1.0}}})), 1, ("'oven' is not in mapping.yaml",)),
    Case("report-running", v(lambda ds: atomic.write_json(ds / "reports" / "masks.json",
                                                          {"stage": "masks", "status": "running"})), 1,
         ("stage 'masks' is running",)),
    Case("report-failed", v(lambda ds: atomic.write_json(ds / "reports" / "poses.json", {
        "stage": "poses", "status": "failed", "error": "StageError: boom"})), 1, ("'poses' is failed", "boom")),
    Case("report-broken-json", v(lambda ds: (ds / "reports").mkdir() or (ds / "reports" / "poses.json").write_text("{")),
         1, ("reports/poses.json", "not valid JSON")),
    Case("report-tmp-left-over", v(lambda ds: (ds / "reports").mkdir() or (ds / "reports" / ".poses.json.x1.tmp")
                                   .write_text("{half")), 0, ("OK",)),
    Case("not-a-folder", lambda ds, tmp: ["validate", str(tmp / "nowhere")], 1, ("not a folder",)),
    Case("empty-folder", lambda ds, tmp: (tmp / "e").mkdir() or ["validate", str(tmp / "e")], 1,
         ("transforms.json", "missing")),
    # staleness (reports stamped as the stages write them)
    Case("stale-images", v(_stamped(lambda ds: new_image(ds))), 1,
         ("masks.json: masks were computed from other images", "poses.json: poses were computed from other images",
          "run `interreal poses")),
    Case("stale-masks", v(_stamped(_rewrite_masks)), 1,
         ("[stale]", "poses were computed from other masks", "motions were computed from other masks")),
    Case("stale-poses", v(_stamped(lambda ds: edit_json(ds / "transforms.json", lambda m: m.update(fl_x=31.0)))), 1,
         ("[stale]", "motions were computed from other poses",)),
    Case("stale-labels", v(_stamped(lambda ds: _labels({"frame_00000": {"door": 0.5}})(ds))), 1,
         ("[stale]", "motions were computed from other labels",)),
    Case("stale-capture", v(_stamped(_other_capture)), 1,
         ("labels were set on the frames of another capture", "--replace",
          "motions were computed from labels that are stale")),
    Case("stamped-copy-is-fresh", v(_stamped(_copy_touch)), 0, ("OK",)),
    Case("stamped-untouched-is-fresh", v(stamp), 0, ("OK",)),
    # label tool: repair and refuse
    Case("label-list-shows-bad", lambda ds, tmp: _labels({"frame_00000": {"door": "abc"}})(ds) or
         ["label", str(ds), "--list"], 0, ("!'abc'", "door = 'abc' is not a number")),
    Case("label-set-repairs", lambda ds, tmp: _labels({"frame_00000": {"door": "abc"}, "frame_00010": "x"})(ds) or
         ["label", str(ds), "--set", "door", "0", "0.5", "--set", "door", "10", "1"], 0, ("frame_00000 door = 0.5000",)),
    Case("label-unset-repairs", lambda ds, tmp: _labels({"frame_00000": {"door": "abc"}})(ds) or
         ["label", str(ds), "--unset", "door", "0"], 0, ("unset door @ frame_00000",)),
    Case("label-list-broken-yaml", lambda ds, tmp: [(ds / "key_frame_value.yaml").write_text("a: [\n"),
                                                    ["label", str(ds), "--list"]][1], 2, ("key_frame_value.yaml is not valid YAML",)),
    Case("label-import-typo", _label_file({"frame_00000": {"drawr": 0.5}}), 2,
         ("unknown objects ['drawr']", "did you mean 'drawer'?", "--add-objects")),
    Case("label-import-add-to-masked", _label_file({"frame_00000": {"oven": 0.5}}, "--add-objects"), 2,
         ("wrong channel count", "re-run `interreal masks`")),
    Case("label-add-object-to-masked", lambda ds, tmp: ["label", str(ds), "--add-object", "oven"], 2,
         ("wrong channel count",)),
    Case("label-import-word", _label_file({"frame_00000": {"door": "half"}}), 2, ("'half' is not a number",)),
    Case("label-import-5", _label_file({"frame_00000": {"door": 5}}), 2, ("5 is outside [0, 1]",)),
    Case("label-set-nan", lambda ds, tmp: ["label", str(ds), "--set", "door", "0", "nan"], 2, ("not a finite",)),
    # readers: one line naming file and entry
    Case("motions-label-word", lambda ds, tmp: _labels({"frame_00000": {"door": "abc"}})(ds) or
         ["motions", str(ds)], 2, ("key_frame_value.yaml: entry frame_00000 / door: 'abc' is not a number",)),
    Case("motions-label-5", lambda ds, tmp: _labels({"frame_00000": {"door": 5.0}})(ds) or ["motions", str(ds)], 2,
         ("entry frame_00000 / door: 5.0 is outside [0, 1]",)),
    Case("motions-mapping-broken", lambda ds, tmp: [(ds / "mapping.yaml").write_text("0: [door\n"),
                                                    ["motions", str(ds)]][1], 2, ("mapping.yaml is not valid YAML",)),
    Case("masks-duplicate-names", _masks_dup, 2, ("['door'] are used for more than one object",)),
    Case("poses-file-broken", _poses_file_broken, 2, ("t.json is not valid JSON",)),
    # frames / ingest
    Case("one-image", _frames_from(_one_image), 2, ("has only 1 image;", "at least 3")),
    Case("video-empty", _frames_from(_bytes("e.mp4", b"")), 2, ("empty (0 bytes)",)),
    Case("video-garbage", _frames_from(_bytes("g.mp4", b"\x00" * 4000)), 2, ("not a readable video",)),
    Case("video-truncated", _frames_from(_truncated_video), 2, ("truncated",)),
    Case("text-file-input", _frames_from(_bytes("notes.txt", b"hello")), 2, ("single file that is not a video",)),
    Case("missing-input", lambda ds, tmp: ["frames", str(tmp / "nope.mp4"), str(tmp / "out")], 2,
         ("does not exist",)),
    Case("folder-garbage-png", _frames_from(_garbage_png), 2, ("004.png",)),
    Case("folder-mixed-sizes", _frames_from(_mixed), 2, ("mixes image sizes",)),
    Case("folder-turned-photo", _frames_from(_turned), 2, ("mixes landscape and portrait photos",
                                                           "the camera was turned for 1 of them", "not resize")),
    Case("folder-only-text", _frames_from(lambda tmp: [(tmp / "t").mkdir(), (tmp / "t" / "a.txt").write_text("x"),
                                                       tmp / "t"][2]), 2, ("holds no images",)),
    Case("process-labels-broken", _process_labels_broken, 2, ("s.yaml", "not valid YAML")),
    Case("frames-target-2", _frames_from(lambda tmp: photos(tmp / "p", 4), "--target", "2"), 2,
         ("at least 3 frames",)),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input(case: Case, tmp_path: Path, capsys):
    ds = make_tiny_dataset(tmp_path / "ds")
    argv = case.setup(ds, tmp_path)
    capsys.readouterr()
    code, text = run(argv, capsys)
    assert code == case.code, text
    for phrase in case.says:
        assert phrase in text, f"{phrase!r} not in:\n{text}"


def test_corpus_is_large_enough():
    assert len(CASES) >= 40


# ------------------------------------------------------------------------------------------------ behaviours
def test_repaired_labels_validate(tiny_dataset, capsys):
    _labels({"frame_00000": {"door": "abc"}, "frame_00030": {"door": 1.0}})(tiny_dataset)
    assert D.validate(tiny_dataset).kinds() == {"label-bad-value"}
    assert run(["label", str(tiny_dataset), "--set", "door", "0", "0"], capsys)[0] == 0
    assert D.validate(tiny_dataset).ok
    assert D.read_labels(tiny_dataset) == {"frame_00000": {"door": 0.0}, "frame_00030": {"door": 1.0}}


def test_labels_of_another_capture_stay_stale_until_replaced(tiny_dataset, capsys):
    stamp(tiny_dataset)
    _other_capture(tiny_dataset)
    ds = str(tiny_dataset)
    assert run(["label", ds, "--set", "door", "10", "0.5"], capsys)[0] == 0  # one edit does not vouch for the rest
    assert [s.stage for s in P.stale_stages(tiny_dataset)][:1] == ["labels"]
    assert run(["label", ds, "--from", str(tiny_dataset / "key_frame_value.yaml"), "--replace"], capsys)[0] == 0
    assert "labels" not in {s.stage for s in P.stale_stages(tiny_dataset)}


def test_stray_text_file_is_left_out_with_a_warning(tmp_path, capsys):
    folder = photos(tmp_path / "p", 4)
    (folder / "K.txt").write_text("camera matrix, not a photo")
    code, text = run(["frames", str(folder), str(tmp_path / "ds")], capsys)
    assert code == 0 and "K.txt" in text and "not images and were left out" in text
    assert len(list((tmp_path / "ds" / "images").glob("*.png"))) == 4
    rep = json.loads((tmp_path / "ds" / "reports" / "frames.json").read_text())
    assert any("K.txt" in w["message"] for w in rep["warnings"])


@pytest.mark.parametrize("err, says", [(errno.ENOSPC, "no space left on the device"),
                                       (errno.EROFS, "read-only"), (errno.EACCES, "permission denied")])
def test_disk_full_and_read_only_are_one_line_and_leave_no_partial_output(tmp_path, capsys, monkeypatch, err, says):
    folder = photos(tmp_path / "p", 4)
    calls = []

    def failing(path, image):
        calls.append(path)
        if len(calls) == 2:
            raise OSError(err, "simulated", str(path))
        return real(path, image)

    real = atomic.write_image
    monkeypatch.setattr(atomic, "write_image", failing)
    code, text = run(["frames", str(folder), str(tmp_path / "ds")], capsys)
    errors = [line for line in text.splitlines() if "error" in line]
    assert code == 2 and len(errors) == 1 and says in errors[0] and "frame_00001.png" in errors[0], text
    assert not (tmp_path / "ds" / ".images.partial").exists() and not (tmp_path / "ds" / "images").exists()


def test_validate_piped_into_head_exits_quietly(tmp_path):
    ds = make_tiny_dataset(tmp_path / "ds", n_frames=4)
    # thousands of problems: more output than the pipe holds once `head` has gone
    atomic.write_yaml(ds / "key_frame_value.yaml", {f"frame_{k:05d}": {"door": "x" * 200} for k in range(0, 3000)})
    proc = subprocess.run(f"'{sys.executable}' -m interreal validate '{ds}' | head -n 2", shell=True,
                          capture_output=True, text=True, timeout=120)
    assert len(proc.stdout.splitlines()) == 2
    assert "Traceback" not in proc.stderr and "BrokenPipeError" not in proc.stderr, proc.stderr


def test_validate_is_fast_on_300_frames(tmp_path, monkeypatch):
    """The cheap mode (what `livescene` runs before training) reads mask headers only and decodes no image: counted,
    not timed (a busy machine must not fail it; the speed itself is ~0.3 ms a frame)."""
    from PIL import ImageFile

    ds = make_tiny_dataset(tmp_path / "ds", n_frames=300, size=(64, 48))
    stamp(ds)
    reads = {"npy": 0, "pixels": 0}

    def counted(fn, key):
        def wrapped(*a, **k):
            reads[key] += 1
            return fn(*a, **k)
        return wrapped

    monkeypatch.setattr(np, "load", counted(np.load, "npy"))
    monkeypatch.setattr(ImageFile.ImageFile, "load", counted(ImageFile.ImageFile.load, "pixels"))
    assert D.validate(ds, check_masks=False).ok
    assert reads == {"npy": 0, "pixels": 0}, reads
    assert D.validate(ds).ok
    assert reads["npy"] >= 300 and reads["pixels"] >= 300, reads  # the full mode reads every mask and image
    _save = np.full((48, 64, 3), 0.5, np.float32)
    np.save(ds / "masks" / "00100.npy", _save)
    assert "bad-mask" in D.validate(ds, check_masks=False).kinds()  # the header check still catches a float mask


def test_rename_keeps_masks_fresh(tiny_dataset, capsys):
    kf = tiny_dataset / "keyframes"
    atomic.write_json(kf / "00000.json", {"shapes": [{"label": "door", "shape_type": "polygon",
                                                      "points": [[0, 0], [4, 0], [4, 4]]}]})
    with StageReport(tiny_dataset, "masks", inputs={"fingerprints": P.fingerprints(tiny_dataset, ["images"], kf)}):
        pass
    assert run(["label", str(tiny_dataset), "--rename", "door", "front door"], capsys)[0] == 0
    assert not [s for s in P.stale_stages(tiny_dataset) if s.stage == "masks"]
    atomic.write_json(kf / "00000.json", {"shapes": [{"label": "front door", "shape_type": "polygon",
                                                      "points": [[0, 0], [9, 0], [9, 9]]}]})
    assert [s.stage for s in P.stale_stages(tiny_dataset)] == ["masks"]


def test_rename_carries_the_measured_motion_along(tiny_dataset, capsys):
    atomic.write_json(tiny_dataset / "articulation.json", {"objects": {"door": {
        "type": "hinge", "axis": [0, 0, 1], "origin": [0, 0, 0], "range": 1.0}}})
    with StageReport(tiny_dataset, "motions", inputs={"fingerprints": P.fingerprints(tiny_dataset, P.MOTION_INPUTS)}):
        pass
    assert D.validate(tiny_dataset, check_masks=False).ok
    assert run(["label", str(tiny_dataset), "--rename", "door", "front door"], capsys)[0] == 0
    doc = json.loads((tiny_dataset / "articulation.json").read_text())
    assert list(doc["objects"]) == ["front door"] and doc["objects"]["front door"]["type"] == "hinge"
    result = D.validate(tiny_dataset, check_masks=False)
    assert result.ok, D.format_problems(result)  # neither an unknown object nor stale motions


# ------------------------------------------------------------------------------------------------ real pipeline
@pytest.fixture(scope="module")
def processed(tmp_path_factory):
    """A simulated capture through `interreal process` (frames, masks, poses, labels, motions): ~20 s."""
    from interreal.synth import SynthConfig, write_capture

    root = tmp_path_factory.mktemp("pipeline")
    cap = write_capture(SynthConfig(frames=24, width=320, height=240), root / "cap", progress=False)
    argv = ["process", str(cap / "video.mp4"), str(root / "ds"), "--target", "12",
            "--keyframes", str(cap / "annotations" / "keyframes"), "--labels", str(cap / "annotations" / "states.yaml")]
    assert cli(argv) == 0
    assert D.validate(root / "ds").ok, D.format_problems(D.validate(root / "ds"))
    return root, cap, argv


@pytest.mark.slow
def test_frames_from_another_video_make_the_dataset_stale(processed, tmp_path, capsys):
    root, cap, argv = processed
    ds = tmp_path / "ds"
    shutil.copytree(root / "ds", ds, symlinks=True)
    assert D.validate(ds).ok  # a copied dataset (new modification times) is not stale
    other = write_video(tmp_path / "other.mp4", [textured(i, 320, 240, seed=3) for i in range(24)])
    frames = [sys.executable, "-m", "interreal", "frames", str(other), str(ds), "--target", "12"]
    before = P.fingerprint(ds, "images")["content"]
    rng = random.Random(7)
    for _ in range(2):  # killed part way: accepted only while it is still the dataset it was
        proc = subprocess.Popen(frames, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            proc.wait(timeout=rng.uniform(1.0, 4.0))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if D.validate(ds).ok:
            assert P.fingerprint(ds, "images")["content"] == before
    assert cli(["frames", str(other), str(ds), "--target", "12"]) == 0
    capsys.readouterr()
    code, text = run(["validate", str(ds)], capsys)
    assert code == 1
    for stage in ("masks", "poses", "labels", "motions"):
        assert f"[stale] {ds / 'reports' / stage}.json: {stage} were" in text, text


@pytest.mark.slow
def test_masks_propagated_again_make_poses_and_motions_stale_and_process_reruns_them(processed, tmp_path, capsys):
    root, cap, argv = processed
    ds = tmp_path / "ds"
    shutil.copytree(root / "ds", ds, symlinks=True)
    kf = tmp_path / "kf"
    shutil.copytree(cap / "annotations" / "keyframes", kf)
    first = sorted(kf.glob("*.png"))[0]
    index = cv2.imread(str(first), cv2.IMREAD_UNCHANGED)
    index[: index.shape[0] // 3] = 0  # the user redraws a keyframe
    cv2.imwrite(str(first), index)
    from interreal.masks import propagate

    propagate(ds, kf, progress=False)  # as the annotation app does (same settings as `process`)
    stale = {s.stage for s in P.stale_stages(ds)}
    assert {"poses", "motions"} <= stale and "masks" not in stale, stale
    capsys.readouterr()
    new_argv = [a if a != str(cap / "annotations" / "keyframes") else str(kf) for a in argv]
    new_argv[new_argv.index(str(root / "ds"))] = str(ds)
    reports = {s: json.loads((ds / "reports" / f"{s}.json").read_text()) for s in ("frames", "masks", "motions")}
    assert cli(new_argv) == 0
    assert D.validate(ds).ok and not P.stale_stages(ds), (D.format_problems(D.validate(ds)), P.stale_stages(ds))
    steps = json.loads((ds / "reports" / "poses.json").read_text())["steps"]
    assert steps["features"]["reused"] is False  # poses really ran again ...
    after = {s: json.loads((ds / "reports" / f"{s}.json").read_text()) for s in ("frames", "masks", "motions")}
    assert after["frames"] == reports["frames"] and after["masks"] == reports["masks"]  # ... frames and masks not
    assert after["motions"]["started"] != reports["motions"]["started"] or \
        after["motions"]["inputs"]["fingerprints"] != reports["motions"]["inputs"]["fingerprints"]


@pytest.mark.slow
def test_process_killed_at_random_points_never_validates_wrong_and_resumes(processed, tmp_path):
    """`interreal process` killed (SIGKILL) at 3 random points: the dataset never validates until a run finishes,
    the next run resumes, and the finished dataset validates."""
    root, cap, argv = processed
    ds = tmp_path / "ds"
    argv = [a if a != str(root / "ds") else str(ds) for a in argv]
    cmd = [sys.executable, "-m", "interreal", *argv]
    rng = random.Random(25)
    complete = False
    for _ in range(3):
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            proc.wait(timeout=rng.uniform(0.5, 6.0))
            finished = proc.returncode == 0
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            finished = False
        err = proc.stderr.read().decode()
        assert "Traceback" not in err, err
        res = D.validate(ds)
        if finished:
            assert res.ok, D.format_problems(res)
            complete = True
            continue
        if res.ok:
            # Killed before it touched a dataset an earlier run had finished (the import alone can outlast the
            # timer on a loaded machine): accepted, and it must still be the right dataset.
            assert complete, "a run killed part way left a dataset that validates"
            assert_right(ds, root / "ds")
            continue
        # as if the stages had been run one by one (no process report): accepted only when it is the right dataset
        probe = tmp_path / "probe"
        shutil.rmtree(probe, ignore_errors=True)
        if ds.exists():
            shutil.copytree(ds, probe, symlinks=True)
            (probe / "reports" / "process.json").unlink(missing_ok=True)
            if D.validate(probe).ok:
                assert_right(probe, root / "ds")
    assert subprocess.run(cmd, capture_output=True, timeout=300).returncode == 0
    res = D.validate(ds)
    assert res.ok, D.format_problems(res)
    assert names(ds / "images") == names(root / "ds" / "images")


def assert_right(ds: Path, reference: Path) -> None:
    assert names(ds / "images") == names(reference / "images")
    assert D.read_labels(ds) == D.read_labels(reference)
    assert not P.stale_stages(ds)


def names(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def test_a_keyframe_drawn_on_another_frame_is_refused(tmp_path):
    """A LabelMe file whose embedded picture is frame 15 but which is named for frame 0 was taken as good (its true
    IoU 0.00 on every frame): refused, naming the frame it was drawn on. The same picture re-encoded passes."""
    import base64

    import cv2

    from interreal.errors import InputError
    from interreal.masks.keyframes import load_keyframes

    rng = np.random.default_rng(0)
    base = cv2.resize(rng.uniform(0, 255, (12, 16, 3)).astype(np.uint8), (64, 48), interpolation=cv2.INTER_CUBIC)
    frames = {f"{i:05d}": np.roll(base, 3 * i, axis=1) for i in range(0, 30, 3)}  # a camera panning

    def embed(img: np.ndarray) -> str:
        return base64.b64encode(cv2.imencode(".jpg", img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 92])[1]).decode()

    shapes = [{"label": "door", "shape_type": "polygon", "points": [[5, 5], [30, 5], [30, 30], [5, 30]]}]
    kf = tmp_path / "kf"
    atomic.write_json(kf / "00000.json", {"shapes": shapes, "imageData": embed(frames["00015"]),
                                          "imageWidth": 64, "imageHeight": 48})
    with pytest.raises(InputError, match=r"drawn on frame 00015 .* named for frame 00000.*rename it to 00015\.json"):
        load_keyframes(kf, list(frames), (64, 48), {0: "door"}, image_of=frames.__getitem__)
    atomic.write_json(kf / "00000.json", {"shapes": shapes, "imageData": embed(frames["00000"]),
                                          "imageWidth": 64, "imageHeight": 48})
    kfs = load_keyframes(kf, list(frames), (64, 48), {0: "door"}, image_of=frames.__getitem__)
    assert (kfs.masks["00000"] == 1).sum() > 400


def test_a_labelme_name_the_label_commands_refuse_is_refused_where_it_comes_in(tmp_path):
    """`masks` let a LabelMe label `door=left` into mapping.yaml; every label command then refused the name."""
    from interreal.errors import InputError
    from interreal.masks.keyframes import load_keyframes

    kf = tmp_path / "kf"
    atomic.write_json(kf / "00000.json", {"shapes": [{"label": "door=left", "shape_type": "polygon",
                                                      "points": [[1, 1], [9, 1], [9, 9]]}]})
    with pytest.raises(InputError, match=r"a LabelMe label in .*'door=left' contains \['='\].*rename it there"):
        load_keyframes(kf, ["00000"], (16, 12), {})


def test_polygon_problems_say_which(tmp_path):
    """A polygon wholly outside the frame was "fewer than 3 points or no area"; each case now says which."""
    from interreal.errors import InputError
    from interreal.masks.keyframes import load_keyframes

    kf = tmp_path / "kf"
    for points, message in (([[200, 200], [260, 200], [260, 260]], r"wholly outside the 16x12 frame .*another image"),
                            ([[1, 1], [9, 9]], r"has 2 point\(s\)"),
                            ([[1, 1], [5, 5], [9, 9]], r"no area")):
        atomic.write_json(kf / "00000.json", {"shapes": [{"label": "door", "shape_type": "polygon", "points": points}]})
        with pytest.raises(InputError, match=message):
            load_keyframes(kf, ["00000"], (16, 12), {0: "door"})


SLOW_IMPORT = """
import pathlib, time
pathlib.Path({flag!r}).touch()
time.sleep(60)
"""


def test_sigterm_while_a_command_loads_is_one_line(tmp_path):
    """SIGTERM in the seconds a command's modules take to import (torch, pycolmap) stops it as it does mid-work:
    one line and 143, not a silent death or a native handler's stack dump."""
    import os
    import signal

    flag = tmp_path / "importing"
    (tmp_path / "slow_command.py").write_text(SLOW_IMPORT.format(flag=str(flag)))
    code = ("import sys; from interreal.runner import run_cli; "
            "sys.exit(run_cli('interreal', {'slow': ('slow_command', 'loads for a minute')}, '', ['slow'], (ValueError,)))")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(Path(__file__).parent.parent)]))
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    for _ in range(600):
        if flag.exists() or proc.poll() is not None:
            break
        time.sleep(0.1)
    assert flag.exists(), proc.communicate(timeout=60)[1].decode()[-2000:]
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, (proc.returncode, err.decode())
    assert err.decode().strip() == "interreal: terminated (SIGTERM)", err.decode()
