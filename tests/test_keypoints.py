"""Track refinement: Lucas-Kanade on tiled patches finds sub-pixel shifts without bias."""

from __future__ import annotations

import numpy as np

from interreal.keypoints import align_points


def _waves(shift=(0.0, 0.0), size=(240, 320), seed: int = 0) -> np.ndarray:
    """A sum of random plane waves sampled at pixel centres, moved by `shift` px: an exact sub-pixel translation
    (resampling an image would add its own interpolation error)."""
    rng = np.random.default_rng(seed)
    freq = rng.uniform(0.05, 0.6, (40, 2)) * rng.choice([-1, 1], (40, 2))
    phase, amp = rng.uniform(0, 2 * np.pi, 40), rng.uniform(0.5, 1.0, 40)
    y, x = np.mgrid[0:size[0], 0:size[1]].astype(float)
    x, y = x + 0.5 - shift[0], y + 0.5 - shift[1]
    v = sum(a * np.sin(f[0] * x + f[1] * y + p) for f, p, a in zip(freq, phase, amp))
    return np.clip(128 + v * (100 / np.abs(v).max()), 0, 255).round().astype(np.uint8)


def test_align_points_recovers_a_subpixel_shift():
    shift = np.array([0.37, -0.61])
    ref, moved = _waves(), _waves(shift)
    g = np.stack(np.meshgrid(np.arange(20.5, 300, 23), np.arange(20.5, 220, 19)), -1).reshape(-1, 2)
    guess = g + shift + np.random.default_rng(1).uniform(-0.7, 0.7, g.shape)  # SIFT-like error
    out, ok = align_points(ref, moved, g, guess)
    assert ok.mean() > 0.95
    err = out[ok] - (g[ok] + shift)
    dist = np.linalg.norm(err, axis=1)
    assert np.median(dist) < 0.06 and np.percentile(dist, 95) < 0.2, (np.median(dist), np.percentile(dist, 95))
    assert np.abs(err.mean(0)).max() < 0.01  # no bias: the pixel-centre convention holds both ways
    assert np.median(np.linalg.norm(guess - (g + shift), axis=1)) > 0.3  # it started far from the answer


def test_points_too_close_to_the_border_are_not_aligned():
    ref = _waves()
    xy = np.array([[2.5, 120.5], [160.5, 120.5], [318.0, 5.0]])
    _, ok = align_points(ref, ref, xy, xy + 0.3)
    assert ok.tolist() == [False, True, False]
