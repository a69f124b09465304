"""recipes/profile_step.py: the step and render profile a GPU session runs first (here on the CPU, tiny)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from conftest import make_tiny_dataset

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "recipes"))


def test_profile_names_the_speed_and_the_costliest_operators(tmp_path, capsys):
    import profile_step

    from livescene.config import load_preset
    from livescene.trainer import train

    ds = make_tiny_dataset(tmp_path / "ds", n_frames=6)
    cfg = load_preset("tiny")
    cfg.steps, cfg.eval_every, cfg.ckpt_every = 3, 0, 0
    train(ds, tmp_path / "run", cfg, device="cpu", show_progress=False)
    assert profile_step.main([str(ds), "--preset", "tiny", "--steps", "4", "--device", "cpu", "--run",
                              str(tmp_path / "run"), "--out", str(tmp_path / "p.json")]) == 0
    rec = json.loads((tmp_path / "p.json").read_text())
    assert rec["device"] == "cpu" and rec["train"]["steps_per_s"] > 0 and rec["train"]["profiled_steps"] == 2
    assert rec["train"]["kernels"] is None and rec["train"]["device_busy_s"] is None  # no CUDA here
    assert len(rec["train"]["top"]) == 12 and all(r["self_s"] >= 0 for r in rec["train"]["top"])
    assert rec["render"]["size"] == [32, 24] and rec["render"]["wall_s"] > 0
    out = capsys.readouterr().out
    assert "steps/s" in out and "render: wall" in out
