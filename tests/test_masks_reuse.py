"""`interreal masks` again after a keyframe change: only the stretches it touched are made again, and the result is
the one a run from scratch gives, bit for bit (`interreal.masks.reuse`); the auto transient layer is kept too."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from interreal.conventions import UNANNOTATED, fid_of_index
from interreal.layout import MASKS_CACHE_DIR
from interreal.masks import propagate
from interreal.masks.reuse import DONE_FILE, Reuse, Segment, chain_segments
from interreal.transients.auto import AutoLayer, load_layer, save_layer
from interreal.transients.hands import HandTrack

from test_masks import make_ds, toy_sequence, write_keys

NAMES = ["red disk", "blue square"]
TIMING = {"fps", "cpu_fps", "transients", "reused_frames"}  # the run's own figures (wall clock, what it kept)


def _masks(ds: Path, n: int) -> list[np.ndarray]:
    return [np.load(ds / "masks" / f"{fid_of_index(i)}.npy") for i in range(n)]


def _steps(ds: Path) -> dict:
    return json.loads((ds / "reports" / "masks.json").read_text())["steps"]["propagate"]


@pytest.fixture(scope="module")
def rounds(tmp_path_factory):
    """A first round with keyframes 4 and 12, a second with 20 added (the stretches before 4 and between 4 and 12
    are the first round's), and the second round's keyframes from scratch in a copy of the dataset."""
    root = tmp_path_factory.mktemp("reuse")
    images, truths = toy_sequence(n=24)
    ds = make_ds(root, images)
    fresh = root / "fresh"
    shutil.copytree(ds, fresh)
    first = propagate(ds, write_keys(root / "k1", truths, [4, 12], NAMES), preview="both", progress=False)
    second = propagate(ds, write_keys(root / "k2", truths, [4, 12, 20], NAMES), preview="both", progress=False)
    steps = _steps(ds)
    scratch = propagate(fresh, root / "k2", preview="both", progress=False, reuse=False)
    return ds, fresh, root, first, second, steps, scratch


def test_a_new_keyframe_makes_only_the_gap_it_splits(rounds):
    ds, *_, steps, _ = rounds
    # frames 0-3 (before keyframe 4) and 5-11 (between 4 and 12) are the first round's; 13-23 are made again,
    # from keyframes 12 and 20: flow pairs 12..22 only
    assert steps["reused_frames"] == 4 + 7 == rounds[4]["reused_frames"]
    assert steps["flow_pairs"] == 22 - 12 + 1


def test_the_reused_run_is_the_run_from_scratch(rounds):
    ds, fresh, _, _, second, _, scratch = rounds
    assert all(np.array_equal(a, b) for a, b in zip(_masks(ds, 24), _masks(fresh, 24), strict=True))
    differ = [k for k in set(second) | set(scratch) if k not in TIMING and second.get(k) != scratch.get(k)]
    assert not differ, differ
    assert _steps(fresh)["reused_frames"] == 0 and not (fresh / "cache").exists()  # --no-reuse keeps nothing
    # the sfm masks and the previews come from the same labels
    for name in ("sfm_masks/frame_00002.png.png", "sfm_masks/frame_00009.png.png"):
        assert (ds / name).read_bytes() == (fresh / name).read_bytes()


def test_only_this_runs_stretches_stay_in_the_cache(rounds):
    ds, *_ = rounds
    kept = sorted(p.name for p in (ds / MASKS_CACHE_DIR).iterdir())
    assert len(kept) == 4  # before 4, gaps 4-12 and 12-20, after 20
    assert all((ds / MASKS_CACHE_DIR / k / DONE_FILE).is_file() for k in kept)


def test_a_stretch_cut_short_is_made_again(rounds, tmp_path):
    ds, fresh, root, *_ = rounds
    again = tmp_path / "ds"
    shutil.copytree(ds, again)
    shutil.rmtree(again / "reports")
    done = sorted((again / MASKS_CACHE_DIR).glob(f"*/{DONE_FILE}"))
    biggest = max(done, key=lambda p: len(list(p.parent.glob("*.png"))))
    biggest.unlink()  # as a crash before the stretch was finished leaves it
    propagate(again, root / "k2", preview="none", progress=False)
    assert _steps(again)["reused_frames"] == 24 - 3 - len(list(biggest.parent.glob("*.png")))
    assert all(np.array_equal(a, b) for a, b in zip(_masks(again, 24), _masks(fresh, 24), strict=True))


def test_a_cache_that_cannot_be_written_is_one_warning(tmp_path, monkeypatch):
    """A full or read-only disk under DS/cache: the run's masks are written as ever, one warning says the next run
    makes every frame again, and it does (nothing half-kept is taken)."""
    from interreal.masks import reuse

    images, truths = toy_sequence(n=12)
    ds = make_ds(tmp_path, images)
    keys = write_keys(tmp_path / "k", truths, [0, 11], NAMES)

    write = reuse.atomic.write_bytes

    def full(path, data):
        if "cache" in Path(path).parts:
            raise OSError(28, "No space left on device")
        write(path, data)

    monkeypatch.setattr(reuse.atomic, "write_bytes", full)
    fig = propagate(ds, keys, preview="none", progress=False, transients="off")
    assert len(list((ds / "masks").glob("*.npy"))) == 12 and fig["reused_frames"] == 0
    rep = json.loads((ds / "reports" / "masks.json").read_text())
    assert [w["cause"] for w in rep["warnings"]].count("cache-not-kept") == 1
    monkeypatch.undo()
    shutil.rmtree(ds / "reports")
    assert propagate(ds, keys, preview="none", progress=False, transients="off")["reused_frames"] == 0


def test_stretches_of_a_run():
    assert chain_segments([0, 5, 9], 10) == [Segment("gap", 0, 5), Segment("gap", 5, 9)]  # no frame before or after
    segs = chain_segments([3, 4, 7], 10)
    assert segs == [Segment("before", 0, 3), Segment("gap", 3, 4), Segment("gap", 4, 7), Segment("after", 7, 9)]
    frames = [t for s in segs for t in s.frames]
    assert sorted(frames + [3, 4, 7]) == list(range(10))  # every frame once: keyframes are their annotation
    assert [list(s.pairs) for s in segs] == [[0, 1, 2], [3], [4, 5, 6], [7, 8]]


def test_a_keyframe_with_unannotated_pixels_is_never_stored(tmp_path):
    images = [tmp_path / f"frame_{i:05d}.png" for i in range(8)]
    for p in images:
        p.write_bytes(b"x")
    full, partial = np.zeros((4, 4), np.uint8), np.zeros((4, 4), np.uint8)
    partial[0, 0] = UNANNOTATED
    r = Reuse(tmp_path / "cache", images, {2: full, 5: partial}, {})
    assert [r.key[s] is None for s in r.segments] == [False, True, True]  # before 2 / gap 2-5 / after 5
    assert not r.found and r.reused_frames == 0


def test_the_auto_layer_is_kept_for_the_same_frames(tmp_path):
    m = np.zeros((6, 10), bool)
    m[1:4, 2:7] = True
    hands = [np.zeros((0, 21, 2)), np.arange(42, dtype=float).reshape(1, 21, 2) / 3, np.zeros((0, 21, 2))]
    layer = AutoLayer({1: m, 2: m}, (10, 6), HandTrack(hands, ["", "tracked", ""], {"tracking": 0.5}), [1],
                      {"grow": 0.1}, carried=[2])
    path = tmp_path / "layer.npz"
    save_layer(path, "k1", layer)
    back = load_layer(path, "k1")
    assert back is not None and sorted(back.masks) == [1, 2] and np.array_equal(back.masks[1], m)
    assert back.work_size == (10, 6) and back.leaked == [1] and back.seconds == {"grow": 0.1}
    assert back.carried == [2]  # frames the masks stage carried the layer to (`masks.carry`)
    assert back.track.how == layer.track.how and back.track.found_share() == pytest.approx(1 / 3)
    assert all(np.array_equal(a, b) for a, b in zip(back.track.hands, hands, strict=True))
    assert load_layer(path, "another key") is None  # other frames (or other code): made again
    path.write_bytes(b"not a layer")
    assert load_layer(path, "k1") is None
    assert load_layer(tmp_path / "missing.npz", "k1") is None
