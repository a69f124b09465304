"""The error map: a share of each batch goes where the colour error is, every tile visited before its error decides."""

from __future__ import annotations

import torch

from livescene.data import ErrorMap


def _map(n_frames: int = 4, h: int = 64, w: int = 96) -> ErrorMap:
    return ErrorMap(n_frames, h, w, torch.tensor([0, 1, 3]))  # frame 2 held out


def test_draws_stay_on_training_frames_and_inside_the_image():
    em = _map(h=60, w=90)  # tiles overhang the image's edge
    f, ys, xs = em.draw(5000, torch.Generator().manual_seed(0))
    assert set(f.tolist()) == {0, 1, 3}
    assert int(ys.min()) >= 0 and int(ys.max()) <= 59 and int(xs.min()) >= 0 and int(xs.max()) <= 89
    assert int(ys.max()) > 50 and int(xs.max()) > 80  # the last, partial tiles are drawn too


def test_rays_go_where_the_error_is():
    em = _map()
    gen = torch.Generator().manual_seed(0)
    f, ys, xs = em.draw(20000, gen)  # every tile at its start value: all visited, near evenly
    tiles = set(zip(f.tolist(), (ys // 16).tolist(), (xs // 16).tolist()))
    assert len(tiles) == 3 * 4 * 6
    err = torch.where((f == 1) & (ys < 16) & (xs < 16), 0.2, 0.001)  # one tile much worse than the rest
    for _ in range(20):
        em.record(f, ys, xs, err)
    f, ys, xs = em.draw(20000, gen)
    share = float(((f == 1) & (ys < 16) & (xs < 16)).float().mean())
    assert 0.68 < share < 0.8  # 0.2 against 71 tiles at 0.001: 0.2 / 0.271 = 0.74 of the draws
    assert torch.all(em.err[2] == torch.tensor(ErrorMap.START))  # the held-out frame is never recorded


def test_the_batch_carries_its_pixels_and_records_its_error(tmp_path):
    """`RayData.sample` with an error share draws that share from the map; `record` feeds it back."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from test_livescene_toy import toy_dataset

    from livescene.config import load_preset
    from livescene.data import RayData, load_views

    ds = toy_dataset(tmp_path / "ds", n_frames=8, size=(32, 24))
    views = load_views(ds, load_preset("tiny"))
    data = RayData(views, torch.device("cpu"))
    gen = torch.Generator().manual_seed(0)
    batch = data.sample(64, gen, 0.0, 0.5)
    f, ys, xs = batch["pixel"].unbind(-1)
    assert torch.equal(batch["rgb"], data.rgb[f, ys, xs].float() / 255.0)
    data.record(batch, torch.full((64,), 0.3))
    assert torch.isclose(data.errors.err[f[0], ys[0] // 16, xs[0] // 16],
                         torch.tensor(ErrorMap.KEEP * ErrorMap.START + (1 - ErrorMap.KEEP) * 0.3))
    # a map that says one tile is all the error: half the batch (the error share) lands there
    data.errors.err.fill_(1e-9)
    t = int(data.train[0])
    data.errors.err[t, 0, 0] = 1.0
    f, ys, xs = data.sample(200, gen, 0.0, 0.5)["pixel"].unbind(-1)
    hit = (f == t) & (ys < 16) & (xs < 16)
    assert bool(hit[:100].all()) and float(hit[100:].float().mean()) < 0.5


def test_a_diverged_ray_leaves_the_map_a_distribution():
    em = _map()
    f, ys, xs = torch.tensor([0, 1]), torch.tensor([0, 0]), torch.tensor([0, 0])
    em.record(f, ys, xs, torch.tensor([float("nan"), 0.0]))
    assert float(em.err[0, 0, 0]) == float(torch.tensor(ErrorMap.START))  # the NaN left out
    assert float(em.err[1, 0, 0]) > 0  # a perfect ray: still drawable
    em.draw(10, torch.Generator().manual_seed(0))
