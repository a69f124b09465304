"""The auto transient layer carried by flow into the frames where the hand model found no hand (`masks.carry`): an
arm the model loses for a stretch is still in the layer there, an arm that leaves the view does not stay behind on
the background, and a stretch longer than the carry's reach stays empty in the middle."""

from __future__ import annotations

import numpy as np

from interreal.masks.carry import CARRY_FRAMES, carry_layer, stretches
from interreal.transients import auto as A
from interreal.transients import hands as Hd

H, W = 120, 160


def background(seed: int = 0) -> np.ndarray:
    """A textured static scene (flow needs texture to follow the camera-free background)."""
    rng = np.random.default_rng(seed)
    small = rng.integers(40, 200, (H // 8, W // 8, 3)).astype(np.uint8)
    return np.repeat(np.repeat(small, 8, 0), 8, 1)


def arm(x: float) -> np.ndarray:
    """(H, W) bool: a sleeve from the right edge to a hand at column x, 24 px tall (it moves left and right)."""
    m = np.zeros((H, W), bool)
    x0 = int(round(x))
    m[50:74, max(0, x0):] = True
    return m


def video(xs: list[float]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Frames of a green sleeve over the background at hand columns xs, and the sleeve's truth per frame."""
    bg = background()
    frames, truth = [], []
    for x in xs:
        m = arm(x)
        img = bg.copy()
        img[m] = (40, 170, 60)
        frames.append(img)
        truth.append(m)
    return frames, truth


def layer_of(truth: list[np.ndarray], found: set[int]) -> A.AutoLayer:
    """The layer as `propose` leaves it where the hand model found a hand on `found` only (exact masks there)."""
    n = len(truth)
    track = Hd.HandTrack([np.zeros((int(p in found), 21, 2)) for p in range(n)],
                         ["tracked" if p in found else "" for p in range(n)])
    return A.AutoLayer({p: truth[p].copy() for p in found}, (W, H), track, [], {})


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


def test_stretches_are_the_runs_without_a_layer():
    found = np.array([True, False, False, True, False, True, True, False])
    assert stretches(found) == [(1, 2), (4, 4), (7, 7)]
    assert stretches(np.zeros(3, bool)) == [(0, 2)]
    assert stretches(np.ones(3, bool)) == []


def test_an_arm_lost_for_a_stretch_is_carried_through_it_from_both_sides():
    xs = [60 + 3 * t for t in range(11)]  # the hand moves right, 3 px a frame
    frames, truth = video(xs)
    clock = iter(np.arange(0.0, 100.0, 0.5))
    layer = carry_layer(layer_of(truth, {0, 10}), lambda p: frames[p], len(frames), clock=lambda: next(clock))
    assert layer.carried == list(range(1, 10))
    for p in range(1, 10):
        assert iou(layer.masks[p], truth[p]) > 0.85, p
        assert (layer.masks[p] & ~truth[p]).sum() < 0.01 * (~truth[p]).sum(), p  # the static scene is not taken
    assert layer.seconds["carry"] == 0.5


def test_an_arm_that_leaves_the_view_is_not_left_behind_on_the_background():
    xs = [100 + 12 * t for t in range(10)]  # gone over the right edge from frame 5
    frames, truth = video(xs)
    layer = carry_layer(layer_of(truth, {0}), lambda p: frames[p], len(frames))
    for p in range(1, 10):
        got = layer.masks.get(p, np.zeros((H, W), bool))
        assert (got & ~truth[p]).sum() < 0.01 * (~truth[p]).sum(), p
    assert all(p not in layer.masks for p in range(5, 10))


def test_the_middle_of_a_stretch_longer_than_the_carry_stays_empty():
    n = 2 * CARRY_FRAMES + 6
    frames, truth = video([80.0] * n)  # a still arm: only the reach limits the carry
    layer = carry_layer(layer_of(truth, {0, n - 1}), lambda p: frames[p], n)
    assert layer.carried == [p for p in range(1, n - 1) if min(p, n - 1 - p) <= CARRY_FRAMES]
    assert all(iou(layer.masks[p], truth[p]) > 0.95 for p in layer.carried)
