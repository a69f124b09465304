"""The fast renderer (`livescene.march` + `livescene.occupancy`): it matches the exact one on a trained toy run,
its occupancy grid travels with the checkpoint (or is built once and cached for older runs), skipping and early
termination really leave field reads out, and a state change still moves the part where the grid covers it."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_livescene_rigid import TOY_DOOR, train_toy_door  # noqa: E402
from test_livescene_toy import ToyScene  # noqa: E402

from livescene.config import ModelConfig  # noqa: E402
from livescene.trainer import load_run  # noqa: E402


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(max(np.mean((a - b) ** 2), 1e-12)))


@pytest.fixture(scope="module")
def rigid_run(tmp_path_factory, one_thread):
    """The toy door trained with its hinge (one torch thread, a few seconds on an idle core)."""
    return train_toy_door(tmp_path_factory.mktemp("fast"), 16, (32, 24), 200)[0]


def _view(run, pos: int = 3, scale: float = 1.0):
    i = run.views.train[pos]
    intr = run.views.intrinsics[i]
    if scale != 1.0:
        intr = intr.scaled(round(intr.w * scale), round(intr.h * scale))
    return i, run.views.c2w_gl[i], intr


def test_fast_matches_exact_and_reads_less(rigid_run):
    from livescene.render import render_view

    run = load_run(rigid_run, device="cpu")
    assert run.occupancy is not None  # saved with the checkpoint at the end of training
    i, c2w, intr = _view(run)
    exact = render_view(run, c2w, intr, {"door": 0.3}, fast=False)
    fast = render_view(run, c2w, intr, {"door": 0.3}, tolerance=0)  # the marcher alone: every pixel traced
    no_grid = render_view(run, c2w, intr, {"door": 0.3}, occupancy=False, tolerance=0)
    assert fast["fast"] and not exact["fast"] and exact["march"] is None
    assert _psnr(fast["rgb"], exact["rgb"]) > 40.0
    assert _psnr(no_grid["rgb"], exact["rgb"]) > 50.0  # termination alone is exact to 1e-4
    assert np.abs(fast["probs"] - exact["probs"]).mean() < 0.01
    ok = exact["acc"] > 0.5
    assert np.median(np.abs(fast["depth"] - exact["depth"])[ok]) < 0.02
    st, st0 = fast["march"], no_grid["march"]
    assert st["samples"] == st0["samples"] == intr.w * intr.h * 48  # tiny preset: 24 + 12 + 12 samples a ray
    assert st["evaluated"] <= st0["evaluated"] < st0["samples"]  # terminated rays read nothing further
    assert fast["seconds"] > 0 and fast["rays"] == intr.w * intr.h
    # a few hundred steps leave fog in the air (density ~0.5 a unit): a coarser threshold skips it, at a cost
    coarse = render_view(run, c2w, intr, {"door": 0.3}, threshold=run.occupancy.threshold(0.2), tolerance=0)
    assert coarse["march"]["evaluated"] < st["evaluated"]


def test_grid_travels_with_the_checkpoint_and_is_cached_for_older_runs(rigid_run, tmp_path, monkeypatch):
    import shutil

    from livescene import occupancy
    from livescene.render import render_view

    ckpt = torch.load(rigid_run / "latest.pt", map_location="cpu", weights_only=False)
    grid = ckpt["occupancy"]
    assert grid["step"] == ckpt["step"] and grid["density"].dtype == torch.float16
    assert list(grid["density"].shape) == grid["info"]["shape"] and grid["info"]["swept_states"][0] > 1
    old = tmp_path / "old_run"  # a run trained before grids: its checkpoint has none
    shutil.copytree(rigid_run, old)
    del ckpt["occupancy"]
    torch.save(ckpt, old / "latest.pt")
    run = load_run(old, device="cpu")
    assert run.occupancy is None
    _, c2w, intr = _view(run, scale=0.5)
    render_view(run, c2w, intr)  # builds it and caches it next to the checkpoint
    assert (old / occupancy.CACHE_NAME).exists()
    assert torch.equal(run.occupancy.density, grid["density"])  # the same grid as the one built after training

    def refuse(*a, **k):
        raise AssertionError("the cached grid should have been used")

    monkeypatch.setattr(occupancy, "build_grid", refuse)
    again = load_run(old, device="cpu")
    assert occupancy.grid_for(again) is not None


def test_state_change_moves_the_part_where_the_grid_covers_it(rigid_run):
    from livescene.march import rest_transform
    from livescene.render import render_view

    run = load_run(rigid_run, device="cpu")
    i, c2w, intr = _view(run, pos=5)
    a = render_view(run, c2w, intr, {"door": 0.0})
    b = render_view(run, c2w, intr, {"door": 1.0})
    _, _, idx0 = ToyScene(1).render(c2w, [0.0], intr)
    _, _, idx1 = ToyScene(1).render(c2w, [1.0], intr)
    diff = np.abs(a["rgb"] - b["rgb"]).max(-1)
    static = (idx0 == 0) & (idx1 == 0)
    assert diff[(idx0 == 1) | (idx1 == 1)].mean() > 0.02
    assert np.percentile(diff[static], 90) < 0.03
    # the door's panel (rest frame: x -0.9..-0.1 at y 0.6, z 0..1.2) is inside occupied cells at every state
    occupied = run.occupancy.tester()
    u, v = np.meshgrid(np.linspace(-0.8, -0.2, 7), np.linspace(0.1, 1.1, 7))
    rest = torch.tensor(np.stack([u.ravel(), np.full(u.size, 0.6), v.ravel()], -1), dtype=torch.float32)
    for s in (0.0, 0.5, 1.0):
        rt, off = rest_transform(run.model, 0, s)
        world = (rest - off) @ rt.T
        assert occupied(world).float().mean() > 0.9


def test_early_termination_stops_reading_an_opaque_ray():
    from livescene.march import SEGMENT, MarchStats, march_level
    from livescene.sampler import volume_weights

    r, s = 5, 4 * SEGMENT
    origins = torch.zeros(r, 3)
    dirs = torch.tensor([[1.0, 0.0, 0.0]]).expand(r, 3)
    edges = torch.linspace(0.1, 2.0, s + 1).expand(r, s + 1).contiguous()
    reads = []

    def wall(pts, ri):  # an opaque wall from x = 0.3 on
        reads.append(len(pts))
        return torch.where(pts[:, 0] > 0.3, 1e4, 0.0)

    stats = MarchStats()
    sigma, _ = march_level(origins, dirs, edges, wall, None, stats)
    assert stats.evaluated == r * SEGMENT  # the wall is inside the first segment: nothing read after it
    full = torch.where(0.5 * (edges[:, 1:] + edges[:, :-1]) > 0.3, 1e4, 0.0)
    assert torch.allclose(volume_weights(sigma, edges), volume_weights(full, edges), atol=1e-4)

    def clear(pts, ri):
        return torch.zeros(len(pts))

    stats = MarchStats()
    march_level(origins, dirs, edges, clear, None, stats)
    assert stats.evaluated == r * s  # nothing stops a clear ray


@pytest.mark.parametrize("motion,warped", [("none", False), ("rigid", False), ("rigid", True)])
def test_fixed_state_placement_is_the_models(motion, warped):
    """`FixedStates.place` (transforms built once, states folded into the first layer, the hull gate deciding)
    gives what `LiveSceneModel.place` gives sample by sample, with the axis warp too."""
    from livescene.articulation import HULL_RES
    from livescene.field import LiveSceneModel
    from livescene.march import FixedStates

    torch.manual_seed(0)
    n = 2 if motion == "none" else 1
    model = LiveSceneModel(ModelConfig(motion=motion, max_objects=3, resolution=8, scales=[1], k_resolution=4,
                                       proposal_resolutions=[8], prob_resolution=8, var_resolution=4), n).eval()
    for p in model.prob.parameters():
        p.data.normal_(0, 1.0)  # planes and weights: owners that differ from sample to sample
    if motion == "rigid":
        model.motions.load([TOY_DOOR])
        hull = torch.rand(HULL_RES, HULL_RES, HULL_RES) > 0.3
        model.motions.set_hull(0, (np.array([-1.0, 0.3, -0.1]), np.array([0.2, 0.9, 1.4]), hull.numpy()))
    box = (torch.tensor([-2.0, -2.0, -0.5]), torch.tensor([2.0, 2.0, 3.0]))
    pts = torch.rand(4000, 3) * torch.tensor([3.0, 2.0, 2.0]) + torch.tensor([-1.5, -0.5, -0.3])
    if warped:
        model.warp.fit(torch.randn(2000, 3) * 0.2, uniform=0.4)
    dirs = torch.nn.functional.normalize(torch.randn(4000, 3), dim=-1)
    values = model.pad_values(torch.tensor([[0.7, 0.2][:n]]))
    with torch.no_grad():  # move the background's bias so that about half of the samples are owned
        raw = model.prob(model.to_field(pts, box), values.expand(len(pts), -1))
        model.prob.net[-1].bias[-1] += (raw[:, :n].max(-1).values - raw[:, -1]).median()
        ref = model.place(pts, dirs, values.expand(len(pts), -1), box)
        xyz, view, k, logits = FixedStates(model, values[0]).place(pts, dirs, box)
    assert torch.allclose(xyz, ref.xyz, atol=1e-5) and torch.allclose(view, ref.dirs, atol=1e-5)
    assert torch.allclose(k, ref.k)
    owned = model.owner(ref.logits)[1]
    assert owned.any() and (~owned).any()  # both owners occur: the test tells them apart
    assert torch.allclose(torch.softmax(logits, -1), torch.softmax(ref.logits, -1), atol=1e-5)


def cube_model(motion: str = "none"):
    """A model whose field is a solid cube (normalised coordinates [-0.3, 0.3]^3) in clear air, the same for every
    k; with `motion` "rigid", object 0 is a door hinged on the z axis through (0.5, 0, 0) (world units) that owns
    the cube inside its hull (world -0.8 .. 0.8 at rest)."""
    from livescene.articulation import HULL_RES
    from livescene.field import LiveSceneModel
    from interreal.dataset import Articulation

    cfg = ModelConfig(motion=motion, max_objects=2, resolution=16, scales=[1], k_resolution=4, features=4, hidden=8,
                      geo_features=3, sh_degree=1, prob_resolution=8, proposal_resolutions=[16], proposal_features=4,
                      proposal_hidden=8, var_resolution=4)
    model = LiveSceneModel(cfg, 1).eval()
    lo, hi = 5, 10  # nodes of 16 at -0.33 .. 0.33
    with torch.no_grad():
        for grid, net in ((model.field.grid, model.field.sigma_net), (model.proposals[0].grid, model.proposals[0].net)):
            for plane in grid.spatial:
                plane.zero_()
                plane[:, 0, lo:hi + 1, lo:hi + 1] = 1.0  # channel 0: 1 inside the cube, 0 outside
            for plane in grid.kplanes:
                plane.fill_(1.0)
            net[0].weight.zero_()
            net[0].bias.zero_()
            net[0].weight[0, 0] = 40.0
            net[2].weight.zero_()
            net[2].bias.zero_()
            net[2].weight[0, 0] = 1.0
            net[2].bias[0] = -20.0  # density exp(40 f - 21): opaque inside, ~1e-9 outside
    if motion == "rigid":
        model.motions.load([Articulation("hinge", np.array([0.0, 0.0, 1.0]), np.array([0.5, 0.0, 0.0]), np.pi / 2)])
        model.motions.set_hull(0, (np.array([-0.8, -0.8, -0.8]), np.array([0.8, 0.8, 0.8]),
                                   np.ones((HULL_RES,) * 3, bool)))
        with torch.no_grad():  # the door owns its hull whatever the random init (it decided before: flaky)
            last = model.prob.net[-1]
            last.weight.zero_()
            last.bias.zero_()
            last.bias[0] = 10.0
    return model


def _rays(n: int = 24):
    u, v = torch.meshgrid(torch.linspace(-0.9, 0.9, n), torch.linspace(-0.9, 0.9, n), indexing="ij")
    origins = torch.stack([u.ravel(), v.ravel(), torch.full((n * n,), -3.0)], -1)
    return origins, torch.tensor([[0.0, 0.0, 1.0]]).expand(n * n, 3).contiguous()


def test_grid_skips_clear_air_and_keeps_the_render():
    from livescene.config import SamplerConfig
    from livescene.march import FixedStates, MarchStats, march_rays
    from livescene.occupancy import build_grid
    from livescene.sampler import render_rays

    model = cube_model()
    box = (torch.full((3,), -1.0), torch.full((3,), 1.0))
    grid = build_grid(model, box, resolution=64)
    assert 0.04 < grid.occupied_fraction() < 0.15  # the cube (6 % of the box up to interpolation), a cell around
    origins, dirs = _rays()
    cfg = SamplerConfig(proposal_samples=[32], samples=16, near=0.0)
    values = model.pad_values(torch.tensor([[0.5]]))
    with torch.no_grad():
        exact = render_rays(model, origins, dirs, values.expand(len(origins), -1), box, cfg, gen=None)
    fixed = FixedStates(model, values[0])
    skipped, full = MarchStats(), MarchStats()
    fast = march_rays(model, fixed, origins, dirs, box, cfg, grid.tester(), True, skipped)
    plain = march_rays(model, fixed, origins, dirs, box, cfg, None, True, full)
    assert _psnr(fast["rgb"].numpy(), exact.rgb.numpy()) > 40.0
    assert _psnr(plain["rgb"].numpy(), exact.rgb.numpy()) > 40.0  # without the grid: early termination alone
    assert torch.allclose(fast["acc"], exact.acc, atol=1e-3)
    hit = exact.acc > 0.5
    assert 0.1 < hit.float().mean() < 0.9  # some rays hit the cube, some pass by
    assert skipped.evaluated < 0.3 * full.evaluated  # air is not read ...
    assert full.evaluated < full.samples  # ... and rays that hit the cube stop there


def test_grid_covers_a_rigid_part_at_every_state():
    from livescene.march import rest_transform
    from livescene.occupancy import build_grid

    model = cube_model("rigid")
    box = (torch.full((3,), -2.0), torch.full((3,), 2.0))  # the cube: world -0.67 .. 0.67 at rest
    grid = build_grid(model, box, resolution=48)
    assert grid.info["swept_states"][0] > 10
    occupied = grid.tester()
    cube = (torch.rand(500, 3, generator=torch.Generator().manual_seed(0)) - 0.5) * 1.2  # world units at rest
    for s in (0.0, 0.3, 0.7, 1.0):
        rt, off = rest_transform(model, 0, s)
        assert occupied((cube - off) @ rt.T).all()  # where the door has swung the cube to
    far = torch.tensor([[1.8, -1.8, 1.8], [-1.8, 1.8, -1.8]])
    assert not occupied(far).any()


def test_eval_and_render_report_their_speed(rigid_run, tmp_path):
    import json

    from livescene.cli import main as cli
    from livescene.evaluate import evaluate

    run = load_run(rigid_run, device="cpu")
    res = evaluate(run, None, max_frames=1, novel=0, progress=False)
    sp = res["speed"]
    assert sp["renderer"] == "fast" and sp["frames"] == 1 and sp["rays_per_s"] > 0 and sp["eval_s"] >= sp["render_s"]
    assert cli(["render", str(rigid_run), "--cameras", "held-out", "--frames", "0", "--out", str(tmp_path),
                "--exact"]) == 0
    speed = json.loads((tmp_path / "render.json").read_text())["speed"]
    assert speed["renderer"] == "exact" and speed["frames"] == 1 and speed["seconds_per_frame"] > 0


def test_a_state_change_rerenders_only_the_rays_a_part_can_reach(tmp_path):
    """With every object moving rigidly, the same camera at another state re-renders only the rays that meet
    the moved part's hull at the old or the new state (`adaptive.changed_pixels`) and reuses the rest: the
    same image as a fresh one when every pixel is traced, within the interpolation's error when not."""
    from types import SimpleNamespace

    from interreal.conventions import opencv_to_opengl
    from interreal.dataset import Intrinsics
    from livescene.config import TrainConfig
    from livescene.occupancy import build_grid
    from livescene.render import render_view
    from livescene.trainer import Run

    model = cube_model("rigid")
    views = SimpleNamespace(names=["door"], box_lo=np.full(3, -2.0, np.float32), box_hi=np.full(3, 2.0, np.float32))
    cfg = TrainConfig()
    cfg.sampler.near = 0.0
    run = Run(tmp_path, model, views, cfg, torch.device("cpu"), 0, checkpoint=tmp_path / "latest.pt")
    run.occupancy = build_grid(model, run.box, resolution=48)
    c2w = np.eye(4)
    c2w[:3, 3] = [0.0, 0.0, -1.9]  # inside the box, looking along +z at the cube
    intr = Intrinsics(w=32, h=24, fl_x=10.0, fl_y=10.0, cx=16.0, cy=12.0, camera_model="PINHOLE")
    c2w_gl = opencv_to_opengl(c2w)
    first = render_view(run, c2w_gl, intr, {"door": 0.0}, tolerance=0)
    moved = render_view(run, c2w_gl, intr, {"door": 1.0}, tolerance=0)
    assert first["rays_reused"] == 0 and 0 < moved["rays_reused"] < moved["rays"]
    assert moved["march"]["rays"] == moved["rays"] - moved["rays_reused"]
    run._image_caches = None
    fresh = render_view(run, c2w_gl, intr, {"door": 1.0}, tolerance=0)
    exact = render_view(run, c2w_gl, intr, {"door": 1.0}, fast=False)
    assert np.abs(moved["rgb"] - fresh["rgb"]).max() < 1e-6 and np.abs(moved["depth"] - fresh["depth"]).max() < 1e-5
    assert _psnr(moved["rgb"], exact["rgb"]) > 40.0
    assert np.abs(first["rgb"] - moved["rgb"]).max() > 0.1  # the cube did move
    render_view(run, c2w_gl, intr, {"door": 0.0})  # interpolated images: reused pixels, the same picture
    again = render_view(run, c2w_gl, intr, {"door": 1.0})
    assert again["rays_reused"] > 0 and _psnr(again["rgb"], exact["rgb"]) > 35.0


def test_fast_render_traces_and_reads_a_fraction_of_the_exact_one(rigid_run):
    """The default fast render (`livescene.adaptive`): a fraction of the pixels traced and of the samples read,
    within a small PSNR of the exact render; every pixel traced (tolerance 0) is the exact render."""
    from livescene.render import render_view
    from livescene.trainer import load_run

    run = load_run(rigid_run, device="cpu")
    i = run.views.train[3]
    intr = run.views.intrinsics[i].scaled(128, 96)
    c2w = run.views.c2w_gl[i]
    exact = render_view(run, c2w, intr, {"door": 0.3}, fast=False)
    fast = render_view(run, c2w, intr, {"door": 0.3})
    every = render_view(run, c2w, intr, {"door": 0.3}, tolerance=0)  # every pixel traced
    per_ray = sum(run.config.sampler.proposal_samples) + run.config.sampler.samples
    assert every["traced"] == 128 * 96 and _psnr(every["rgb"], exact["rgb"]) > 40.0
    assert fast["traced"] < 0.55 * 128 * 96  # flat regions interpolated (at 2x the training size)
    assert fast["march"]["evaluated"] < 0.55 * 128 * 96 * per_ray  # field reads: >= 1.8x fewer
    assert _psnr(fast["rgb"], exact["rgb"]) > 35.0
    assert np.abs(fast["probs"] - exact["probs"]).mean() < 0.02
    ok = exact["acc"] > 0.5
    assert np.median(np.abs(fast["depth"] - exact["depth"])[ok]) < 0.02
