"""Rigid part motions: the fit from a part's per-frame poses, the file, and the trainer's rest-frame warp."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from interreal.dataset import Articulation, DatasetError, known_states, read_articulation, write_articulation
from interreal.motions import PartViews, fit_motion, part_pairs
from livescene.articulation import PartMotions, carve_hull


def _views(motion: Articulation, states: np.ndarray, scale: float, seed: int, rot_noise_deg: float = 0.0,
           outliers: int = 0) -> PartViews:
    """What `part_views` gives for a part moving by `motion`: its reconstruction (scale `scale`, placed at a random
    rest pose) seen from cameras on a circle."""
    rng = np.random.default_rng(seed)
    r0 = Rotation.random(random_state=seed).as_matrix()
    b0 = rng.normal(size=3)
    rot, u, centre = [], [], []
    for i, s in enumerate(states):
        r, t = motion.pose(float(s))
        noise = Rotation.from_rotvec(np.radians(rot_noise_deg) * rng.normal(size=3)).as_matrix()
        if i < outliers:  # a misregistered frame: wrong pose altogether
            noise = Rotation.random(random_state=seed + 100 + i).as_matrix()
        c = np.array([3 * np.cos(i / 7), 1.0, 3 * np.sin(i / 7)])
        rot.append(noise @ r @ r0)
        u.append((r @ b0 + t - c) / scale)
        centre.append(c)
    return PartViews(np.arange(len(states)), np.asarray(rot), np.asarray(u), np.asarray(centre))


def _line_distance(p: np.ndarray, origin: np.ndarray, axis: np.ndarray) -> float:
    d = p - origin
    return float(np.linalg.norm(d - (d @ axis) * axis))


@pytest.mark.parametrize("noise,outliers", [(0.0, 0), (0.3, 3)])
def test_fit_motion_recovers_a_hinge(noise, outliers):
    axis = np.array([0.1, 0.98, -0.15])
    axis /= np.linalg.norm(axis)
    truth = Articulation("hinge", axis, np.array([0.4, -0.2, 1.1]), 1.6)
    rng = np.random.default_rng(1)
    states = np.clip(np.concatenate([np.zeros(10), np.linspace(0, 1, 30), np.full(10, 1.0), rng.uniform(0, 1, 20)]),
                     0, 1)
    known = np.zeros(len(states), bool)
    known[::4] = True
    pv = _views(truth, states, scale=0.37, seed=3, rot_noise_deg=noise, outliers=outliers)
    fit, extra = fit_motion(pv, states, known)
    assert fit.kind == "hinge"
    assert np.degrees(np.arccos(min(1.0, abs(float(fit.axis @ axis))))) < 1.0 + 2 * noise
    assert float(fit.axis @ axis) > 0  # right-hand sense: the range is positive
    assert abs(fit.range - truth.range) < 0.02 + 0.05 * noise
    assert _line_distance(truth.origin, fit.origin, fit.axis) < 0.01 + 0.05 * noise
    assert abs(extra["scale"] - 0.37) < 0.01 + 0.05 * noise
    # the fitted motion moves a rest point where the truth does
    p = np.array([0.9, 0.3, 1.4])
    for s in (0.25, 0.75):
        r, t = fit.pose(s)
        rt, tt = truth.pose(s)
        assert np.linalg.norm((r @ p + t) - (rt @ p + tt)) < 0.02 + 0.1 * noise


def test_fit_motion_recovers_a_slide():
    axis = np.array([0.0, 0.2, 1.0])
    axis /= np.linalg.norm(axis)
    truth = Articulation("slide", axis, np.zeros(3), 0.45)
    states = np.concatenate([np.zeros(8), np.linspace(0, 1, 20), np.full(8, 1.0)])
    known = np.zeros(len(states), bool)
    known[::3] = True
    fit, extra = fit_motion(_views(truth, states, scale=2.0, seed=5), states, known)
    assert fit.kind == "slide"
    assert float(fit.axis @ axis) > 0.999
    assert abs(fit.range - 0.45) < 1e-3
    assert abs(extra["scale"] - 2.0) < 1e-2


def _slide_case(seed: int, wild: int) -> tuple[Articulation, np.ndarray, np.ndarray, PartViews]:
    """A drawer: 1 deg of rotation noise per frame; `wild` frames registered flipped by ~90 deg and a stretch whose
    rotation drifts to 10 deg (what a nearly planar part's reconstruction gives with an unlucky mapper seed)."""
    truth = Articulation("slide", np.array([0.6, 0.0, 0.8]), np.zeros(3), 0.3)
    states = np.concatenate([np.zeros(20), np.linspace(0, 1, 30), np.full(20, 1.0), np.linspace(1, 0, 20)])
    known = np.zeros(len(states), bool)
    known[::3] = True
    pv = _views(truth, states, scale=0.5, seed=seed, rot_noise_deg=1.0)
    rng = np.random.default_rng(seed)
    for i in rng.choice(np.flatnonzero(known), wild, replace=False):
        axis = rng.normal(size=3)
        pv.rot[i] = Rotation.from_rotvec(np.radians(91) * axis / np.linalg.norm(axis)).as_matrix() @ pv.rot[i]
    for j, i in enumerate(range(75, 85)):  # a drifting stretch while it closes
        pv.rot[i] = Rotation.from_rotvec(np.radians(j + 1.0) * np.array([0, 1.0, 0])).as_matrix() @ pv.rot[i]
    return truth, states, known, pv


@pytest.mark.parametrize("wild", [1, 3])
def test_fit_motion_keeps_a_slide_whose_reconstruction_has_wild_frames(wild):
    """One frame flipped by ~90 deg must neither set the hinge axis nor spoil the slide (it did: RMSE 0.8 from a
    single frame, the slide dropped); frames that turn away from the part's usual orientation are left out."""
    truth, states, known, pv = _slide_case(seed=2, wild=wild)
    fit, extra = fit_motion(pv, states, known)
    assert fit.kind == "slide", extra
    assert extra["state_rmse_from_pose"] < 0.03, extra
    assert extra["slide_rejected"] >= wild
    assert float(fit.axis @ truth.axis) > np.cos(np.radians(2)) and abs(fit.range - truth.range) < 0.01, fit


def test_measure_part_tries_another_mapper_seed_when_the_first_model_is_bent(monkeypatch, tmp_path):
    """The geometry judges the part's reconstruction: a model bent by a drifting scale (positions that miss a rigid
    motion's by more than MAX_RESIDUAL of how far it moves the part) is mapped again with the next seed (on the
    same matches), and the best attempt is kept."""
    from interreal.motions import part as motions

    truth, states, known, good = _slide_case(seed=4, wild=0)
    bent = PartViews(good.frames, good.rot.copy(), good.u * np.linspace(1, 3, len(good.frames))[:, None],
                     good.centre)  # scale drifting along the capture: positions no slide explains
    seeds = []
    monkeypatch.setattr(motions, "match_part", lambda *a, **k: tmp_path / "database.db")
    monkeypatch.setattr(motions, "map_part", lambda pc, ds, db, out, cfg, seed: seeds.append(seed) or seed)
    monkeypatch.setattr(motions, "part_views", lambda rec, ds: bent if rec == 0 else good)
    monkeypatch.setattr(motions, "measure_part_pnp", lambda *a, **k: (None, {}))  # the other route finds nothing
    monkeypatch.setattr(motions, "known_camera_motion",  # its tracks locate nothing: the poses are its own
                        lambda *a, **k: (None, {"registered": 0, "at_known_state": 0, "known_located": 0}))
    motion, fig = motions.measure_part(None, None, [], tmp_path, states, known, motions.MotionConfig(attempts=3))
    assert seeds == [0, 1] and fig["attempt"] == 1 and fig["attempts"] == 2 and fig["accepted"]
    assert motion.kind == "slide" and fig["state_rmse_from_pose"] < 0.03
    seeds.clear()
    monkeypatch.setattr(motions, "part_views", lambda rec, ds: bent)
    motion, fig = motions.measure_part(None, None, [], tmp_path, states, known, motions.MotionConfig(attempts=3))
    assert seeds == [0, 1, 2] and fig["attempts"] == 3 and not fig["accepted"] and "bent" in fig["reason"]


def test_part_pairs_link_far_frames():
    pairs = part_pairs(40, overlap=3, key_every=8)
    assert (0, 1) in pairs and (0, 3) in pairs and (0, 16) in pairs and (8, 32) in pairs
    assert all(a < b < 40 for a, b in pairs) and len(set(pairs)) == len(pairs)


def test_known_states_fill_still_stretches_only():
    times = np.arange(8, dtype=float)
    labels = np.zeros((8, 1))
    given = np.zeros((8, 1), bool)
    for i, v in ((0, 0.0), (3, 0.0), (6, 1.0)):
        labels[i, 0], given[i, 0] = v, True
    states, known = known_states(times, labels, given)
    assert known[:4, 0].all() and not known[4:6, 0].any() and known[6, 0] and not known[7, 0]
    assert np.allclose(states[:4, 0], 0.0)


def test_articulation_file_round_trip_and_bad_input(tmp_path):
    hinge = Articulation("hinge", np.array([0, 2.0, 0]), np.array([1.0, 0, 0]), 1.2, {"frames": 40})
    write_articulation(tmp_path, {"door": hinge}, {"source": "test"})
    back = read_articulation(tmp_path)["door"]
    assert back.kind == "hinge" and np.allclose(back.axis, [0, 1, 0]) and back.extra["frames"] == 40
    r, t = back.pose(0.5)
    assert np.allclose(r @ np.array([1.0, 0, 0]) + t, [1.0, 0, 0])  # a point on the axis stays
    (tmp_path / "articulation.json").write_text(json.dumps({"objects": {"door": {"type": "twist", "axis": [0, 1, 0],
                                                                                  "range": 1}}}))
    with pytest.raises(DatasetError, match="twist"):
        read_articulation(tmp_path)


def test_to_rest_inverts_the_articulation_pose():
    hinge = Articulation("hinge", np.array([0.0, 0.6, 0.8]), np.array([0.3, -0.1, 0.2]), 1.3)
    slide = Articulation("slide", np.array([1.0, 0.0, 0.0]), np.zeros(3), 0.5)
    pm = PartMotions(4)
    pm.load([hinge, None, slide])
    assert pm.rigid(3) == [0, 2]
    rng = np.random.default_rng(0)
    rest = rng.normal(size=(16, 3))
    values = torch.zeros(16, 4)
    values[:, 0], values[:, 2] = 0.7, 0.4
    for j, (o, m) in enumerate(((0, hinge), (2, slide))):
        r, t = m.pose(float(values[0, o]))
        world = torch.as_tensor(rest @ r.T + t, dtype=torch.float32)
        dirs = torch.as_tensor(rest @ r.T, dtype=torch.float32)
        back, back_d = pm.to_rest(world, dirs, values, [0, 2])
        assert torch.allclose(back[j], torch.as_tensor(rest, dtype=torch.float32), atol=1e-5)
        assert torch.allclose(back_d[j], torch.as_tensor(rest, dtype=torch.float32), atol=1e-5)


def test_carve_hull_keeps_the_part_and_drops_the_air():
    """A unit cube part on a slide, seen by 24 cameras around it at states 0..1: the hull holds the cube's centre
    in the rest frame and not a point beside it."""
    import cv2

    slide = Articulation("slide", np.array([1.0, 0.0, 0.0]), np.zeros(3), 1.0)
    h = w = 64
    k = np.array([[60.0, 0, 32], [0, 60.0, 32], [0, 0, 1]])
    cube = np.stack(np.meshgrid(*[np.linspace(-0.25, 0.25, 12)] * 3, indexing="ij"), -1).reshape(-1, 3)
    cams, masks, states = [], [], []
    for i in range(24):
        s = (i % 5) / 4
        a = 2 * np.pi * i / 24
        c = np.array([4 * np.cos(a), 1.5, 4 * np.sin(a)])
        z = -c / np.linalg.norm(c)
        x = np.cross([0, 1.0, 0], z)
        x /= np.linalg.norm(x)
        r_wc = np.stack([x, np.cross(z, x), z])  # world -> camera rows
        rvec, tvec = cv2.Rodrigues(r_wc)[0], -r_wc @ c
        px, _ = cv2.projectPoints(cube + [s, 0, 0], rvec, tvec, k, np.zeros(5))
        m = np.full((h, w), 1, np.uint8)  # background = class 1
        hull = cv2.convexHull(px.reshape(-1, 2).astype(np.float32)).astype(np.int32)
        cv2.fillConvexPoly(m, hull, 0)
        cams.append((rvec, tvec, k, np.zeros(5)))
        masks.append(m)
        states.append(s)
    out = carve_hull(slide, 0, 1, list(range(24)), np.array(states), np.stack(masks), cams,
                     (np.array([-2.0, -2, -2]), np.array([2.0, 2, 2])), res=32)
    assert out is not None
    lo, hi, occ = out

    def at(p):
        c = np.floor((np.asarray(p) - lo) / (hi - lo) * 32).astype(int)
        return bool(((c >= 0) & (c < 32)).all() and occ[tuple(c)])

    assert at([0, 0, 0]) and at([0.2, 0.2, -0.2])
    assert not at([0.9, 0, 0]) and not at([0, 0.9, 0])


def test_validate_names_a_motion_for_an_unknown_object(tiny_dataset):
    from interreal.dataset import validate

    assert validate(tiny_dataset).ok
    write_articulation(tiny_dataset, {"sofa": Articulation("slide", np.array([1.0, 0, 0]), np.zeros(3), 0.3)}, {})
    res = validate(tiny_dataset)
    assert not res.ok and any(p.kind == "bad-articulation" and "sofa" in p.message for p in res.problems)


@pytest.mark.slow
def test_motions_of_a_simulated_capture_match_the_truth(tmp_path):
    """`interreal motions` on the default simulated capture at 320x240 (truth masks and poses, its ~10 % state labels): the fridge
    door is a hinge and the drawer a slide, each within a few degrees and per cent of the simulator's motion (~70 s)."""
    from interreal import cli
    from interreal.scoring import motion_errors
    from interreal.synth import SynthConfig, truth_dataset, write_capture

    cap = write_capture(SynthConfig(frames=300, width=320, height=240, seed=0), tmp_path / "cap")
    ds = truth_dataset(cap, tmp_path / "ds", size=(320, 240))
    assert cli.main(["motions", str(ds)]) == 0
    errs = motion_errors(ds, cap)
    door, drawer = errs["fridge door"], errs["top drawer"]
    assert door["kind"] == "hinge" and drawer["kind"] == "slide", errs
    assert door["axis_deg"] < 4 and door["range_error"] < 0.08 and door["origin_error"] < 0.05, door
    assert drawer["axis_deg"] < 10 and drawer["range_error"] < 0.1, drawer  # 6.7 deg, 2 % when written
    rep = json.loads((ds / "reports" / "motions.json").read_text())
    assert rep["status"] == "ok" and rep["figures"]["measured"] == 2
    # every registered frame's measured state travels with the motion (what training fits the states to), and on
    # the labelled frames (the simulator's exact states) it agrees with them
    from interreal.dataset import load_dataset

    dset = load_dataset(ds)
    labels, given = dset.label_matrix()
    for o, name in enumerate(dset.object_names):
        measured = dset.articulation[name].measured_states([f.fid for f in dset.frames])
        ok = np.isfinite(measured)
        assert ok.sum() >= 30, (name, int(ok.sum()))
        both = ok & given[:, o]
        assert both.sum() >= 3 and np.median(np.abs(measured[both] - labels[both, o])) < 0.05, name
    # a second run with the same inputs reuses the first
    before = (ds / "articulation.json").stat().st_mtime_ns
    assert cli.main(["motions", str(ds)]) == 0
    assert (ds / "articulation.json").stat().st_mtime_ns == before


def test_motion_flags_come_from_the_config_fields():
    """`interreal motions` flags are generated from `MotionConfig`'s `option` fields."""
    import argparse
    from dataclasses import asdict

    from interreal.errors import InputError
    from interreal.motions import MotionConfig, add_arguments, estimate_motions
    from interreal.options import values_from_args

    p = argparse.ArgumentParser()
    add_arguments(p)
    flags = {s for a in p._actions for s in a.option_strings} - {"-h", "--help"}
    assert flags == {"--erode", "--min-pixels", "--route", "--trust-labels", "--workers", "--verbose", "--force"}
    defaults = asdict(MotionConfig())
    opts = values_from_args(MotionConfig, p.parse_args(["ds"]))
    assert opts == {k: defaults[k] for k in ("erode", "min_pixels", "route", "trust_labels", "workers", "verbose")}
    opts = values_from_args(MotionConfig, p.parse_args(["ds", "--erode", "4", "--route", "pnp", "--verbose"]))
    assert opts == {"erode": 4, "min_pixels": 400, "route": "pnp", "trust_labels": False, "workers": 0,
                    "verbose": True}
    with pytest.raises(SystemExit):
        p.parse_args(["ds", "--route", "icp"])
    with pytest.raises(InputError, match="unknown motion options"):
        estimate_motions("ds", erosion=4)
