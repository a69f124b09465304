"""`interreal synth`: a simulated phone capture of an articulated room, with full ground truth.

API (see docs/synth.md and docs/interfaces.md):
    cfg = SynthConfig(frames=300, width=640, height=480, seed=0, parts=2)
    scene = build_scene(cfg); scene.render(c2w_gl, states) -> RenderResult(rgb, depth, instance)
    write_capture(cfg, out_dir); Capture.open(out_dir); truth_dataset(capture_dir, ds_dir, size=(320, 240))
"""

from .capture import Capture, write_capture
from .config import SynthConfig, list_presets, load_preset
from .scene import RenderResult, Scene, build_scene
from .truth import truth_articulation, truth_dataset

__all__ = ["SynthConfig", "build_scene", "Scene", "RenderResult", "write_capture", "Capture", "truth_dataset",
           "truth_articulation", "list_presets", "load_preset"]

