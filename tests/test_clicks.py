"""Click to segment (`interreal.masks.clicks`) on small synthetic images: what one click, a negative click, a prior and
bad clicks give. Fixed seeds; figures, not timings (the benchmark measures the time: `bench_masks.py --clicks`)."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from interreal.errors import InputError
from interreal.masks.clicks import Click, as_clicks, segment

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "recipes"))
from bench_clicks import click_frame, next_click  # noqa: E402  (the benchmark's simulated user)

W, H = 160, 120
RED, RED2 = (210, 40, 40), (200, 50, 45)  # the object, and a look-alike of a near shade


def textured(seed: int = 0) -> np.ndarray:
    """A background of 8 px tiles of random colours with noise: edges everywhere, none of them the object's."""
    rng = np.random.default_rng(seed)
    tiles = cv2.resize(rng.integers(60, 200, (H // 8, W // 8, 3), dtype=np.uint8), (W, H), interpolation=cv2.INTER_NEAREST)
    return np.clip(tiles.astype(int) + rng.integers(-15, 16, (H, W, 3)), 0, 255).astype(np.uint8)


def scene(seed: int = 0, distractor: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image, object, distractor): a red ellipse on the texture; with a distractor, a red box of a near shade that
    touches it (what a first click wrongly takes too)."""
    img = textured(seed)
    obj = np.zeros((H, W), np.uint8)
    cv2.ellipse(obj, (60, 60), (30, 22), 0, 0, 360, 1, -1)
    dis = np.zeros((H, W), np.uint8)
    if distractor:
        cv2.rectangle(dis, (88, 48), (130, 72), 1, -1)
    img[obj > 0], img[dis > 0] = RED, RED2
    noise = np.random.default_rng(seed + 100).integers(-8, 9, (H, W, 3))
    return np.clip(img.astype(int) + noise, 0, 255).astype(np.uint8), obj > 0, dis > 0


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_one_positive_click_finds_the_object(seed):
    img, obj, _ = scene(seed)
    mask = segment(img, [(60, 60, True)])
    assert mask.shape == (H, W) and mask.dtype == bool
    assert iou(mask, obj) >= 0.8


def test_a_negative_click_removes_a_wrongly_included_region():
    img, obj, dis = scene(0, distractor=True)
    first = segment(img, [(60, 60, True)])
    assert (first & dis).sum() > 0.3 * dis.sum()  # the look-alike touching box is taken by the first click ...
    second = segment(img, [(60, 60, True), (115, 60, False)], prior=first)
    assert (second & dis).sum() < 0.05 * dis.sum()  # ... and the negative click on it takes it out
    assert iou(second, obj) >= 0.9


def test_negative_clicks_alone_give_an_empty_mask():
    img, _, _ = scene(0)
    assert not segment(img, [(60, 60, False)]).any()
    assert not segment(img, [(60, 60, False), (10, 10, False)], prior=np.zeros((H, W), bool)).any()


def test_a_prior_is_refined_where_the_clicks_are_and_kept_elsewhere():
    img, obj, _ = scene(1)
    prior = obj.copy()
    prior[:, 75:] = False  # the propagated mask lost the right part of the object
    mask = segment(img, [(82, 60, True)], prior=prior)
    assert iou(mask, obj) >= 0.85 and iou(prior, obj) < 0.8
    assert mask[obj & prior].mean() > 0.95  # what the prior had right stays


def test_a_negative_click_on_a_prior_removes_only_its_region():
    img, obj, dis = scene(2, distractor=True)
    prior = obj | dis
    mask = segment(img, [(115, 60, False)], prior=prior)
    assert (mask & dis).sum() < 0.05 * dis.sum() and iou(mask, obj) >= 0.85


def test_full_size_and_work_size_agree():
    img, obj, _ = scene(0)
    big = cv2.resize(img, (W * 4, H * 4), interpolation=cv2.INTER_NEAREST)
    big_obj = cv2.resize(obj.astype(np.uint8), (W * 4, H * 4), interpolation=cv2.INTER_NEAREST) > 0
    assert iou(segment(big, [(240, 240, True)]), big_obj) >= 0.8  # cut at the work size, brought back to 640x480


@pytest.mark.parametrize("clicks, words", [
    ([(160, 10, True)], "outside the 160x120 image"),
    ([(-1, 10, True)], "outside"),
    ([(10, float("nan"), True)], "outside"),
    ([(10, 10)], "[x, y, positive]"),
    ([(10, 10, "yes")], "true/false"),
    ([("a", 10, True)], "numbers"),
])
def test_bad_clicks_are_input_errors_naming_them(clicks, words):
    img, _, _ = scene(0)
    with pytest.raises(InputError, match=None) as err:
        segment(img, clicks)
    assert words in str(err.value)


def test_bad_image_and_prior_are_input_errors():
    img, _, _ = scene(0)
    with pytest.raises(InputError, match="uint8 RGB"):
        segment(img[..., 0], [(1, 1, True)])
    with pytest.raises(InputError, match="prior mask is 10x10"):
        segment(img, [(1, 1, True)], prior=np.zeros((10, 10), bool))


def test_clicks_from_objects_and_triples_are_the_same():
    assert as_clicks([(1, 2, True), Click(3.0, 4.0, False)]) == [Click(1.0, 2.0, True), Click(3.0, 4.0, False)]


def test_the_simulated_user_clicks_the_centre_of_the_largest_error():
    gt = np.zeros((40, 60), bool)
    gt[5:35, 15:45] = True
    pred = np.zeros_like(gt)
    c = next_click(pred, gt)
    assert c.positive and abs(c.x - 29.5) <= 2 and abs(c.y - 19.5) <= 2
    pred = gt.copy()
    pred[0:6, :] = True  # a false-positive band along the top border: its centre is inside it, not on the border
    c = next_click(pred, gt)
    assert not c.positive and 0 <= c.y < 6
    assert next_click(gt, gt) is None


def test_the_simulated_user_reaches_iou_90_on_the_synthetic_scene_in_few_clicks():
    img, obj, _ = scene(0, distractor=True)
    r = click_frame(img, obj, max_clicks=10, stop_at=0.9)
    assert r["noc90"] <= 3 and r["ious"][-1] >= 0.9


@pytest.mark.parametrize("size", [(2, 2), (3, 7), (9, 9), (1, 40)])
def test_tiny_and_flat_images_give_a_mask_not_an_error(size):
    img = np.full(size + (3,), 128, np.uint8)
    if min(size) < 2:
        with pytest.raises(InputError, match="uint8 RGB"):
            segment(img, [(0, 0, True)])
        return
    mask = segment(img, [(0, 0, True)])
    assert mask.shape == size and mask[0, 0]
    assert not segment(img, [(0, 0, True), (size[1] - 1, size[0] - 1, False)])[-1, -1]
