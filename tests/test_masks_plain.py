"""A plain, untextured part keeps its mask between two keyframes (issue 50: the masks are what a plain door's
motion is measured from).

A plain door's inside gives the flow nothing to follow: its forward-backward check fails there, and the fill of
untrusted pixels from their trusted neighbours pulled the inside toward its rim and the background beyond it, step
by step, until the mask was a sliver. Plain pixels now keep the flow's own label (`TrackConfig.fill_plain`); what
has texture is filled as before.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from interreal.conventions import fid_of_index
from interreal.masks import propagate
from interreal.masks.soft import fill_untrusted
from interreal.masks.stage import make_config
from interreal.masks.workframes import FrameCache, texture
from interreal.synth import Capture, SynthConfig, write_capture

sys.path.insert(0, str(Path(__file__).parent))
from test_masks import make_ds  # noqa: E402

cv2.setNumThreads(2)

HARD = {"furniture": "plain", "exposure_drift": 0.2, "noise": 3.0, "occluder": 0.3, "arm": True}


@pytest.mark.parametrize("sigma", [1.0, 4.0])
def test_texture_is_judged_against_the_image_own_noise_floor(sigma: float):
    rng = np.random.default_rng(0)
    pattern = cv2.GaussianBlur(rng.integers(0, 255, (120, 160, 3), dtype=np.uint8), (0, 0), 2.0)
    pattern = cv2.normalize(pattern, None, 60, 200, cv2.NORM_MINMAX).astype(np.float64)
    img = np.full((120, 160, 3), 140.0)
    img[:, 80:] = pattern[:, 80:]  # plain left half, patterned right half
    img = np.clip(img + rng.normal(0, sigma, img.shape), 0, 255).astype(np.uint8)
    t = texture(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32))
    assert t.shape == (120, 160) and t.dtype == np.float32
    assert t[:, :70].mean() < 0.05, t[:, :70].mean()   # a noisy plain surface is plain at either noise level
    assert t[:, 90:].mean() > 0.8, t[:, 90:].mean()


def test_the_fill_leaves_a_plain_inside_to_the_flow():
    soft = np.zeros((60, 60, 2), np.float32)
    soft[..., 1] = 1.0
    soft[10:50, 10:50] = (1.0, 0.0)        # the object, as the flow carried it
    trust = np.ones((60, 60), np.float32)
    trust[13:47, 13:47] = 0.0              # its inside untrusted (plain), its rim and the background trusted
    filled = fill_untrusted(soft, trust, radius=7)
    kept = fill_untrusted(soft, trust, radius=7, keep=np.ones((60, 60), np.float32))
    assert (filled[..., 0] > 0.5).sum() < 0.85 * 1600      # filled from the rim's neighbourhood: eaten
    assert np.allclose(kept, soft)                          # plain: the flow's label stays
    sub = fill_untrusted(soft, trust, radius=7, keep=np.zeros((60, 60), np.float32))
    assert np.allclose(sub, filled, atol=1e-5)              # textured, or another colour: the fill as before


def test_a_plain_pixel_keeps_the_flow_label_only_where_the_flow_brings_its_hue():
    """A plain door that brightens as it turns to the light keeps the flow's label; a plain wall uncovered where a red
    coat was is the fill's, as every textured pixel is."""
    rng = np.random.default_rng(1)
    pattern = cv2.normalize(cv2.GaussianBlur(rng.integers(0, 255, (90, 120, 3), dtype=np.uint8), (0, 0), 2.0),
                            None, 60, 200, cv2.NORM_MINMAX).astype(np.float64)
    src, dst = pattern.copy(), pattern.copy()
    src[:, :40] = (150, 150, 150)
    dst[:, :40] = (200, 200, 200)     # the door, a third brighter
    src[:, 40:80] = (200, 60, 60)     # a red coat ...
    dst[:, 40:80] = (150, 150, 150)   # ... gone: the plain wall behind it
    frames = [np.clip(f + rng.normal(0, 2.0, f.shape), 0, 255).astype(np.uint8) for f in (src, dst)]
    cache = FrameCache(lambda i: frames[i], (120, 90))
    kept = cache.flow_kept(0, 1, lambda a: a)  # the flow: nothing moved
    assert kept[5:-5, 5:35].mean() > 0.9, kept[5:-5, 5:35].mean()
    assert kept[5:-5, 45:75].mean() < 0.05, kept[5:-5, 45:75].mean()
    assert kept[5:-5, 85:115].mean() < 0.1, kept[5:-5, 85:115].mean()


def _door_j(cap: Capture, ds: Path, keys: list[int], n: int) -> float:
    vals = []
    for i in range(n):
        if i in keys:
            continue
        truth = cap.instance(i) == 1
        mask = np.load(ds / "masks" / f"{fid_of_index(i)}.npy")[..., 0]
        union = (truth | mask).sum()
        if union:
            vals.append((truth & mask).sum() / union)
    return float(np.mean(vals))


@pytest.mark.parametrize("seed", [1, 2])
def test_a_plain_door_keeps_its_mask_between_two_keyframes(tmp_path: Path, seed: int):
    """Simulated hard captures (plain painted door, exposure drift, noise, an arm): the door's mask J over the frames
    between its two keyframes, with plain pixels left to the flow and without (measured: seed 1 0.23 -> 0.39,
    seed 2 0.32 -> 0.44; seeds 3-6 +0.09 to +0.25)."""
    cap_dir = write_capture(SynthConfig(frames=48, width=320, height=240, seed=seed, **HARD), tmp_path / "cap",
                            progress=False)
    cap = Capture.open(cap_dir)
    images = [img for _, img in cap.frames()]
    ds = make_ds(tmp_path, images)
    kdir = cap_dir / "annotations" / "keyframes"
    keys = sorted(int(p.stem) for p in kdir.glob("*.png"))
    j = {}
    for plain in (True, False):
        cfg = dataclasses.replace(make_config(), fill_plain=plain)
        propagate(ds, kdir, progress=False, preview="none", reuse=False, transients="off", config=cfg)
        j[plain] = _door_j(cap, ds, keys, len(images))
    assert j[True] >= j[False] + 0.08, j
    assert j[True] >= 0.36, j
