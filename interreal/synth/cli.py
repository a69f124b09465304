"""`interreal synth OUT`: simulate a phone capture of an articulated room, with full ground truth."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import InputError
from ..options import add_flags, given_values
from .capture import write_capture
from .config import SynthConfig, list_presets, load_preset, preset_description
from .truth import truth_dataset

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

def add_arguments(p: argparse.ArgumentParser) -> None:
    p.epilog = EPILOG.format(presets="\n  ".join(f"{n:<20} {preset_description(n)}" for n in list_presets()))
    p.add_argument("out", type=Path, help="output folder for the capture")
    p.add_argument("--preset", help="a preset name or YAML file of SynthConfig fields")
    p.add_argument("--size", help="frame size WxH (default 640x480)")
    add_flags(p, SynthConfig)
    p.add_argument("--truth-dataset", type=Path, metavar="DS",
                   help="also write a LiveScene dataset from the truth to DS (320 px wide, or the capture size)")
    p.add_argument("--truth-size", metavar="WxH", help="image size of --truth-dataset (default: 320 px wide)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def config_from_args(args: argparse.Namespace) -> SynthConfig:
    settings = load_preset(args.preset) if args.preset else {}
    settings.update(given_values(SynthConfig, args))  # flags override the preset
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
    cfg = config_from_args(args)
    write_capture(cfg, args.out, progress=not args.quiet, log=print)
    if args.truth_dataset:
        size = _parse_size(args.truth_size, "--truth-size") if args.truth_size else _truth_size(cfg)
        ds = truth_dataset(args.out, args.truth_dataset, size=size, progress=not args.quiet)
        print(f"wrote {ds}/ (LiveScene dataset from the truth, {size[0]}x{size[1]}): "
              f"check it with `interreal validate {ds}`")
    return 0
