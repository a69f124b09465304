"""`interreal synth`: a simulated phone capture of an articulated room, with full ground truth.

API (see docs/synth.md and docs/interfaces.md):
    cfg = SynthConfig(frames=300, width=640, height=480, seed=0, parts=2)
    scene = build_scene(cfg); scene.render(c2w_gl, states) -> RenderResult(rgb, depth, instance)
    write_capture(cfg, out_dir); Capture.open(out_dir); truth_dataset(capture_dir, ds_dir, size=(320, 240))
"""

from .config import SynthConfig, list_presets, load_preset
from .scene import RenderResult, Scene, build_scene

__all__ = ["SynthConfig", "build_scene", "Scene", "RenderResult", "write_capture", "Capture", "truth_dataset",
           "truth_articulation", "list_presets", "load_preset"]


def __getattr__(name: str):
    # capture / truth pull in PyAV; load them on first use
    if name in ("write_capture", "Capture"):
        from . import capture

        return getattr(capture, name)
    if name in ("truth_dataset", "truth_articulation"):
        from . import truth

        return getattr(truth, name)
    raise AttributeError(name)
