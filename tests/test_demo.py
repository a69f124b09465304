"""The demo's whole path at a tiny size: simulate -> process -> train -> eval -> render, with truth scores."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import pytest

from interreal.demo import DemoConfig, format_table, run_demo


@pytest.mark.slow
def test_demo_pipeline_tiny(tmp_path: Path):
    cfg = DemoConfig(out=tmp_path / "demo", frames=30, size=(320, 240), train_long_side=320, preset="tiny",
                     steps=60, minutes=1.0, sweep_frames=3, eval_frames=2, eval_scale=0.5, novel=1,
                     device="cpu")
    rows = run_demo(cfg)
    stages = [r["stage"] for r in rows]
    assert stages == ["simulate", "frames", "masks", "poses", "labels", "motions", "train", "eval", "render", "total"]
    by = {r["stage"]: r["quality"] for r in rows}
    assert "30/30 registered" in by["poses"] or "29/30 registered" in by["poses"]
    assert "mask IoU" in by["masks"] and "PSNR" in by["eval"]
    assert "fridge door" in by["motions"]  # measured, or named as not measured (30 frames may not follow it)
    ev = json.loads((cfg.out / "eval.json").read_text())
    assert ev["psnr"] > 10.0 and ev["state_mae"] is not None
    sweeps = sorted((cfg.out / "renders").glob("sweep_*.mp4"))
    assert len(sweeps) == 2 and all(p.stat().st_size > 1000 for p in sweeps)
    assert "from the view that shows it best" in by["render"] and "fridge door" in by["render"]
    strip = cv2.imread(str(cfg.out / "renders" / "sweep_strip.png"))
    assert strip is not None and strip.shape[1] == 4 * 200 and strip.shape[0] > 100  # 2 objects x 4 states
    table = (cfg.out / "demo.md").read_text()
    assert table == format_table(rows) + "\n"
    # the README's grounding example on the demo's run: the capture's prompts travelled into the dataset
    from interreal.dataset import read_prompts
    from livescene import cli as livescene_cli

    assert "keeps food cold" in read_prompts(cfg.out / "dataset").get("fridge door", "")
    assert livescene_cli.main(["ground", str(cfg.out / "run"), "the thing that keeps food cold", "--out",
                               str(tmp_path / "g")]) == 0
    assert json.loads((tmp_path / "g" / "ground.json").read_text())["object"] == "fridge door"
    assert livescene_cli.main(["ground", str(cfg.out / "run"), "the dishwasher"]) == 2  # not in the scene
    # a second run resumes: the capture is reused
    from interreal.demo import simulate

    again = DemoConfig(**{**cfg.__dict__, "rows": []})
    simulate(again)
    assert "reused" in again.rows[0]["quality"]


def test_demo_rejects_keyframes_without_video(tmp_path: Path):
    r = subprocess.run([sys.executable, "-m", "interreal", "demo", str(tmp_path / "x"), "--keyframes", str(tmp_path)],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "--keyframes / --labels go with --video" in r.stderr and "Traceback" not in r.stderr


def test_demo_missing_video_is_a_clear_error(tmp_path: Path):
    r = subprocess.run([sys.executable, "-m", "interreal", "demo", str(tmp_path / "x"), "--video",
                        str(tmp_path / "nope.mp4")], capture_output=True, text=True)
    assert r.returncode == 2 and "does not exist" in r.stderr


@pytest.mark.slow
def test_demo_on_your_own_video_reports_without_truth(tmp_path: Path, capsys):
    """`interreal demo --video --keyframes --labels`: the same path with no simulator behind it. The table shows what
    the stages measured themselves (no 'n/a' truth figures) and the stages' warnings reach the terminal."""
    from interreal.synth import SynthConfig, write_capture

    cap = tmp_path / "cap"
    write_capture(SynthConfig(frames=30, width=320, height=240, seed=1), cap)
    cfg = DemoConfig(out=tmp_path / "demo", video=cap / "video.mp4", keyframes=cap / "annotations" / "keyframes",
                     labels=cap / "annotations" / "states.yaml", train_long_side=320, preset="tiny", steps=40,
                     minutes=1.0, sweep_frames=2, eval_frames=2, eval_scale=0.5, novel=1, device="cpu")
    rows = run_demo(cfg)
    by = {r["stage"]: r["quality"] for r in rows}
    assert "simulate" not in by and "registered" in by["poses"]
    assert "keyframes ->" in by["masks"] and "mean confidence" in by["masks"]
    assert "PSNR" in by["eval"] and "no truth" in by["eval"]
    assert "n/a" not in " ".join(by.values()) and "state MAE" not in by["eval"]
    ev = json.loads((cfg.out / "eval.json").read_text())
    assert ev["psnr"] > 5.0 and ev.get("state_mae") is None
    out = capsys.readouterr().out
    for stage in ("frames", "masks", "poses", "labels"):
        report = json.loads((cfg.out / "dataset" / "reports" / f"{stage}.json").read_text())
        for w in report["warnings"]:
            assert f"warning ({stage}): {w['message']}" in out
