"""Grounding on a tiny trained scene: a simulated capture -> truth dataset -> tiny run; the grounded object's
rendered mask matches its truth mask; `livescene ground --out` writes masks and overlays; commands set states;
a run trained without masks is refused."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from interreal.dataset import read_image_rgb
from livescene import cli
from livescene.errors import LiveSceneError
from livescene.language import apply_command, ground_query, require_match
from livescene.language.grounding import check_run_has_masks, frame_views, mask_iou, render_mask

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A 32-frame capture of the default room (fridge door, top drawer) at 48x36, tiny preset, 300 steps
    with the mask loss weighted up so a few hundred steps learn the probability field (about a minute)."""
    from interreal.synth import SynthConfig, truth_dataset, write_capture
    from livescene.config import load_preset
    from livescene.trainer import load_run, train

    root = tmp_path_factory.mktemp("ground")
    write_capture(SynthConfig(frames=32, width=96, height=72, seed=0), root / "cap", progress=False)
    ds = truth_dataset(root / "cap", root / "ds", size=(48, 36))
    cfg = load_preset("tiny")
    cfg.steps, cfg.eval_every = 300, 0
    cfg.loss.focal = 1.0
    train(ds, root / "run", cfg, device="cpu", show_progress=False)
    return root, ds, root / "run", load_run(root / "run", device="cpu")


def _train_views(run, n=3):
    ids = [run.dataset.frames[i].fid for i in run.views.train[:: max(1, len(run.views.train) // n)][:n]]
    return frame_views(run, ",".join(ids))


def test_grounded_mask_matches_truth(scene):
    """The fridge door (a large object) is learned in a few hundred steps: its grounded mask overlaps its truth
    and not the drawer's; the small drawer only has to overlap its own truth more than the fridge's."""
    root, ds, run_dir, run = scene
    check_run_has_masks(run)
    assert run.names == ["fridge door", "top drawer"]
    fridge = require_match(ground_query(run_dir, "the refrigerator", run=run))
    drawer = require_match(ground_query(run_dir, "the upper drawer", run=run))
    assert (fridge.index, drawer.index) == (0, 1)
    iou = {(a, b): [] for a in (0, 1) for b in (0, 1)}  # (grounded object, truth object) -> IoUs
    for view in _train_views(run):
        vm = render_mask(run, view, fridge.index)
        truth = run.dataset.load_mask(next(f for f in run.dataset.frames if f.fid == view.name))
        assert vm.mask.shape == truth.shape[:2] and vm.rgb.dtype == np.uint8
        masks = {0: vm.mask, 1: vm.probs[..., 1] > 0.5}
        for (a, b), values in iou.items():
            values.append(mask_iou(masks[a], truth[..., b]) or 0.0)
    mean = {key: float(np.mean(v)) for key, v in iou.items()}
    assert mean[0, 0] > 0.4 and mean[0, 1] < 0.05, mean
    assert mean[1, 1] > mean[1, 0], mean


def test_cli_ground_writes_masks_and_overlays(scene, capsys):
    root, ds, run_dir, run = scene
    out = root / "g"
    fids = [run.dataset.frames[i].fid for i in run.views.train[:2]]
    rc = cli.main(["ground", str(run_dir), "open the refrigerator", "--views", ",".join(fids), "--out", str(out)])
    assert rc == 0
    assert "-> fridge door" in capsys.readouterr().out
    payload = json.loads((out / "ground.json").read_text())
    assert payload["object"] == "fridge door" and payload["command"]["value"] == 1.0
    assert [v["view"] for v in payload["views"]] == fids
    for fid in fids:
        mask = read_image_rgb(out / f"mask_{fid}.png")[..., 0]
        assert mask.shape == (36, 48) and set(np.unique(mask)) <= {0, 255}
        assert read_image_rgb(out / f"overlay_{fid}.png").shape == (36, 48, 3)
    report = json.loads((out / "reports" / "ground.json").read_text())
    assert report["status"] == "ok" and report["figures"]["object"] == "fridge door"
    assert cli.main(["ground", str(run_dir), "fridge", "--views", "99999", "--out", str(out)]) == 2
    assert "not a frame" in capsys.readouterr().err


def test_command_sets_the_grounded_state(scene):
    root, ds, run_dir, run = scene
    assert apply_command(run, "close the drawer") == {"top drawer": 0.0}
    assert apply_command(run, "half open the fridge") == {"fridge door": 0.5}
    from livescene.render import render_view

    view = _train_views(run, 1)[0]
    opened = render_view(run, view.c2w_gl, view.intrinsics, apply_command(run, "open the fridge"), time=view.time)
    closed = render_view(run, view.c2w_gl, view.intrinsics, apply_command(run, "close the fridge"), time=view.time)
    assert opened["states"][0] == 1.0 and closed["states"][0] == 0.0
    assert opened["states"][1] == closed["states"][1]  # the other object keeps its learned state


def test_run_trained_without_masks_is_refused(scene, tmp_path, capsys):
    from livescene.config import load_preset
    from livescene.trainer import train

    root, ds, run_dir, run = scene
    bare = tmp_path / "ds"
    shutil.copytree(ds, bare, ignore=shutil.ignore_patterns("masks"))
    cfg = load_preset("tiny")
    cfg.steps = 2
    train(bare, tmp_path / "run", cfg, device="cpu", show_progress=False)
    rc = cli.main(["ground", str(tmp_path / "run"), "the fridge", "--out", str(tmp_path / "g")])
    assert rc == 2
    assert "without object masks" in capsys.readouterr().err
    from livescene.trainer import load_run

    with pytest.raises(LiveSceneError, match="without object masks"):
        check_run_has_masks(load_run(tmp_path / "run", device="cpu"))


def test_render_command_hook(scene, capsys):
    """`livescene render RUN --command "open the fridge"` grounds the object and renders it open."""
    root, ds, run_dir, run = scene
    out = root / "r"
    assert cli.main(["render", str(run_dir), "--command", "open the fridge", "--frames", "0", "--out", str(out)]) == 0
    assert (out / f"{run.dataset.frames[0].fid}.png").exists()
    assert cli.main(["render", str(run_dir), "--command", "open the purple elephant", "--frames", "0",
                     "--out", str(out)]) == 2
    assert "no object matches" in capsys.readouterr().err
