"""Ingest: videos (rotation metadata, truncation), image folders (content sniffing), RAW (shared white balance)."""

from __future__ import annotations

import json
from pathlib import Path

import av
import cv2
import numpy as np
import pytest

from interreal import cli
from interreal.errors import InputError
from interreal.frames import extract_frames
from interreal.ingest import RawFolderSource, _frame_rotation, open_source, sniff
from interreal.paths import require_shared


def textured(i: int, w: int = 128, h: int = 96, seed: int = 0) -> np.ndarray:
    """A textured RGB frame that shifts with i (so frames differ, like a moving camera)."""
    rng = np.random.default_rng(seed)
    big = cv2.resize(rng.integers(0, 256, (h // 4, (w + 64) // 4, 3), dtype=np.uint8), (w + 64, h),
                     interpolation=cv2.INTER_CUBIC)
    return np.ascontiguousarray(big[:, 2 * i:2 * i + w])


def write_video(path: Path, frames: list[np.ndarray], rotation: int = 0, faststart: bool = False) -> Path:
    with av.open(str(path), "w", options={"movflags": "faststart"} if faststart else {}) as c:
        s = c.add_stream("libx264", rate=30)
        s.height, s.width = frames[0].shape[:2]
        s.pix_fmt = "yuv420p"
        s.options = {"crf": "12"}
        if rotation:
            s.set_display_rotation(rotation)
        for f in frames:
            for p in s.encode(av.VideoFrame.from_ndarray(f, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return path


def read_rgb(path: Path) -> np.ndarray:
    return cv2.imread(str(path))[..., ::-1]


# ------------------------------------------------------------------------------------------------ video
@pytest.mark.parametrize("rotation,k", [(-90, 3), (90, 1), (180, 2)])
def test_phone_rotation_metadata_gives_upright_frames(tmp_path, rotation, k):
    frames = [textured(i) for i in range(6)]
    for f in frames:
        f[:] = f.mean(axis=2, keepdims=True).astype(np.uint8)  # grey texture ...
        f[:12, :12] = (255, 0, 0)  # ... and a red marker in the stored top-left corner
    video = write_video(tmp_path / "portrait.mp4", frames, rotation=rotation)
    src = open_source(video)
    assert src.info.kind == "video" and src.info.rotation == ((rotation + 180) % 360) - 180
    out = extract_frames(video, tmp_path / "ds", every=1)
    img = read_rgb(out[0])
    want = np.rot90(frames[0], k)
    assert img.shape == want.shape  # portrait for +-90

    def diff(a, b):
        return np.abs(a.astype(int) - b.astype(int)).mean()

    others = [np.rot90(frames[0], j) for j in range(4) if j != k and np.rot90(frames[0], j).shape == img.shape]
    assert diff(img, want) < 0.5 * min(diff(img, o) for o in others)  # this rotation, not another one
    red = np.argwhere((img[..., 0].astype(int) - img[..., 1] > 100))
    red_want = np.argwhere((want[..., 0].astype(int) - want[..., 1] > 100))
    assert np.allclose(red.mean(0), red_want.mean(0), atol=1.5)


def test_legacy_rotate_tag_is_clockwise():
    class F:
        rotation = 0

    assert _frame_rotation(F(), {"rotate": "90"}) == -90
    assert _frame_rotation(F(), {}) == 0


def test_video_frames_are_named_by_source_index_and_downscaled(tmp_path):
    frames = [textured(i, 256, 192) for i in range(12)]
    video = write_video(tmp_path / "v.mp4", frames)
    out = extract_frames(video, tmp_path / "ds", every=3, long_side=128)
    idx = [int(p.stem.split("_")[1]) for p in out]
    assert len(idx) == 4 and all(3 * k <= i < 3 * (k + 1) for k, i in enumerate(idx))
    assert read_rgb(out[0]).shape == (96, 128, 3)
    rep = json.loads((tmp_path / "ds" / "reports" / "frames.json").read_text())
    assert rep["status"] == "ok" and rep["figures"]["source_frames"] == 12


def test_empty_video_is_a_clear_error(tmp_path):
    (tmp_path / "empty.mp4").write_bytes(b"")
    with pytest.raises(InputError, match="empty"):
        extract_frames(tmp_path / "empty.mp4", tmp_path / "ds")
    assert not (tmp_path / "ds" / "images").exists()


@pytest.mark.parametrize("faststart", [False, True])
def test_truncated_video_is_a_clear_error_and_nothing_is_written(tmp_path, faststart):
    video = write_video(tmp_path / "v.mp4", [textured(i) for i in range(40)], faststart=faststart)
    data = video.read_bytes()
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(data[: len(data) // 3])
    with pytest.raises(InputError, match="truncated|damaged|not a readable"):
        extract_frames(cut, tmp_path / "ds")
    assert not (tmp_path / "ds" / "images").exists()
    rep = json.loads((tmp_path / "ds" / "reports" / "frames.json").read_text())
    assert rep["status"] == "failed"
    assert cli.main(["frames", str(cut), str(tmp_path / "ds2")]) == 2


def test_black_and_textureless_videos_are_refused(tmp_path):
    black = write_video(tmp_path / "black.mp4", [np.zeros((96, 128, 3), np.uint8)] * 8)
    with pytest.raises(InputError, match="black"):
        extract_frames(black, tmp_path / "a")
    grey = write_video(tmp_path / "grey.mp4", [np.full((96, 128, 3), 128, np.uint8)] * 8)
    with pytest.raises(InputError, match="blank"):
        extract_frames(grey, tmp_path / "b")


def test_video_with_only_two_usable_frames_is_refused(tmp_path):
    frames = [textured(0), textured(1)] + [np.zeros((96, 128, 3), np.uint8)] * 6
    with pytest.raises(InputError, match="only 2 of 8 frames are usable"):
        extract_frames(write_video(tmp_path / "v.mp4", frames), tmp_path / "ds")


# ------------------------------------------------------------------------------------------------ image folders
def test_jpeg_bytes_in_png_files_are_sniffed_and_kept_in_name_order(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    frames = [textured(i) for i in range(4)]
    for i, f in enumerate(frames):
        ok, enc = cv2.imencode(".jpg", f[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
        (folder / f"IMG_{10 + i}.png").write_bytes(enc.tobytes())  # JPEG bytes, .png name
    (folder / ".DS_Store").write_bytes(b"\0\0junk")  # hidden files are ignored
    assert sniff(folder / "IMG_10.png") == "jpeg"
    out = extract_frames(folder, tmp_path / "ds")
    assert [p.name for p in out] == [f"frame_{i:05d}.png" for i in range(4)]
    assert sniff(out[0]) == "png"
    for p, f in zip(out, frames):
        assert np.abs(read_rgb(p).mean(axis=2) - f.mean(axis=2)).mean() < 4  # same image (JPEG subsamples chroma)
    rep = json.loads((tmp_path / "ds" / "reports" / "frames.json").read_text())
    assert rep["figures"]["source_names"]["frame_00002"] == "IMG_12.png"


def test_real_photos_folder(tmp_path):
    fox = require_shared("fox", "images")
    folder = tmp_path / "fox"
    folder.mkdir()
    for p in sorted(fox.iterdir())[:3]:
        (folder / p.name).symlink_to(p)
    out = extract_frames(folder, tmp_path / "ds", long_side=400)
    assert len(out) == 3 and read_rgb(out[0]).shape == (400, 225, 3)  # 1080x1920 portrait -> long side 400


def test_mixed_sizes_are_refused(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i}.png"), textured(i))
    cv2.imwrite(str(folder / "3.png"), textured(3, 100, 80))
    with pytest.raises(InputError, match="mixes image sizes"):
        extract_frames(folder, tmp_path / "ds")


def test_non_image_files_are_refused(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i}.png"), textured(i))
    (folder / "notes.txt").write_text("not an image")
    (folder / "4.png").write_bytes(b"garbage bytes that are not a png")
    # a damaged file named like an image is refused; a stray note (notes.txt) alone is only left out with a warning
    with pytest.raises(InputError, match="not images: 4.png;"):
        extract_frames(folder, tmp_path / "ds")


def test_two_images_are_too_few(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    for i in range(2):
        cv2.imwrite(str(folder / f"{i}.png"), textured(i))
    with pytest.raises(InputError, match="at least 3"):
        extract_frames(folder, tmp_path / "ds")


def test_failed_rerun_keeps_the_previous_images(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    for i in range(4):
        cv2.imwrite(str(folder / f"{i}.png"), textured(i))
    extract_frames(folder, tmp_path / "ds")
    (folder / "x.png").write_text("oops")
    with pytest.raises(InputError):
        extract_frames(folder, tmp_path / "ds")
    assert len(list((tmp_path / "ds" / "images").glob("*.png"))) == 4


# ------------------------------------------------------------------------------------------------ RAW
def test_raw_dng_with_one_white_balance_and_exposure(tmp_path):
    dng = require_shared("raw", "colorchart.dng")
    folder = tmp_path / "raw"
    folder.mkdir()
    for i in range(3):
        (folder / f"IMG_{i}.DNG").symlink_to(dng)
    src = open_source(folder)
    assert isinstance(src, RawFolderSource) and (src.info.width, src.info.height) == (1734, 1156)
    assert src.wb[1] == 1.0 and src.gain > 0
    out = extract_frames(folder, tmp_path / "ds", long_side=800)
    imgs = [read_rgb(p) for p in out]
    assert imgs[0].shape == (533, 800, 3)
    assert all(np.array_equal(imgs[0], im) for im in imgs[1:])  # same developing for every frame: no flicker
    lum = imgs[0].mean(axis=2)
    assert 40 < lum.mean() < 200 and np.percentile(lum, 99) > 200  # exposed, not black, highlights near white
    rep = json.loads((tmp_path / "ds" / "reports" / "frames.json").read_text())
    assert rep["inputs"]["source_info"]["extra"]["exposure_gain"] == pytest.approx(src.gain)


def test_unsupported_raw_is_refused(tmp_path):
    folder = tmp_path / "raw"
    folder.mkdir()
    for i in range(3):
        (folder / f"IMG_{i}.NEF").write_bytes(b"II*\x00" + bytes(200))
    with pytest.raises(InputError, match="unsupported or damaged RAW"):
        extract_frames(folder, tmp_path / "ds")


def test_single_non_video_file_is_refused(tmp_path):
    p = tmp_path / "a.txt"
    p.write_text("hello")
    with pytest.raises(InputError, match="not a video"):
        open_source(p)
    with pytest.raises(InputError, match="does not exist"):
        open_source(tmp_path / "missing.mp4")


def test_heic_photos_are_read_upright(tmp_path):
    """An iPhone's default: HEIC photos were called "not images: remove them". Read with pillow-heif, a portrait
    shot (EXIF orientation 6) comes out upright at its displayed size; a damaged one is named."""
    from PIL import Image

    folder = tmp_path / "photos"
    folder.mkdir()
    for i in range(4):
        img = textured(i)  # 96 x 128, stored landscape
        exif = Image.Exif()
        exif[274] = 6  # shot in portrait: displayed rotated a quarter turn
        Image.fromarray(img).save(folder / f"IMG_{i:04d}.HEIC", format="HEIF", exif=exif.tobytes(), quality=95)
    ds = tmp_path / "ds"
    paths = extract_frames(folder, ds)
    assert len(paths) == 4
    out = cv2.imread(str(paths[0]))
    assert out.shape[:2] == (128, 96)  # upright: portrait
    info = json.loads((ds / "reports" / "frames.json").read_text())["inputs"]["source_info"]
    assert info["extra"]["formats"] == ["heif"]
    (folder / "IMG_0001.HEIC").write_bytes((folder / "IMG_0001.HEIC").read_bytes()[:200])
    with pytest.raises(InputError, match="IMG_0001.HEIC"):
        extract_frames(folder, tmp_path / "ds2")
