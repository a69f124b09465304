"""The fast renderer's image (`livescene.adaptive`): flat regions are interpolated from a coarse lattice of traced
pixels and edges are traced, and `reach_pixels` marks every pixel whose ray can meet a moving part (so reusing the
others across states is safe). On a trained run: tests/test_render_fast.py."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_render_fast import cube_model  # noqa: E402

from livescene.adaptive import agree_by, padded, reach_pixels, refine  # noqa: E402


def _image(h: int, w: int) -> torch.Tensor:
    """(h, w, F) features: a smooth ramp, a sharp step at x = 0.6 w, a one-pixel line on row 12; depth last."""
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    rgb = torch.stack([x / w * 0.2, y / h * 0.2, torch.where(x >= 0.6 * w, 0.9, 0.1)], -1)
    if h > 12:
        rgb[12] = 1.0
    depth = torch.where(x >= 0.6 * w, 2.0, 1.0)[..., None]
    return torch.cat([rgb, torch.ones(h, w, 1), depth], -1)


def recording_tracer(flat: torch.Tensor):
    """(trace, calls): a tracer reading pixels of `flat` (P, F) that records how many it was asked for."""
    calls: list[int] = []

    def trace(idx):
        calls.append(len(idx))
        return flat[idx]

    return trace, calls


def test_refine_interpolates_flat_regions_and_traces_edges():
    h, w, stride = 48, 64, 4
    hp, wp = padded(h, stride), padded(w, stride)
    assert (hp - 1) % stride == 0 and hp >= h and (wp - 1) % stride == 0 and wp >= w
    truth = _image(hp, wp)
    flat = truth.reshape(hp * wp, -1)
    trace, calls = recording_tracer(flat)
    values, traced = refine(hp, wp, stride, trace, agree_by(0.02))
    assert sum(calls) == int(traced.sum())  # each traced pixel traced once
    values, traced = values.view(hp, wp, -1), traced.view(hp, wp)
    assert traced.float().mean() < 0.35  # the ramp is interpolated ...
    assert (values - truth).abs().max() < 0.02  # ... within the tolerance, and nothing else is off
    step = int(np.ceil(0.6 * wp))  # the first column of the step's far side
    assert traced[:, step - 1: step + 1].any(1).all()  # on every row the step is found by a traced pixel
    # a one-pixel line on a coarse row is found and its neighbouring rows are traced (a feature thinner than the
    # stride that falls between coarse rows and columns can be missed: the price of the lattice)
    assert traced[13].all() and traced[14, ::2].all() and (values[12, :, :3] == 1.0).all()
    nothing = refine(hp, wp, stride, trace, lambda c: torch.zeros(len(c), dtype=torch.bool))[1]
    assert nothing.all()  # neighbours that never agree: every pixel traced
    for h, w in ((1, 1), (2, 7), (5, 1)):  # images smaller than the lattice step
        hp, wp = padded(h, stride), padded(w, stride)
        small = _image(hp, wp).reshape(hp * wp, -1)
        values, traced = refine(hp, wp, stride, lambda idx: small[idx], agree_by(0.02))
        assert (values - small).abs().max() < 0.02 and traced.any()


def test_reach_pixels_covers_every_ray_that_meets_a_reach_cell():
    """Each pixel whose ray (densely sampled) passes a reach cell is marked; pixels far from the part are not."""
    from interreal.conventions import opencv_to_opengl
    from interreal.dataset import Intrinsics
    from livescene.data import camera_rays, pixel_directions
    from livescene.occupancy import build_grid

    model = cube_model("rigid")
    box = (torch.full((3,), -2.0), torch.full((3,), 2.0))
    grid = build_grid(model, box, resolution=32)
    assert grid.reach is not None and 0 < grid.reach.float().mean() < 0.9
    intr = Intrinsics(w=40, h=30, fl_x=18.0, fl_y=18.0, cx=20.0, cy=15.0, camera_model="PINHOLE")
    c2w = np.eye(4)
    c2w[:3, 3] = [0.3, -0.2, -5.0]  # the swept cube fills the middle of the image
    c2w_gl = opencv_to_opengl(c2w)
    mask = reach_pixels(grid, c2w_gl, intr)
    o, d, _ = camera_rays(c2w_gl, intr, pixel_directions(intr))
    t = torch.linspace(0.0, 9.0, 3600)
    pts = torch.from_numpy(o)[:, None] + torch.from_numpy(d)[:, None] * t[None, :, None]
    inside = ((pts >= -2.0) & (pts <= 2.0)).all(-1)
    hits = (grid.tester(reach=True)(pts.reshape(-1, 3)).view(pts.shape[:2]) & inside).any(1).view(30, 40).numpy()
    assert hits.any() and not hits.all()
    assert mask[hits].all()  # conservative: never misses a ray that meets a reach cell
    assert mask.mean() < 0.8  # and leaves the others out
    # a camera inside a reach cell: every pixel may change
    c2w[:3, 3] = [0.0, 0.0, 0.0]
    assert reach_pixels(grid, opencv_to_opengl(c2w), intr) is None

