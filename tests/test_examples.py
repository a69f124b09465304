"""The examples a user copies still run: `examples/own_video.sh` end to end on a small simulated capture (its
annotations standing in for the browser step)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_own_video_script_runs_end_to_end(tmp_path: Path):
    from interreal.synth import SynthConfig, write_capture

    cap = write_capture(SynthConfig(frames=24, width=240, height=180, parts=1, keyframe_every=8, seed=2),
                        tmp_path / "cap", progress=False)
    ds = tmp_path / "out" / "room"
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
           "KEYFRAMES": str(cap / "annotations" / "keyframes"), "LABELS": str(cap / "annotations" / "states.yaml"),
           "TRAIN_ARGS": "--preset tiny --steps 30 --device cpu --no-progress --threads 1"}
    r = subprocess.run(["bash", str(ROOT / "examples" / "own_video.sh"), str(cap / "video.mp4"), str(ds)],
                       env=env, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    assert (ds / "transforms.json").exists() and (ds / "reports" / "motions.json").exists()
    assert list((Path(f"{ds}.renders")).glob("*.png")) and (Path(f"{ds}.renders") / "sweep.mp4").exists()
    assert list(Path(f"{ds}.asset").glob("*.urdf"))
    assert f"livescene view {ds}.run" in r.stdout
