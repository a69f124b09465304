"""Plain, low-texture captures (issue 59) on the simulator made as hard as real ones: painted furniture and parts,
exposure drift, sensor noise, a person walking across, an arm holding each moving part. No usable frame is skipped,
every frame gets a camera in one model, no part is given a motion it does not have."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

HARD = {"furniture": "plain", "exposure_drift": 0.2, "noise": 3.0, "occluder": 0.3, "arm": True}


@pytest.mark.slow
def test_a_plain_hard_capture_keeps_every_frame_and_poses_it_in_one_model(tmp_path: Path):
    from interreal.process import process
    from interreal.synth import SynthConfig, write_capture

    cap = write_capture(SynthConfig(frames=48, width=320, height=240, seed=2, **HARD), tmp_path / "cap", progress=False)
    ds = tmp_path / "ds"
    fig = process(cap / "video.mp4", ds, keyframes=cap / "annotations" / "keyframes",
                  labels=cap / "annotations" / "states.yaml", motions=False)
    frames = json.loads((ds / "reports" / "frames.json").read_text())["figures"]
    assert not frames.get("unusable_indices"), frames.get("unusable_indices")  # plain is not blank
    poses = json.loads((ds / "reports" / "poses.json").read_text())["figures"]
    assert fig["registered"] == fig["total"] == 48
    assert poses["models"][0] == 48  # one model holds every frame
