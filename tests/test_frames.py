"""Frame selection: sharpest per window, motion-aware windows, near-duplicates, forced keep-frames, the CLI."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from interreal import cli
from interreal.errors import InputError
from interreal.frames import FrameStats, SelectConfig, analyse, extract_frames, select, skipped_lines
from interreal.ingest import open_source

from test_ingest import textured, write_video


def stats(n: int, sharp=None, motion=None, usable=None) -> FrameStats:
    sharp = np.full(n, 100.0) if sharp is None else np.asarray(sharp, float)
    motion = np.full(n, 0.01) if motion is None else np.asarray(motion, float)
    corners = np.full(n, 500.0)
    if usable is not None:
        corners[~np.asarray(usable)] = 0
    return FrameStats(sharpness=sharp, corners=corners, brightness=np.full(n, 120.0), motion=motion)


def test_sharpest_frame_of_each_window_is_taken():
    sharp = np.full(30, 50.0)
    sharp[[4, 13, 27]] = 500.0
    chosen, _ = select(range(30), stats(30, sharp), SelectConfig(every=10))
    assert chosen == [4, 13, 27]


def test_target_count_is_met_and_windows_follow_motion():
    motion = np.r_[np.zeros(50), np.full(50, 0.02)]  # still for 50 frames, then moving
    chosen, _ = select(range(100), stats(100, motion=motion), SelectConfig(target=20))
    assert len(chosen) <= 20
    assert sum(c >= 50 for c in chosen) >= 14  # most frames where the camera moves
    assert len(chosen) >= 15


def test_target_equal_to_source_takes_every_moving_frame():
    chosen, _ = select(range(40), stats(40), SelectConfig(target=40))
    assert chosen == list(range(40))


def test_near_duplicates_are_dropped_when_the_camera_stands_still():
    motion = np.r_[np.full(20, 0.02), np.zeros(40), np.full(20, 0.02)]
    chosen, info = select(range(80), stats(80, motion=motion), SelectConfig(every=4, time_weight=0.25))
    still = [c for c in chosen if 20 < c < 60]
    assert len(still) <= 1 and info["near_duplicates"]


def test_keep_frames_always_survive_and_unusable_frames_never_do():
    usable = np.ones(30, bool)
    usable[10:20] = False
    chosen, info = select(range(30), stats(30, usable=usable), SelectConfig(every=5), keep=[15, 29])
    assert 15 in chosen and 29 in chosen  # annotated frames are forced in, even an unusable one
    assert not any(10 <= c < 20 and c != 15 for c in chosen)
    assert info["unusable"] == list(range(10, 20))


def test_keep_frame_outside_the_source_is_an_error():
    with pytest.raises(InputError, match="only 10 frames"):
        select(range(10), stats(10), SelectConfig(every=2), keep=[12])


def test_image_folders_keep_everything_without_a_target():
    chosen, _ = select(range(6), stats(6, motion=np.zeros(6)), SelectConfig(keep_all=True))
    assert chosen == list(range(6))


def test_blurred_video_frames_are_skipped(tmp_path):
    frames = [textured(i, 160, 120) for i in range(16)]
    blurred = [1, 2, 5, 6, 9, 10, 13, 14]
    for i in blurred:
        frames[i] = cv2.GaussianBlur(frames[i], (0, 0), 3)
    video = write_video(tmp_path / "v.mp4", frames)
    idx, st = analyse(open_source(video), progress=False)
    assert st.sharpness[blurred].max() < st.sharpness[[0, 3, 4, 7]].min()
    assert st.motion[0] == 0 and np.all(st.motion[1:] > 0)
    out = extract_frames(video, tmp_path / "ds", every=4)
    assert not {int(p.stem[-5:]) for p in out} & set(blurred)


def test_rerun_replaces_the_selection_and_the_cli_reports(tmp_path, capsys):
    video = write_video(tmp_path / "v.mp4", [textured(i) for i in range(12)])
    ds = tmp_path / "ds"
    extract_frames(video, ds, every=1)
    assert len(list((ds / "images").glob("frame_*.png"))) == 12
    assert cli.main(["frames", str(video), str(ds), "--every", "4", "--keep", "5"]) == 0
    names = sorted(p.name for p in (ds / "images").glob("*.png"))
    assert len(names) == 4 and "frame_00005.png" in names  # stale frames are gone
    rep = json.loads((ds / "reports" / "frames.json").read_text())
    assert rep["status"] == "ok" and rep["settings"]["keep"] == [5] and 5 in rep["figures"]["selected_indices"]
    assert "4 frames" in capsys.readouterr().out
    assert not list(ds.glob(".images*"))  # no staging folders left


def test_cli_help_has_examples(capsys):
    with pytest.raises(SystemExit):
        cli.main(["frames", "--help"])
    assert "examples:" in capsys.readouterr().out


def test_unchanged_rerun_reuses_the_frames(tmp_path, capsys):
    video = write_video(tmp_path / "v.mp4", [textured(i) for i in range(12)])
    ds = tmp_path / "ds"
    first = extract_frames(video, ds, every=2)
    stamps = [p.stat().st_mtime_ns for p in first]
    assert extract_frames(video, ds, every=2) == first and [p.stat().st_mtime_ns for p in first] == stamps
    assert "up to date" in capsys.readouterr().out
    first[0].unlink()  # a missing image: the stage runs again
    assert extract_frames(video, ds, every=2) == first and first[0].exists()
    assert len(extract_frames(video, ds, every=3)) != len(first)  # another setting runs again


def test_frames_flags_come_from_the_config_fields():
    """`interreal frames` flags are generated from `FramesConfig` (--target / --every exclusive, --keep a list)."""
    import argparse
    from dataclasses import asdict

    from interreal.frames import FramesConfig, add_arguments, frames_options

    p = argparse.ArgumentParser()
    add_arguments(p)
    flags = {s for a in p._actions for s in a.option_strings} - {"-h", "--help"}
    assert flags == {"--target", "--every", "--long-side", "--keep"}
    assert frames_options(p.parse_args(["in.mp4", "ds"])) == asdict(FramesConfig())
    opts = frames_options(p.parse_args(["in.mp4", "ds", "--every", "3", "--long-side", "640", "--keep", "4", "9"]))
    assert opts == {"target": None, "every": 3, "long_side": 640, "keep": [4, 9]}
    with pytest.raises(SystemExit):
        p.parse_args(["in.mp4", "ds", "--every", "3", "--target", "20"])
    with pytest.raises(InputError, match="unknown frames options"):
        extract_frames("in.mp4", "ds", long_sides=640)


def test_plain_videos_keep_their_frames_and_skips_say_why():
    """A plain dishwasher on a wood floor: every frame has few corners (12-18) and soft edges, none is blank; 21
    such frames were skipped as "black, blank or textureless" (the only ones at state 0). Now few corners is no
    reason (a plain door filling the view has 2, and shows the part); a black, a blank and a far blurrier frame are
    skipped, each named with its reason, a run at the start called out."""
    n = 40
    rng = np.random.default_rng(0)
    plain = FrameStats(sharpness=rng.uniform(6, 9, n), corners=rng.integers(12, 19, n).astype(float),
                       brightness=np.full(n, 110.0), motion=np.full(n, 0.01), contrast=np.full(n, 25.0))
    assert plain.usable.all()
    plain.brightness[[0, 1]] = 3.0  # a lens cap at the start
    plain.contrast[10] = 0.5  # blank
    plain.sharpness[20] = 0.3  # far blurrier than the rest
    plain.corners[30:33] = [0.0, 1.0, 2.0]  # the plain door filling the view: kept
    plain.contrast[35] = 1.0  # blank, but kept for an annotation
    reasons = plain.reasons()
    assert [i for i in range(n) if reasons[i]] == [0, 1, 10, 20, 35]
    assert (reasons[0], reasons[10], reasons[20]) == ("black", "blank", "blurred")
    lines = skipped_lines(list(range(n)), plain, keep=[35])
    assert lines == ["2 black frame(s) skipped: 0-1 (at the start of the video)",
                     "1 blank frame(s) skipped: 10 (no texture at all)",
                     "1 blurred frame(s) skipped: 20 (far blurrier than the video's other frames)"]
