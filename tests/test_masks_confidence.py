"""The masks stage's honest confidence: lost stretches reported as such, warnings only where masks fail."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np

from interreal import atomic
from interreal.conventions import fid_of_index, frame_name
from interreal.masks import health as H
from interreal.masks import propagate
from interreal.masks.stage import make_config
from interreal.paths import require_shared

cv2.setNumThreads(2)


def disk_sequence(n: int = 24, hidden: range = range(0), w: int = 128, h: int = 96) -> tuple[list, list]:
    """A slowly panning textured wall and a red disk moving right; the disk is painted over (gone) on `hidden`."""
    rng = np.random.default_rng(5)
    wall = cv2.GaussianBlur(rng.integers(0, 255, (h, w + n, 3), dtype=np.uint8), (0, 0), 2.0)
    wall = cv2.normalize(wall, None, 60, 200, cv2.NORM_MINMAX)
    tex = cv2.GaussianBlur(rng.integers(0, 255, (h, w), dtype=np.uint8), (0, 0), 1.5)
    images, truths = [], []
    for t in range(n):
        img = wall[:, t:t + w].copy()
        lab = np.zeros((h, w), np.uint8)
        if t not in hidden:
            cv2.circle(lab, (30 + 2 * t, 48), 15, 1, -1)
            img[lab > 0] = np.stack([200 + tex // 8, 30 + tex // 6, 30 + tex // 6], -1)[lab > 0]
        images.append(img)
        truths.append(lab)
    return images, truths


def run(root: Path, images: list, truths: list, keys: list[int], name: str = "disk", **track) -> dict:
    """The masks stage on these frames and keyframe truths; `track`: TrackConfig fields to change."""
    ds = root / "ds"
    for i, img in enumerate(images):
        atomic.write_image(ds / "images" / f"{frame_name(i)}.png", img)
    kdir = root / "keys"
    for k in keys:
        atomic.write_image(kdir / f"{fid_of_index(k)}.png", truths[k])
    atomic.write_yaml(kdir / "mapping.yaml", {0: name})
    config = dataclasses.replace(make_config(), **track) if track else None
    propagate(ds, kdir, preview="none", progress=False, config=config)
    return json.loads((ds / "reports" / "masks.json").read_text())


def lost_frames(rep: dict, name: str) -> set[int]:
    return {int(f) for f, s in rep["figures"]["states"][name].items() if s == "lost"}


def test_vanished_object_is_reported_lost_for_that_stretch(tmp_path):
    hidden = range(8, 14)
    images, truths = disk_sequence(hidden=hidden)
    rep = run(tmp_path, images, truths, [0, 23])
    assert lost_frames(rep, "disk") == set(hidden), rep["figures"]["states"]["disk"]
    lost = [w for w in rep["warnings"] if w["cause"] == "object-lost"]
    assert len(lost) == 1 and "object lost at frames 8-13" in lost[0]["message"], rep["warnings"]
    conf = rep["figures"]["confidence"]["disk"]
    assert max(conf[fid_of_index(t)] for t in hidden) < 0.3  # a lost frame is not reported as fairly sure
    assert rep["figures"]["health"]["disk"]["lost"] == "8-13"
    assert set(rep["figures"]["suggested_frames"]) & {fid_of_index(t) for t in hidden}  # a keyframe is asked for there


def test_clean_sequence_gets_no_warning(tmp_path):
    images, truths = disk_sequence()
    rep = run(tmp_path, images, truths, [0, 23])
    assert rep["warnings"] == [], rep["warnings"]
    assert not rep["figures"]["states"]["disk"]
    assert rep["figures"]["confidence_mean"]["disk"] > 0.8


def test_annotated_absence_is_not_a_loss(tmp_path):
    """A keyframe where the object is absent on purpose says 'not in view here': no error, no lost stretch."""
    hidden = range(8, 14)
    images, truths = disk_sequence(hidden=hidden)
    rep = run(tmp_path, images, truths, [0, 10, 23])
    assert rep["status"] == "ok" and not lost_frames(rep, "disk")


def test_jump_and_loss_rules():
    area = np.array([[0.1], [0.1], [0.01], [0.0], [0.1], [0.3]])
    ref = np.full_like(area, 0.1)
    cen = np.zeros((6, 1, 2))
    feats = H.build_features(area, ref, np.ones_like(area), np.ones_like(area), np.ones_like(area),
                             np.full_like(area, np.nan), cen, np.zeros(6), np.full_like(area, 0.3))
    hl = H.assess(feats, area, ref, np.ones_like(area, bool), np.array([True, False, False, False, False, False]))
    states = [H.STATES[s] for s in hl.state[:, 0]]
    assert states[2:4] == ["lost", "lost"] and states[5] == "jumped", states
    assert hl.predicted[3, 0] == 0.0 and hl.stretches["lost"][0] == [(2, 3)]


def test_health_fit_holds_each_cue_to_its_sign():
    """J made of area and edges only, with trust a noisy copy of the area's error: an unconstrained fit gives trust a
    negative weight (less flow agreement, better mask), the signed fit leaves it out and recovers the rest."""
    rng = np.random.default_rng(0)
    n = 30
    f = np.zeros((n, len(H.FEATURES)))
    f[:, 0] = rng.uniform(0.5, 1.0, n)                         # area
    f[:, 3] = rng.uniform(0.8, 1.2, n)                         # edges
    f[:, 2] = rng.uniform(0.2, 1.0, n)                         # thin (no effect)
    j = 0.6 * f[:, 0] + 0.2 * f[:, 3] + 0.05
    f[:, 1] = 1.5 - f[:, 0] + 0.05 * rng.normal(size=n)        # trust: falls where the area rises
    f[:, 4], f[:, 5] = 0.5, 1.0                                # agree, two_sided: constant
    j = j - 0.1 * (f[:, 1] - f[:, 1].mean())                   # ... and the truth leans on it the wrong way
    free = np.linalg.lstsq(np.c_[f[:, :len(H.MODEL)], np.ones(n)], j, rcond=None)[0]
    assert free[1] < -0.05                                     # the wrong-signed rule an unconstrained fit learns
    w = H.fit(f, j, ridge=0.0)
    assert w[1] == 0.0 and w[2] <= 0.0 and np.all(w[[0, 3]] > 0), w
    assert abs(w[3] - 0.2) < 0.05 and w[0] > 0.6, w             # area takes trust's share, edges are recovered
    pred = H.predict(f, w)
    assert np.abs(pred - j).mean() < 0.02, np.abs(pred - j).mean()


def test_fine_share_counts_the_parts_an_opening_removes():
    m = np.zeros((96, 128), np.uint8)
    cv2.circle(m, (40, 60), 20, 1, -1)
    assert H.fine_share(m, 2) < 0.01  # a disk's outline is not a fine part
    disk = m.copy()
    m[2:45, 39:41] = 1  # a 2 px line up from it (a kite's string)
    line = int(m.sum() - disk.sum())
    assert abs(H.fine_share(m, 2) - line / m.sum()) < 0.02 and abs(H.fine_share(m, 1) - line / m.sum()) < 0.02
    m[2:45, 38:43] = 1  # 5 px wide: kept by an opening of radius 1 and 2, not by 3
    assert H.fine_share(m, 1) < 0.01 and H.fine_share(m, 2) < 0.01 and H.fine_share(m, 3) > 0.1
    assert H.fine_share(np.zeros((8, 8), bool), 2) == 0.0
    # about two work-size pixels, in full-size pixels
    assert H.fine_radius(854, 480) == 2 and H.fine_radius(640, 640) == 1 and H.fine_radius(1920, 480) == 4


def test_an_object_made_of_lines_is_warned_about_them(tmp_path):
    """kite-surf: a fifth of the kite-surfer's mask is the kite's lines (1-2 px at this size), which no flow
    follows; the report gives the share and warns with the J it caps. blackswan's outline is not fine: no warning
    (`test_davis_lost_object_is_warned_and_an_easy_sequence_is_not`)."""
    images, truths = davis_clip("kite-surf", 10)
    rep = run(tmp_path, images, truths, [0, 9], "kite-surfer")
    fine = rep["figures"]["fine_parts"]
    assert fine["width_px"] == 3 and 0.15 < fine["share"]["kite-surfer"] < 0.25, fine  # 0.19 measured
    assert fine["keyframe"]["kite-surfer"] in ("00000", "00009")
    warn = [w for w in rep["warnings"] if w["cause"] == "masks-fine-parts"]
    assert len(warn) == 1 and "narrower than 3 px" in warn[0]["message"], rep["warnings"]
    cap = 1 - fine["share"]["kite-surfer"]
    assert f"J {cap:.2f} at most" in warn[0]["message"]
    masks = [np.load(tmp_path / "ds" / "masks" / f"{fid_of_index(i)}.npy")[..., 0] for i in range(1, 9)]
    j = [float((m & (t == 1)).sum() / (m | (t == 1)).sum()) for m, t in zip(masks, truths[1:9])]
    assert np.mean(j) < cap + 0.03, j  # the lines are indeed lost: J is held under the cap


def davis_clip(name: str, n: int, size=(427, 240)) -> tuple[list, list]:
    src = require_shared("davis2016", name)
    jpgs = sorted((src / "images").glob("*.jpg"))[:n]
    gts = sorted((src / "masks").glob("*.png"))[:n]
    images = [cv2.resize(cv2.imread(str(p))[..., ::-1], size, interpolation=cv2.INTER_AREA) for p in jpgs]
    truths = [(cv2.resize(cv2.imread(str(p), 0), size, interpolation=cv2.INTER_NEAREST) > 127).astype(np.uint8)
              for p in gts]
    return images, truths


def test_davis_lost_object_is_warned_and_an_easy_sequence_is_not(tmp_path):
    """drift-straight, first frame only: the car's mask collapses near the end (propagation alone left it empty on
    the last six frames, J 0); re-detection finds the car again by its keyframe's colours, the report names those
    frames, and the sequence is still warned about (J about 0.45). blackswan: J about 0.9, nothing to warn about."""
    images, truths = davis_clip("drift-straight", 50)
    rep = run(tmp_path / "drift", images, truths, [0], "car")
    causes = {w["cause"] for w in rep["warnings"]}
    assert "masks-unreliable" in causes, rep["warnings"]
    found = [int(f) for f in rep["figures"]["redetected"]["car"]]
    assert found and min(found) >= 35, found
    assert any("found again" in w["message"] for w in rep["warnings"]), rep["warnings"]
    # where the mask collapsed is the first frame to annotate (the stage could not hold the car there)
    assert 35 <= int(rep["figures"]["suggested_frames"][0]) <= min(found), rep["figures"]["suggested_frames"]
    masks = [np.load(tmp_path / "drift" / "ds" / "masks" / f"{fid_of_index(i)}.npy")[..., 0] for i in range(44, 50)]
    assert min(m.sum() for m in masks) > 0  # no empty mask where the car is in view
    j = [float((m & (t == 1)).sum() / (m | (t == 1)).sum()) for m, t in zip(masks, truths[44:50])]
    assert np.mean(j) > 0.25 and min(j) > 0.1, j  # J 0 on all six without re-detection
    assert rep["figures"]["confidence_mean"]["car"] < 0.7
    images, truths = davis_clip("blackswan", 20)
    rep = run(tmp_path / "swan", images, truths, [0], "swan")
    assert rep["warnings"] == [] and not rep["figures"]["states"]["swan"], rep["warnings"]
    assert rep["figures"]["confidence_mean"]["swan"] > 0.8


def test_davis_look_alike_on_the_background_is_not_taken_for_the_lost_object(tmp_path):
    """motocross-jump, first frame only, full size: the bike flies away from the camera. With the growth's colour
    test by the whole keyframe's histograms (`TrackConfig.local_colour` off) its mask shrinks and counts as collapsed
    at frame 32, and a patch of the dirt track has the muddy bike's colours. Taken for the bike (as it was before the
    motion check), the mask then stays on the track and frames 32-39 score J 0.13; refused because it pans with the
    background while what is left of the mask moves with the bike, they score 0.66. The report names the refused
    frames, the warning says why, and the collapse is the first frame to annotate. With the keyframe's colours near
    each pixel (the default) the mask holds the bike: nothing collapses, nothing is taken, J 0.79 there."""
    images, truths = davis_clip("motocross-jump", 40, size=(854, 480))

    def j(root: Path) -> list[float]:
        masks = [np.load(root / "ds" / "masks" / f"{fid_of_index(i)}.npy")[..., 0] for i in range(32, 40)]
        return [float((m & (t == 1)).sum() / max((m | (t == 1)).sum(), 1)) for m, t in zip(masks, truths[32:40])]

    rep = run(tmp_path / "moto", images, truths, [0], "bike", local_colour=False)
    fig = rep["figures"]
    refused = [int(f) for f in fig["redetect_refused"]["bike"]]
    assert refused and 30 <= min(refused) <= 34, refused
    assert not any(30 <= int(f) <= 34 for f in fig["redetected"]["bike"]), fig["redetected"]
    assert np.mean(j(tmp_path / "moto")) > 0.5, j(tmp_path / "moto")
    assert any("moved with the background" in w["message"] for w in rep["warnings"]), rep["warnings"]
    # where the mask collapsed (the chain's first frame under the collapse size, at or before the first refusal)
    # is the first frame to annotate, as for a collapse that was found again
    assert 28 <= int(fig["suggested_frames"][0]) <= min(refused), fig["suggested_frames"]
    rep = run(tmp_path / "local", images, truths, [0], "bike")
    assert not any(30 <= int(f) <= 39 for f in rep["figures"]["redetected"]["bike"]), rep["figures"]["redetected"]
    assert np.mean(j(tmp_path / "local")) > 0.7, j(tmp_path / "local")


def approaching_disk(n: int = 24, w: int = 480, h: int = 360, r0: int = 50) -> tuple[list, list]:
    """A textured red disk that comes closer: its radius doubles (4x the area) on a still wall."""
    rng = np.random.default_rng(7)
    wall = cv2.normalize(cv2.GaussianBlur(rng.integers(0, 255, (h, w, 3), dtype=np.uint8), (0, 0), 2.0), None, 60,
                         200, cv2.NORM_MINMAX)
    tex = cv2.GaussianBlur(rng.integers(0, 255, (h, w), dtype=np.uint8), (0, 0), 1.5)
    cx, cy = w // 2, h // 2
    images, truths = [], []
    for t in range(n):
        s = 1 + t / (n - 1)
        zoom = cv2.warpAffine(tex, np.float32([[s, 0, cx * (1 - s)], [0, s, cy * (1 - s)]]), (w, h))  # texture too
        lab = np.zeros((h, w), np.uint8)
        cv2.circle(lab, (cx, cy), round(r0 * s), 1, -1)
        img = wall.copy()
        img[lab > 0] = np.stack([200 + zoom // 8, 30 + zoom // 6, 30 + zoom // 6], -1)[lab > 0]
        images.append(img)
        truths.append(lab)
    return images, truths


def test_object_that_comes_closer_is_not_called_unreliable(tmp_path):
    """First frame only: the mask follows a disk that grows to 4x its keyframe area. The area cue compares the mask
    with the area the disk's own motion predicts, not with the keyframe's, so the right mask is trusted."""
    images, truths = approaching_disk()
    rep = run(tmp_path, images, truths, [0])
    ds = tmp_path / "ds"
    ious = []
    for t in range(1, len(images)):
        m = np.load(ds / "masks" / f"{fid_of_index(t)}.npy")[..., 0]
        g = truths[t] > 0
        ious.append((m & g).sum() / (m | g).sum())
    assert min(ious) > 0.9, np.round(ious, 3)
    area = np.array(rep["figures"]["cues"]["disk"]["area"])[1:]
    assert area[-5:].min() > 0.7, area                   # 0.77-0.8 (flow underestimates a zoom); keyframe: 0.27-0.3
    assert not [w for w in rep["warnings"] if w["cause"] == "masks-unreliable"], rep["warnings"]
    assert rep["figures"]["confidence_mean"]["disk"] > H.WARN_J    # 0.78 (0.60 against the keyframe alone)
