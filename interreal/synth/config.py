"""SynthConfig: every knob of the simulated capture, plus named presets (interreal/presets/*.yaml).

One dataclass so that a capture is reproducible from `gt/meta.json` alone: `SynthConfig.from_dict(meta["config"])`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import yaml

from ..errors import InputError
from ..options import option

PRESETS_DIR = Path(__file__).resolve().parent.parent / "presets"
TEXTURES = ("photo", "low", "none")
FURNITURE = ("photo", "plain")
MAX_PARTS = 10
MIN_ROOM_SCALE = 0.65  # smaller: the back-wall furniture and the camera's arc no longer fit in the room
MAX_ROOM_SCALE = 2.5  # truth depth PNGs hold up to 16.4 m


@dataclass
class SynthConfig:
    """What to simulate. Defaults: a 10 s, 640x480 phone clip of a room with a fridge door and a drawer. The fields
    declared with `option` are the flags of `interreal synth`."""

    frames: int = option(300, "number of video frames (300 = 10 s at 30 fps)")
    width: int = 640
    height: int = 480
    seed: int = option(0, "random seed: textures, camera path, schedules")
    parts: int = option(2, "interactive parts, 1-10 (2: fridge door, top drawer; then microwave door, ...)")
    fps: float = option(30.0, "frame rate")
    hfov_deg: float = option(65.0, "horizontal field of view of the (undistorted) pinhole in degrees", flag="--hfov")
    k1: float = -0.05  # radial distortion, OpenCV model
    k2: float = 0.01
    texture: str = option("photo", "room surface texture (walls, floor, ceiling)", choices=TEXTURES)
    texture_contrast: float = 0.8  # photo contrast around its mean (lower = easier to fit for a radiance field)
    furniture: str = option("photo", "furniture and part surfaces: photo, or plain (each surface one painted colour, "
                                     "as most appliances and cabinet doors are; the room keeps its texture)",
                            choices=FURNITURE)
    motion_blur: float = option(0.0, "shutter time as a fraction of the frame interval, 0-1 (0 = sharp)")
    blur_samples: int = 5  # sub-frame renders averaged when motion_blur > 0
    supersample: int = option(1, "S x S rays per pixel in the video (anti-aliasing, S^2 the cost)")
    noise: float = option(0.0, "sensor noise std in 8-bit levels (3 = mild, 8 = strong)")
    exposure_drift: float = option(0.0, "auto-exposure swing, e.g. 0.2 = +-20 %")
    speed: float = option(1.0, "camera speed multiplier (fast motion: the arc is swept back and forth)")
    jitter: float = option(1.0, "hand-shake scale (0 = tripod-smooth)")
    occluder: float = option(0.0, "fraction of frames a person walks across the view, 0-1")
    arm: bool = option(False, "a hand (palm, fingers, thumb: one a hand model finds) and a sleeved forearm reach in "
                              "from the image's right edge and hold each part while it moves (in front of it, as in "
                              "a real capture)")
    paint_occluders: bool = option(False, "keyframes paint the person and the arm as the ignore class, as a careful "
                                          "user does in the annotate app (otherwise they are left as background)")
    articulation: float = option(1.0, "scale of each part's range of motion (angle / slide length)")
    room_scale: float = option(1.0, "room floor plan and camera distance x this, 0.65-2.5; furniture keeps its size "
                                    "(1: 6 x 5 m; 0.7 small, 1.6 large)")
    keyframe_every: int = option(60, "annotated keyframe masks every N frames (+ first, last, and where a part they "
                                     "miss shows most)")
    label_fraction: float = option(0.1, "fraction of frames with annotated states (plus the keyframes)")
    crf: int = option(17, "H.264 quality, lower = better (17 without x264's macroblock tree ~ 18 with it)")
    threads: int = option(2, "render threads")

    def check(self) -> "SynthConfig":
        """Raise InputError on settings that cannot produce a capture; returns self."""
        problems = []
        if self.frames < 2:
            problems.append(f"frames must be >= 2 (got {self.frames})")
        if self.width < 16 or self.height < 16 or self.width % 2 or self.height % 2:
            problems.append(f"size must be even and >= 16 px for H.264 (got {self.width}x{self.height})")
        if not 1 <= self.parts <= MAX_PARTS:
            problems.append(f"parts must be in 1..{MAX_PARTS} (got {self.parts})")
        if self.texture not in TEXTURES:
            problems.append(f"texture must be one of {TEXTURES} (got {self.texture!r})")
        if self.furniture not in FURNITURE:
            problems.append(f"furniture must be one of {FURNITURE} (got {self.furniture!r})")
        if not 20.0 <= self.hfov_deg <= 120.0:
            problems.append(f"hfov_deg must be in [20, 120] (got {self.hfov_deg})")
        for name in ("motion_blur", "occluder"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                problems.append(f"{name} must be in [0, 1] (got {getattr(self, name)})")
        for name in ("noise", "exposure_drift", "jitter", "texture_contrast"):
            if getattr(self, name) < 0:
                problems.append(f"{name} must be >= 0 (got {getattr(self, name)})")
        if self.speed <= 0 or self.articulation <= 0 or self.fps <= 0:
            problems.append("speed, articulation and fps must be > 0")
        if not MIN_ROOM_SCALE <= self.room_scale <= MAX_ROOM_SCALE:
            problems.append(f"room_scale must be in [{MIN_ROOM_SCALE}, {MAX_ROOM_SCALE}] (got {self.room_scale}): "
                            "below, the furniture and the camera path do not fit; above, depth exceeds the 16 m the depth PNGs hold")
        if min(self.keyframe_every, self.blur_samples, self.threads, self.supersample) < 1:
            problems.append("keyframe_every, blur_samples, supersample and threads must be >= 1")
        if not 0.0 <= self.label_fraction <= 1.0:
            problems.append(f"label_fraction must be in [0, 1] (got {self.label_fraction})")
        if problems:
            raise InputError("invalid synth settings: " + "; ".join(problems))
        return self

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "SynthConfig":
        """Build from a dict (a preset or meta.json); unknown keys are an error so typos do not pass silently."""
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(d) - set(known))
        if unknown:
            raise InputError(f"unknown synth setting(s) {unknown}; known: {sorted(known)}")
        kwargs = {}
        for k, v in d.items():
            typ = type(getattr(cls(), k))
            kwargs[k] = typ(v)
        return cls(**kwargs)


def list_presets() -> list[str]:
    return sorted(p.stem for p in PRESETS_DIR.glob("*.yaml"))


def preset_description(name: str) -> str:
    """The `description:` line of a preset (shown in `interreal synth --help`)."""
    try:
        with open(PRESETS_DIR / f"{name}.yaml", encoding="utf-8") as fh:
            return str((yaml.safe_load(fh) or {}).get("description", ""))
    except (OSError, yaml.YAMLError):
        return ""


def load_preset(name_or_path: str | Path) -> dict[str, Any]:
    """Settings of a preset: a name from interreal/presets/ (e.g. "small", "stress-blur") or a YAML file path."""
    path = Path(name_or_path)
    if not path.suffix:
        path = PRESETS_DIR / f"{name_or_path}.yaml"
    if not path.exists():
        raise InputError(f"no synth preset {name_or_path!r}; choose from {', '.join(list_presets())} or give a YAML path")
    try:
        with open(path, encoding="utf-8") as fh:
            data = yaml.safe_load(fh) or {}
    except yaml.YAMLError as exc:
        raise InputError(f"preset {path} is not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise InputError(f"preset {path} must be a mapping of SynthConfig fields")
    data.pop("description", None)
    SynthConfig.from_dict(data)  # reject unknown keys early
    return data
