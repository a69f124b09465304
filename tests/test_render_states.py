"""What the fast renderer computes once per state or per ray instead of per sample, and how it reuses an image
across states: each equals the per-sample rule it replaces (`livescene.march`: the hull gate, the colour net's
per-ray half, the rendered object logits; `livescene.adaptive`: the pixels a state change may alter, gradients
interpolated by their second differences)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_livescene_rigid import TOY_DOOR  # noqa: E402
from test_render_adaptive import recording_tracer  # noqa: E402
from test_render_fast import cube_model  # noqa: E402

from livescene.config import ModelConfig  # noqa: E402


def _rigid_model(seed: int = 0):
    """A one-door model with a random hull and random fields (owners and colours that differ sample to sample)."""
    from livescene.articulation import HULL_RES
    from livescene.field import LiveSceneModel

    torch.manual_seed(seed)
    model = LiveSceneModel(ModelConfig(motion="rigid", max_objects=3, resolution=8, scales=[1, 2], k_resolution=4,
                                       proposal_resolutions=[8], prob_resolution=8, var_resolution=4), 1).eval()
    for p in list(model.prob.parameters()) + list(model.field.color_net.parameters()):
        p.data.normal_(0, 1.0)
    model.motions.load([TOY_DOOR])
    hull = torch.rand(HULL_RES, HULL_RES, HULL_RES) > 0.3
    model.motions.set_hull(0, (np.array([-1.0, 0.3, -0.1]), np.array([0.2, 0.9, 1.4]), hull.numpy()))
    return model


def test_gate_is_the_hull_test_of_the_rest_points():
    """`FixedStates.gate` (one transform and one flat lookup per part) says what `PartMotions.inside` says of the
    rest-frame points, inside the hull's box and outside it."""
    from livescene.march import FixedStates

    model = _rigid_model()
    fixed = FixedStates(model, model.pad_values(torch.tensor([[0.6]]))[0])
    lo, hi = model.motions.hull_lo[0], model.motions.hull_hi[0]
    u = torch.rand(20000, 3, generator=torch.Generator().manual_seed(1)) * 1.4 - 0.2  # the hull's box and around
    pts = (lo + u * (hi - lo) - fixed.offset[0]) @ fixed.rt[0].T  # rest = world @ rt + offset
    rest = torch.stack([fixed.rest(j, pts) for j in range(len(fixed.rigid))])
    want = model.motions.inside(fixed.rigid, rest)
    assert 0.05 < want.float().mean() < 0.5  # both answers occur
    assert torch.equal(fixed.gate(pts), want)


def test_colour_per_ray_equals_the_colour_net():
    """`RayColor`: the colour net's view-direction half once per ray gives `RadianceField.color` (to 1e-5), also
    for samples read in a part's frame (their direction turned)."""
    from livescene.march import FixedStates, Placed, RayColor

    model = _rigid_model()
    fixed = FixedStates(model, model.pad_values(torch.tensor([[0.6]]))[0])
    g = torch.Generator().manual_seed(2)
    rays = torch.nn.functional.normalize(torch.randn(50, 3, generator=g), dim=-1)
    ri = torch.randint(0, 50, (3000,), generator=g)
    h = torch.randn(3000, 1 + model.cfg.geo_features, generator=g)
    view = rays[ri].clone()
    moved = torch.arange(0, 3000, 7)
    view[moved] = view[moved] @ fixed.rt[0]  # read in the door's frame
    placed = Placed(torch.zeros(3000, 3), view, torch.zeros(3000), None, None, moved)
    which = torch.arange(0, 3000, 2)  # the samples whose colour is read
    with torch.no_grad():
        got = RayColor(model, rays).color(h[which], ri[which], which, placed)
        want = model.field.color(h[which], view[which])
    assert (got - want).abs().max() < 1e-5
    assert (want[:, 0] - want[:, 0].mean()).abs().max() > 0.05  # colours that differ: the check means something


def test_pixel_logits_from_sums_equal_the_samplers_rule():
    """The fast renderer sums w x probabilities (w x logits) over a ray's samples, the samples outside every hull
    at their shared default logits: the same pixel logits as `sampler.render_logits` over every sample."""
    from livescene.march import pixel_logits
    from livescene.sampler import render_logits

    g = torch.Generator().manual_seed(3)
    r, s, c = 40, 12, 5
    logits = torch.randn(r, s, c, generator=g) * 3
    default = torch.tensor([-30.0, -30.0, -1e4, -1e4, 0.0])
    own = torch.rand(r, s, generator=g) < 0.3  # samples the probability field decided
    logits[~own] = default
    w = torch.rand(r, s, generator=g) / s
    slots = torch.tensor([True, True, False, False, True])
    acc = w.sum(1)
    for mode in ("probs", "logits"):
        per = logits if mode == "logits" else torch.softmax(logits, -1)
        d = default if mode == "logits" else torch.softmax(default, -1)
        mixed = (w[..., None] * per * own[..., None]).sum(1) + (w * ~own).sum(1)[:, None] * d
        got = pixel_logits(mixed, acc, slots, mode)
        want = render_logits(logits, w, slots, mode)
        assert torch.allclose(got[:, slots], want[:, slots], atol=1e-4), mode


def test_a_state_change_alters_only_pixels_that_see_a_moved_hull(tmp_path):
    """`changed_pixels` marks every pixel whose exact render changes when the door moves (a door whose hull is the
    cube it owns, not the whole box), leaves most of the others out, and the image re-traced there equals a fresh
    one (every pixel traced)."""
    from types import SimpleNamespace

    from interreal.conventions import opencv_to_opengl
    from interreal.dataset import Intrinsics
    from livescene.adaptive import ImageCache, changed_pixels
    from livescene.articulation import HULL_RES
    from livescene.config import TrainConfig
    from livescene.render import render_view
    from livescene.trainer import Run

    model = cube_model("rigid")
    hull = np.zeros((HULL_RES,) * 3, bool)
    ax = np.linspace(-0.8, 0.8, HULL_RES + 1)
    inside = (ax[:-1] > -0.75) & (ax[1:] < 0.75)  # the cube (world -0.67 .. 0.67 at rest) and a little around
    hull[np.ix_(inside, inside, inside)] = True
    model.motions.set_hull(0, (np.array([-0.8] * 3), np.array([0.8] * 3), hull))
    with torch.no_grad():  # the door owns its hull
        model.prob.net[-1].weight.zero_()
        model.prob.net[-1].bias.zero_()
        model.prob.net[-1].bias[0] = 5.0
    views = SimpleNamespace(names=["door"], box_lo=np.full(3, -2.0, np.float32), box_hi=np.full(3, 2.0, np.float32))
    cfg = TrainConfig()
    cfg.sampler.near = 0.0
    run = Run(tmp_path, model, views, cfg, torch.device("cpu"), 0, checkpoint=tmp_path / "latest.pt")
    c2w = np.eye(4)
    c2w[:3, 3] = [0.0, 0.3, -1.9]  # inside the box, looking along +z at the cube
    c2w_gl = opencv_to_opengl(c2w)
    intr = Intrinsics(w=40, h=30, fl_x=10.0, fl_y=10.0, cx=20.0, cy=15.0, camera_model="PINHOLE")
    a = render_view(run, c2w_gl, intr, {"door": 0.0}, fast=False, occupancy=False)
    b = render_view(run, c2w_gl, intr, {"door": 0.6}, fast=False, occupancy=False)
    differs = np.abs(a["rgb"] - b["rgb"]).max(-1) > 1e-4
    old, new = (model.pad_values(torch.tensor([[v]]))[0] for v in (0.0, 0.6))
    mask = changed_pixels(model, ImageCache((), torch.zeros(0), old), new, c2w_gl, intr).view(30, 40).numpy()
    assert differs.any() and mask[differs].all()  # conservative: every pixel that changes is re-traced
    assert mask.mean() < 0.7  # and pixels beside the door are not
    first = render_view(run, c2w_gl, intr, {"door": 0.0}, tolerance=0, occupancy=False)
    moved = render_view(run, c2w_gl, intr, {"door": 0.6}, tolerance=0, occupancy=False)
    assert first["rays_reused"] == 0 and moved["rays_reused"] == int((~mask).sum())
    run._image_caches = None
    fresh = render_view(run, c2w_gl, intr, {"door": 0.6}, tolerance=0, occupancy=False)
    assert np.abs(moved["rgb"] - fresh["rgb"]).max() < 1e-6


def test_refine_interpolates_gradients_by_their_second_differences():
    """A shading gradient steeper than the tolerance across a lattice step is traced by the spread test alone;
    with the smooth test (second differences within it) it is interpolated, with the curved estimates nearly
    exact, while a step edge is still traced on every row and no estimate overshoots its neighbours."""
    from livescene.adaptive import agree_by, padded, refine, smooth_by

    h, w, stride = 48, 64, 4
    hp, wp = padded(h, stride), padded(w, stride)
    y, x = torch.meshgrid(torch.arange(hp, dtype=torch.float32), torch.arange(wp, dtype=torch.float32),
                          indexing="ij")
    shade = 0.05 + 1.2 * x / wp + 0.3 * (y / hp) ** 2  # 0.074 across a coarse lattice step: above 0.04
    step = torch.where(x >= 0.75 * wp, 0.5, 0.0)
    truth = torch.stack([shade + step, shade, shade * 0.5, torch.ones_like(x), 1.0 + 0 * x], -1)
    flat = truth.reshape(hp * wp, -1)
    trace, _ = recording_tracer(flat)
    plain, traced_plain = refine(hp, wp, stride, trace, agree_by(0.04))
    values, traced = refine(hp, wp, stride, trace, agree_by(0.04), "cpu", smooth_by(0.08))
    assert traced.float().mean() < 0.6 * traced_plain.float().mean()  # the gradient is interpolated
    fine = refine(hp, wp, stride, trace, agree_by(0.04), "cpu", smooth_by(0.08), smooth_spacing=2)[1]
    assert traced.sum() < fine.sum() < traced_plain.sum()  # asked at the finest level only: between the two
    err = (values - flat).abs().view(hp, wp, -1)
    left = torch.arange(wp) < 0.75 * wp - 2 * stride  # away from the step
    assert err[:, left].max() < 0.01  # ... within a quarter of the tolerance (exact away from the border)
    edge = int(np.ceil(0.75 * wp))
    assert traced.view(hp, wp)[:, edge - 1: edge + 1].any(1).all()  # the step is found on every row
    lo = flat.view(hp, wp, -1).amin((0, 1))
    hi = flat.view(hp, wp, -1).amax((0, 1))
    assert (values >= lo - 1e-6).all() and (values <= hi + 1e-6).all()  # no overshoot


def test_sweep_camera_picks_the_view_where_the_part_changes_most(monkeypatch):
    """A door seen edge-on from camera 0 (its pixels barely change between states) and from the front by camera 2
    (most change): the sweep is rendered from camera 2, with the share that changes."""
    import types

    import numpy as np

    from interreal.dataset import Intrinsics
    from livescene import render as R

    intr = Intrinsics(w=40, h=30, fl_x=30.0, fl_y=30.0, cx=20.0, cy=15.0)
    views = types.SimpleNamespace(names=["door"], intrinsics=[intr] * 3, c2w_gl=[np.eye(4) * (i + 1) for i in range(3)],
                                  times=np.zeros(3))
    run = types.SimpleNamespace(views=views)

    def fake(run, c2w, small, states, time=0.0):
        cam = int(c2w[0, 0]) - 1
        h, w = small.h, small.w
        probs = np.zeros((h, w, 2), np.float32)
        probs[2:8, 2:8, 0] = 1.0  # the door's pixels
        rgb = np.zeros((h, w, 3), np.float32)
        changes = {0: 0.05, 1: 0.3, 2: 0.8}[cam]  # share of the door's rows that change colour at state 1
        assert set(states) == {"door"}
        if states["door"] == 1.0:
            rgb[2:2 + round(6 * changes), 2:8] = 1.0
        return {"rgb": rgb, "probs": probs}

    monkeypatch.setattr(R, "render_view", fake)
    i, share = R.sweep_camera(run, "door", [0, 1, 2], scale=0.5)
    assert i == 2 and 0.7 < share <= 1.0
