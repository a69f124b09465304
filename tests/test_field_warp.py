"""The axis warp (`livescene.field.AxisWarp`): the planes' cells follow the SfM points, the map stays monotone and
onto [-1, 1], runs trained before it load as the identity, and `build_model` fits it only from a point cloud."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_livescene_train import toy_dataset  # noqa: E402

from livescene.config import ModelConfig, load_preset  # noqa: E402
from livescene.field import AxisWarp, LiveSceneModel  # noqa: E402


def _clustered(n: int = 3000, seed: int = 0) -> torch.Tensor:
    """Box coordinates: 90 % of the points in [-0.6, -0.2] on every axis (the object), the rest anywhere (walls)."""
    g = torch.Generator().manual_seed(seed)
    near = torch.rand(int(n * 0.9), 3, generator=g) * 0.4 - 0.6
    far = torch.rand(n - len(near), 3, generator=g) * 2 - 1
    return torch.cat([near, far])


def test_warp_is_identity_until_fitted():
    w = AxisWarp()
    x = torch.rand(100, 3) * 2 - 1
    assert w.identity and w(x) is x


def test_warp_gives_the_points_cells_and_keeps_the_box():
    w = AxisWarp()
    w.fit(_clustered(), uniform=0.5)
    assert not w.identity
    ends = w(torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    assert torch.allclose(ends, torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), atol=1e-6)
    line = torch.linspace(-1, 1, 2001)[:, None].expand(-1, 3).contiguous()
    f = w(line)
    assert (f.diff(dim=0) > 0).all()  # strictly monotone: no two places share a cell
    span = w(torch.tensor([[-0.6] * 3, [-0.2] * 3]))
    stretch = (span[1] - span[0]) / 0.4
    # 0.4 of the box's 2 with ~92 % of the points: 0.5 x 0.4 + 0.5 x 2 x 0.92 = 1.12 of the field's 2
    assert ((stretch > 2.5) & (stretch < 3.0)).all(), stretch
    # every part of the box keeps at least the uniform share of its cells
    slope = f.diff(dim=0) / (2 / 2000)
    assert slope.min() >= 0.5 - 1e-3


def test_warp_carries_gradients_and_survives_points_on_one_plane():
    pts = _clustered()
    pts[:, 2] = 0.25  # a flat scene: every quantile of z is the same
    w = AxisWarp()
    w.fit(pts, uniform=0.3)
    assert (w.xk.diff(dim=1) > 0).all() and torch.isfinite(w.fk).all()
    x = (torch.rand(500, 3) * 2 - 1).requires_grad_()
    y = w(x)
    y.sum().backward()
    assert torch.isfinite(y).all() and (x.grad > 0).all()
    assert y[:, 2].min() >= -1 and y[:, 2].max() <= 1


def _small_model() -> LiveSceneModel:
    return LiveSceneModel(ModelConfig(max_objects=2, resolution=8, scales=[1], k_resolution=4,
                                      proposal_resolutions=[8], prob_resolution=8, var_resolution=4), 1)


def test_warp_travels_with_the_state_dict_and_old_runs_load_as_identity():
    model = _small_model()
    model.warp.fit(_clustered(), uniform=0.5)
    state = model.state_dict()
    again = _small_model()
    again.load_state_dict(state)
    assert not again.warp.identity and torch.equal(again.warp.fk, model.warp.fk)
    old = {k: v for k, v in state.items() if not k.startswith("warp.")}  # a checkpoint from before the warp
    fitted = _small_model()
    fitted.warp.fit(_clustered(seed=1), uniform=0.5)
    fitted.load_state_dict(old)
    assert fitted.warp.identity


def test_model_refuses_a_bad_warp_setting():
    from livescene.errors import LiveSceneError

    with pytest.raises(LiveSceneError, match="model.warp must"):
        LiveSceneModel(ModelConfig(warp="hash"), 1)
    with pytest.raises(LiveSceneError, match="warp_uniform"):
        LiveSceneModel(ModelConfig(warp_uniform=0.0), 1)


def test_build_model_fits_the_warp_from_the_point_cloud(tmp_path):
    import trimesh

    from livescene.data import load_views
    from livescene.trainer import build_model

    ds = toy_dataset(tmp_path / "ds", n_frames=8)
    cfg = load_preset("tiny")
    views = load_views(ds, cfg)
    assert build_model(cfg, views)[1].warp.identity  # no point cloud: even
    centre = views.c2w_gl[:, :3, 3].mean(0)
    rng = np.random.default_rng(0)
    pts = np.vstack([centre + rng.normal(scale=0.05, size=(900, 3)), centre + rng.uniform(-2, 2, size=(100, 3))])
    trimesh.PointCloud(pts).export(ds / "sparse_pc.ply")
    views = load_views(ds, cfg)
    model = build_model(cfg, views)[1]
    assert not model.warp.identity
    box = (torch.as_tensor(views.box_lo), torch.as_tensor(views.box_hi))
    at = torch.as_tensor(np.stack([centre - 0.05, centre + 0.05]), dtype=torch.float32)
    from livescene.field import normalise

    plain, warped = normalise(at, box), model.to_field(at, box)
    assert ((warped[1] - warped[0]) > 1.5 * (plain[1] - plain[0])).all()  # the cluster got more cells
    cfg.model.warp = "off"
    assert build_model(cfg, views)[1].warp.identity
