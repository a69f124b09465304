"""Re-detection (`interreal.masks.redetect`): an object its chain lost is found again from its keyframe's look."""

from __future__ import annotations

import cv2
import numpy as np

from interreal.masks.appearance import AppearanceConfig, quantize
from interreal.masks.redetect import RedetectConfig, Redetector
from interreal.masks.soft import anchor_soft
from interreal.masks.track import Propagator, TrackConfig

cv2.setNumThreads(2)

W, H = 160, 120


def background(rng: np.random.Generator) -> np.ndarray:
    """A grey-green textured scene (no orange in it)."""
    bg = cv2.GaussianBlur(rng.integers(0, 255, (H, W, 3), dtype=np.uint8), (0, 0), 2.0)
    bg = cv2.normalize(bg, None, 70, 150, cv2.NORM_MINMAX)
    bg[..., 0] = (bg[..., 0] * 0.6).astype(np.uint8)  # little red: the object's colour is its own
    return bg


def paint_disk(img: np.ndarray, centre: tuple[int, int], r: int, tex: np.ndarray) -> np.ndarray:
    mask = np.zeros((H, W), np.uint8)
    cv2.circle(mask, centre, r, 1, -1)
    obj = np.stack([210 + tex // 10, 110 + tex // 8, 30 + tex // 10], -1)
    img[mask > 0] = obj[mask > 0]
    return mask


def hidden_and_moved(n: int = 22, seed: int = 0) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """An orange disk moves right; at frame 8 a grey panel hides it for six frames; when the panel goes the disk
    is somewhere else (lower right) and moves on from there. Returns images and truth (index maps)."""
    rng = np.random.default_rng(seed)
    bg = background(rng)
    tex = cv2.GaussianBlur(rng.integers(0, 255, (H, W), dtype=np.uint8), (0, 0), 1.0)
    panel = cv2.normalize(cv2.GaussianBlur(rng.integers(0, 255, (H, W, 3), dtype=np.uint8), (0, 0), 3.0),
                          None, 90, 130, cv2.NORM_MINMAX)
    images, truths = [], []
    for t in range(n):
        img = bg.copy()
        if t < 8:
            truth = paint_disk(img, (30 + 2 * t, 40), 14, tex)
        elif t < 14:
            truth = np.zeros((H, W), np.uint8)
            img[10:80, 5:90] = panel[10:80, 5:90]  # the panel, with the disk behind it
        else:
            truth = paint_disk(img, (100 + 2 * (t - 14), 85), 14, tex)
        images.append(img)
        truths.append(truth)
    return images, truths


def iou(a: np.ndarray, b: np.ndarray) -> float:
    u = (a | b).sum()
    return float((a & b).sum() / u) if u else 1.0


def run(images: list[np.ndarray], truth0: np.ndarray, redetect: bool) -> tuple[list[np.ndarray], Propagator]:
    cfg = TrackConfig(work_long_side=0, redetect=RedetectConfig(enabled=redetect))
    prop = Propagator(lambda i: images[i], len(images), (W, H), 1, cfg)
    out = {r.pos: r.labels for r in prop.run({0: truth0})}
    return [out[i] for i in range(len(images))], prop


def test_object_hidden_then_elsewhere_is_found_again():
    images, truths = hidden_and_moved()
    labels, prop = run(images, truths[0], redetect=True)
    after = [iou(labels[t] == 1, truths[t] == 1) for t in range(15, len(images))]
    assert min(after) > 0.75, after
    found = [e for e in prop.redetections if e.obj == 0]
    assert found and 14 <= found[0].pos <= 16, [(e.pos, e.how) for e in prop.redetections]
    assert 8 <= found[0].since <= found[0].pos  # the collapse began behind the panel
    # without re-detection the chain never gets it back: the feature is what finds it
    plain, _ = run(images, truths[0], redetect=False)
    assert max(iou(plain[t] == 1, truths[t] == 1) for t in range(15, len(images))) < 0.2


def test_no_search_while_the_mask_holds():
    """A mask that keeps its size is left as it is (re-detection costs nothing and changes nothing)."""
    images, truths = hidden_and_moved()
    labels, prop = run(images[:8], truths[0], redetect=True)
    assert prop.redetections == []
    assert min(iou(labels[t] == 1, truths[t] == 1) for t in range(1, 8)) > 0.8


def test_a_larger_region_of_the_same_colour_is_not_taken_for_the_object():
    """A lost object is not 're-found' in a region of its colour far larger than it was (a wall of the same paint):
    the candidate's size must stay within `RedetectConfig.size` of the object's size before the loss."""
    rng = np.random.default_rng(1)
    bg = background(rng)
    tex = cv2.GaussianBlur(rng.integers(0, 255, (H, W), dtype=np.uint8), (0, 0), 1.0)
    key = bg.copy()
    truth = paint_disk(key, (40, 40), 12, tex)
    cfg = RedetectConfig()
    soft, known = anchor_soft(truth, 1, (W, H))
    det = Redetector(key, soft, known, cfg, AppearanceConfig(), 1)
    later = bg.copy()
    wall = np.zeros((H, W), np.uint8)
    wall[20:110, 60:150] = 1  # 8100 px of the object's orange: 18x the disk
    big = np.stack([210 + tex // 10, 110 + tex // 8, 30 + tex // 10], -1)
    later[wall > 0] = big[wall > 0]
    empty = np.zeros_like(soft)
    empty[..., -1] = 1.0
    out = det.check(empty, later, quantize(later, AppearanceConfig().bins), 5)
    assert det.events == []
    assert np.allclose(out, empty)
    # the same colour at the object's own size is found (the control: the wall was refused for its size only)
    again = bg.copy()
    where = paint_disk(again, (110, 80), 12, tex)
    out = det.check(empty, again, quantize(again, AppearanceConfig().bins), 6)
    assert len(det.events) == 1 and det.events[0].pos == 6
    assert iou(out[..., 0] > 0.5, where > 0) > 0.7


def test_features_pick_the_object_among_look_alikes():
    """Two regions of the object's colours and size: colour alone cannot choose (no re-detection from colour),
    ORB features matched back to the keyframe's object can: the one with the object's own texture is taken."""
    w, h = 320, 240
    rng = np.random.default_rng(2)
    bg = cv2.normalize(cv2.GaussianBlur(rng.integers(0, 255, (h, w, 3), dtype=np.uint8), (0, 0), 3.0),
                       None, 60, 140, cv2.NORM_MINMAX)
    bg[..., 0] = (bg[..., 0] * 0.5).astype(np.uint8)

    def pattern(seed: int) -> np.ndarray:
        """A sharp two-tone texture (orange and dark brown) of 8 px cells: corners ORB can describe."""
        cells = np.random.default_rng(seed).integers(0, 2, (10, 10)).astype(np.uint8)
        cells = cv2.resize(cells, (80, 80), interpolation=cv2.INTER_NEAREST)
        return np.where(cells[..., None] > 0, np.array([230, 130, 20], np.uint8), np.array([90, 40, 10], np.uint8))

    own, other = pattern(10), pattern(11)
    key = bg.copy()
    key[40:120, 30:110] = own
    truth = np.zeros((h, w), np.uint8)
    truth[40:120, 30:110] = 1
    soft, known = anchor_soft(truth, 1, (w, h))
    det = Redetector(key, soft, known, RedetectConfig(), AppearanceConfig(), 1)
    later = bg.copy()
    later[130:210, 40:120] = other      # the look-alike, nearer to where the object was
    later[120:200, 210:290] = own       # the object, moved
    empty = np.zeros_like(soft)
    empty[..., -1] = 1.0
    out = det.check(empty, later, quantize(later, AppearanceConfig().bins), 9)
    assert det.key_desc[0] is not None and len(det.key_desc[0]) >= RedetectConfig().min_matches
    assert [e.how for e in det.events] == ["features"]
    found = out[..., 0] > 0.5
    where = np.zeros((h, w), bool)
    where[120:200, 210:290] = True
    assert iou(found, where) > 0.8, iou(found, where)


def panning_pair(object_shift: int, seed: int = 3) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Two frames of a textured scene panning 3 px left, with an orange textured disk moving `object_shift` px right
    and an orange look-alike patch painted on the background (it pans with it). Returns the frames, the disk's mask
    and the patch's mask in the second frame."""
    w, h = 2 * W, 2 * H
    rng = np.random.default_rng(seed)
    scene = cv2.normalize(cv2.GaussianBlur(rng.integers(0, 255, (h, w + 40, 3), dtype=np.uint8), (0, 0), 2.0),
                          None, 60, 150, cv2.NORM_MINMAX)
    scene[..., 0] = (scene[..., 0] * 0.6).astype(np.uint8)
    tex = cv2.GaussianBlur(rng.integers(0, 255, (h, w + 40), dtype=np.uint8), (0, 0), 1.5)
    orange = np.stack([200 + tex // 8, 100 + tex // 5, 20 + tex // 8], -1).astype(np.uint8)
    patch = np.zeros(scene.shape[:2], np.uint8)
    cv2.circle(patch, (250, 170), 26, 1, -1)
    scene[patch > 0] = orange[patch > 0]
    frames, disk = [], None
    for t in range(2):
        img = np.ascontiguousarray(scene[:, 3 * t:3 * t + w])
        disk = np.zeros((h, w), np.uint8)
        cv2.circle(disk, (90 + object_shift * t, 70), 30, 1, -1)
        shifted = np.roll(orange, object_shift * t, axis=1)[:, :w]  # the disk's own texture moves with it
        img[disk > 0] = shifted[disk > 0]
        frames.append(img)
    return frames, disk > 0, patch[:, 3:3 + w] > 0


def test_a_colour_find_that_moves_with_the_background_is_not_the_object():
    """The flow tells a look-alike on the background from the object: where what is left of the object moves
    against the background, a region found by colour that pans with the background is refused
    (`Propagator._moves_apart`), and the rest of the object itself is not."""
    frames, disk, patch = panning_pair(object_shift=5)
    h, w = disk.shape
    prop = Propagator(lambda i: frames[i], 2, (w, h), 1, TrackConfig(work_long_side=0))
    ys, xs = np.nonzero(disk)
    remnant = disk & (xs.mean() > np.arange(w))[None, :]  # the disk's left half is what the chain kept
    assert not prop._moves_apart(1, 0, patch, remnant)
    assert prop._moves_apart(1, 0, disk, remnant)
    # an object that moves as the background does gives no evidence either way: the find is not refused
    still, disk2, patch2 = panning_pair(object_shift=-3)
    prop2 = Propagator(lambda i: still[i], 2, (w, h), 1, TrackConfig(work_long_side=0))
    assert prop2._moves_apart(1, 0, patch2, disk2 & (xs.mean() > np.arange(w))[None, :])


def test_a_refused_colour_find_leaves_the_map_and_is_recorded():
    """`Redetector.check` puts back no region that `moves_apart` refuses; it records the refusal and keeps searching."""
    rng = np.random.default_rng(1)
    bg = background(rng)
    tex = cv2.GaussianBlur(rng.integers(0, 255, (H, W), dtype=np.uint8), (0, 0), 1.0)
    key = bg.copy()
    truth = paint_disk(key, (40, 40), 12, tex)
    soft, known = anchor_soft(truth, 1, (W, H))
    det = Redetector(key, soft, known, RedetectConfig(), AppearanceConfig(), 1)
    later = bg.copy()
    paint_disk(later, (110, 80), 12, tex)
    remnant = np.zeros_like(soft)
    remnant[..., -1] = 1.0
    remnant[38:41, 38:41] = (1.0, 0.0)  # a speck of the object is left where it was
    bins = quantize(later, AppearanceConfig().bins)
    out = det.check(remnant, later, bins, 5, lambda region, rest: False)
    assert det.events == [] and [(e.pos, e.obj, e.how) for e in det.refusals] == [(5, 0, "refused")]
    assert np.allclose(out, remnant)
    out = det.check(remnant, later, bins, 6, lambda region, rest: True)
    assert len(det.events) == 1 and det.events[0].how == "colour"
