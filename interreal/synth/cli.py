"""`interreal synth OUT`: simulate a phone capture of an articulated room, with full ground truth."""

from __future__ import annotations

import argparse
from dataclasses import fields
from pathlib import Path

from ..errors import InputError
from .config import TEXTURES, SynthConfig, list_presets, load_preset, preset_description

EPILOG = """examples:
  interreal synth out/cap                                  # 300 frames, 640x480, fridge door + top drawer
  interreal synth out/small --preset small                 # 60 frames at 320x240 (quick)
  interreal synth out/cap --frames 120 --size 320x240 --seed 3 --parts 4
  interreal synth out/blur --preset stress-blur            # a stress preset (see the list below)
  interreal synth out/hard --texture low --motion-blur 0.6 --noise 4 --exposure-drift 0.2 \\
      --speed 2 --occluder 0.3 --parts 6
  interreal synth out/big --room-scale 1.6                 # a 9.6 x 8 m room, camera 1.6x further away
  interreal synth out/cap --truth-dataset out/ds           # also write a LiveScene dataset from the truth

presets (interreal/presets/*.yaml; --preset NAME or a YAML path; flags override them):
  {presets}

writes OUT/video.mp4 (H.264), OUT/gt/ (poses, intrinsics, depth, instance masks, states, names),
OUT/annotations/ (keyframe masks every 60th frame + first + last, states for ~10 % of frames).
Layout: docs/synth.md."""

# flag -> (SynthConfig field, help)
_FLAGS = {
    "--frames": ("frames", "number of video frames (default 300 = 10 s at 30 fps)"),
    "--seed": ("seed", "random seed: textures, camera path, schedules (default 0)"),
    "--parts": ("parts", "interactive parts, 1-10 (default 2: fridge door, top drawer)"),
    "--fps": ("fps", "frame rate (default 30)"),
    "--hfov": ("hfov_deg", "horizontal field of view in degrees (default 65)"),
    "--texture": ("texture", f"room surface texture: {' | '.join(TEXTURES)} (default photo)"),
    "--motion-blur": ("motion_blur", "shutter time as a fraction of the frame interval, 0-1 (default 0)"),
    "--noise": ("noise", "sensor noise std in 8-bit levels (default 0)"),
    "--exposure-drift": ("exposure_drift", "auto-exposure swing, e.g. 0.2 = +-20 %% (default 0)"),
    "--speed": ("speed", "camera speed multiplier (fast motion; default 1)"),
    "--jitter": ("jitter", "hand-shake scale (default 1)"),
    "--occluder": ("occluder", "fraction of frames a person walks across the view, 0-1 (default 0)"),
    "--articulation": ("articulation", "scale of each part's range of motion (default 1)"),
    "--room-scale": ("room_scale", "room floor plan and camera distance x this, 0.6-2.5; furniture keeps its size "
                                   "(default 1: 6 x 5 m; 0.7 small, 1.6 large)"),
    "--keyframe-every": ("keyframe_every", "annotated keyframe masks every N frames (+ first, last; default 60)"),
    "--label-fraction": ("label_fraction", "fraction of frames with annotated states (default 0.1)"),
    "--supersample": ("supersample", "S x S rays per pixel in the video (anti-aliasing, S^2 the cost; default 1)"),
    "--crf": ("crf", "H.264 quality, lower = better (default 18)"),
    "--threads": ("threads", "render threads (default 2)"),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.epilog = EPILOG.format(presets="\n  ".join(f"{n:<20} {preset_description(n)}" for n in list_presets()))
    p.add_argument("out", type=Path, help="output folder for the capture")
    p.add_argument("--preset", help="a preset name or YAML file of SynthConfig fields")
    p.add_argument("--size", help="frame size WxH (default 640x480)")
    types = {f.name: f.type for f in fields(SynthConfig)}
    for flag, (name, helptext) in _FLAGS.items():
        typ = {"int": int, "float": float, "str": str}[str(types[name])]
        kw = {"choices": TEXTURES} if name == "texture" else {}
        p.add_argument(flag, dest=name, type=typ, default=None, help=helptext, **kw)
    p.add_argument("--truth-dataset", type=Path, metavar="DS",
                   help="also write a LiveScene dataset from the truth to DS (320 px wide, or the capture size)")
    p.add_argument("--truth-size", metavar="WxH", help="image size of --truth-dataset (default: 320 px wide)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def config_from_args(args: argparse.Namespace) -> SynthConfig:
    settings = load_preset(args.preset) if args.preset else {}
    for _, (name, _) in _FLAGS.items():
        value = getattr(args, name, None)
        if value is not None:
            settings[name] = value
    if args.size:
        settings["width"], settings["height"] = _parse_size(args.size, "--size")
    return SynthConfig.from_dict(settings).check()


def _parse_size(text: str, flag: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"{flag} must look like 640x480 (got {text!r})") from None
    return w, h


def _truth_size(cfg: SynthConfig) -> tuple[int, int]:
    """320 px wide with the capture's aspect ratio (640x480 -> 320x240); never larger than the capture."""
    w = min(320, cfg.width)
    return w, max(8, int(round(cfg.height * w / cfg.width)))


def main(args: argparse.Namespace) -> int:
    from .capture import write_capture

    cfg = config_from_args(args)
    write_capture(cfg, args.out, progress=not args.quiet, log=print)
    if args.truth_dataset:
        from .truth import truth_dataset

        size = _parse_size(args.truth_size, "--truth-size") if args.truth_size else _truth_size(cfg)
        ds = truth_dataset(args.out, args.truth_dataset, size=size, progress=not args.quiet)
        print(f"wrote {ds}/ (LiveScene dataset from the truth, {size[0]}x{size[1]}): "
              f"check it with `interreal validate {ds}`")
    return 0
