"""Quickstart with the Python API: simulate a small capture, make a dataset, train briefly, render a state sweep.

    .venv/bin/python examples/quickstart.py out/quick      # about 5 minutes on 2 CPU cores
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from interreal.dataset import validate
from interreal.process import process
from interreal.synth import SynthConfig, write_capture
from livescene.config import load_preset
from livescene.render import render_view, write_video
from livescene.trainer import load_run, train

out = Path(sys.argv[1] if len(sys.argv) > 1 else "out/quick")

# 1. a simulated phone capture: video + truth + the sparse input a person would give
cap = out / "capture"
if not (cap / "gt" / "meta.json").exists():
    write_capture(SynthConfig(frames=90, width=640, height=480, seed=0), cap)

# 2. video -> dataset: frames, masks propagated from the keyframe annotations, poses (pycolmap), state labels
ds = out / "dataset"
process(cap / "video.mp4", ds, keyframes=cap / "annotations" / "keyframes",
        labels=cap / "annotations" / "states.yaml", long_side=320)
result = validate(ds)
assert result.ok, result.problems

# 3. train the interactive radiance field (the CPU preset, capped at 3 minutes here)
cfg = load_preset("cpu")
train(ds, out / "run", cfg, max_minutes=3)

# 4. render one camera while opening the first object from 0 to 1
run = load_run(out / "run")
views = run.views
i = views.held_out[0]
name = views.names[0]
frames = []
for v in np.linspace(0, 1, 16):
    r = render_view(run, views.c2w_gl[i], views.intrinsics[i], {name: float(v)}, time=float(views.times[i]))
    frames.append((r["rgb"] * 255).astype(np.uint8))
write_video(out / f"sweep_{name.replace(' ', '_')}.mp4", frames, fps=8)
print(f"done: {out}")
