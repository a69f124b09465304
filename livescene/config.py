"""Training configuration: dataclasses, YAML presets (`livescene/presets/*.yaml`) and scene-driven auto sizes.

A value of 0 for a resolution means "follow the scene" (`resolve_sizes`): plane resolutions come from the image
size, focal length and scene extent, the interaction axis and the per-frame variable from the frame count. The
parameter count never depends on the number of objects (a fixed number of object slots, `max_objects`).
`resolve(cfg, views)` is the one place a configuration meets its scene (sizes, near plane, object slots).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import sys
import typing
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, Protocol

import yaml

from .errors import ConfigError, LiveSceneError

PRESETS_DIR = Path(__file__).resolve().parent / "presets"


@dataclass
class ModelConfig:
    resolution: int = 0  # base spatial plane resolution of the radiance field (0 = auto)
    scales: list[int] = field(default_factory=lambda: [1, 2, 4])  # multipliers of `resolution`
    k_resolution: int = 0  # interaction-axis resolution (0 = auto)
    features: int = 16  # features per plane and scale
    hidden: int = 64
    geo_features: int = 15
    sh_degree: int = 4  # number of spherical-harmonic bands for the view direction (16 coefficients at 4)
    prob_resolution: int = 0  # interaction probability field planes (0 = auto)
    prob_features: int = 8
    prob_hidden: int = 64
    proposal_resolutions: list[int] = field(default_factory=lambda: [0, 0])  # one per proposal level (0 = auto)
    proposal_features: int = 8
    proposal_hidden: int = 64
    proposal_k: bool = True  # proposals read k too (needs the probability field at every level); False = 3-D
    # proposals that learn the envelope of all states (about 2x faster on CPU)
    var_resolution: int = 0  # per-frame variable line nodes (0 = half the number of frames)
    var_features: int = 4
    var_hidden: int = 32
    max_objects: int = 8  # object slots: the parameter count is independent of the scene's object count
    reject_threshold: float = 0.5  # s: samples whose best object probability is below s use the background k
    background_k: str = "slice"  # what rejected samples read on the k axis: "slice" = a node of their own (the
    # paper's "background feature"); "zero" = k = 0 as the official code does, which is also every object's state 0,
    # so space an object leaves when it moves must read as that object at every state or it contradicts itself
    mask_render: str = "auto"  # what the mask losses see per pixel: "logits" = sum of weight x logit as the
    # official code renders it; "probs" = sum of weight x per-sample probability, so a pixel is right only when the
    # samples that carry its colour (those whose k the field reads) are; "auto" = "probs" with rigid parts, else
    # "logits". With the k-axis alone, "probs" made per-sample probabilities sharp but a 15-minute run scored lower
    # (held-out PSNR / state MAE / mask IoU 30.3 / 0.039 / 0.870 against 30.6 / 0.024 / 0.889); with rigid parts
    # (true motions) it scored higher (29.6 / 0.017 / 0.82 and novel-state 25.1 against 27.3 / 0.016 / 0.80 / 21.9)
    mask_shapes: str = "detach"  # do the mask losses reach the density? "detach" = no, only ownership (the
    # paper's); "grad" = yes, moving light along each ray (not its amount) towards the samples its mask's owner owns.
    # With rigid parts (estimated motions, 15 min) "grad" fixed the fridge door's ownership where it is black and
    # close to the last cameras (a floater 0.1 units from them, owned by the static scene; mask IoU 0.72 -> 0.85,
    # novel-state 23.7 -> 24.1 dB) but cost 1.5 dB held-out (29.85 -> 28.40); only on object pixels: 27.96 / 22.5
    motion: str = "auto"  # rigid part motions (`articulation.json`, `interreal motions`): "auto" = rigid when the
    # dataset has them, "rigid" = required, "none" = the k-axis alone moves parts (the paper's model)
    part_k: str = "rest"  # what a rigid part's samples read on the k axis: "rest" = k 0 at every state (one
    # appearance, moved by the motion), "state" = its state (appearance may also change with the state)
    motion_grad: bool = False  # the colour and mask losses reach the per-frame states through the motions too
    background: str = "white"  # white | black | learned
    capacity: float = 1.0  # multiplies the auto resolutions (capacity sweeps)
    max_resolution: int = 256  # cap for the finest auto spatial resolution
    max_k_resolution: int = 16
    warp: str = "points"  # where the planes' cells go (`field.AxisWarp`): "points" = each axis follows the SfM
    # points' distribution (a real capture's box is mostly far walls), "off" = evenly over the box; a dataset
    # without a point cloud is even either way
    warp_uniform: float = 0.5  # under "points", the share of each axis spread evenly (1 = "off")
    appearance: str = "off"  # per-frame colour transform of the training renders (`livescene.appearance`): phone
    # auto-exposure and white balance; "gain" (per channel), "affine" (3x3 + bias) or "off"; new views render
    # neutral. Off by default: it did not help on the real laptop video (figures: docs/interfaces.md)
    appearance_frames: int = 0  # rows of the appearance table: the dataset's frame count (set by `resolve`)
    appearance_lr: float = 0.005  # peak learning rate of the appearance codes (the schedule of `lr`)


@dataclass
class SamplerConfig:
    proposal_samples: list[int] = field(default_factory=lambda: [64, 32])
    samples: int = 24  # final samples per ray
    anneal_steps: int = 1000  # proposal weight annealing (K-planes)
    anneal_slope: float = 10.0
    near: float = 0.05  # scene units: closest sample from a camera (at least; see near_auto)
    near_auto: float = 0.5  # near = max(near, this share of the closest SfM point depth any camera sees; 0 = off):
    # nothing filmed is nearer, and a floater in front of an untextured close-up has nowhere to sit


@dataclass
class LossConfig:
    rgb: float = 1.0  # the plain colour loss (always computed: the logs' training PSNR)
    rgb_trimmed: float = 0.0  # the trimmed colour loss (`losses.trimmed_mse`): `--set loss.rgb=0 --set loss.rgb_trimmed=1`
    # swaps it in; measured not to pay yet (docs/measurements.md 2026-12-04: -2.3 dB elsewhere, +0.5 at a person)
    trim: float = 0.2  # share of each batch's rays, largest colour error first, that the trimmed loss leaves out
    depth: float = 0.1  # only when the dataset has depth (ours do not by default)
    focal: float = 0.01
    focal_alpha: float = 0.5
    focal_gamma: float = 1.5
    repulsion: float = 0.001
    repulsion_k: float = 10.0
    var: float = 0.1  # Lvar: MSE on labelled (frame, object) pairs only
    var_smooth: float = 0.01  # smoothness of the per-frame variable line along time
    k_smooth: float = 0.1  # Laplacian along k on the field's k-planes
    k_smooth_proposal: float = 0.001
    l1_k: float = 0.001  # keeps k-planes near 1 (static content independent of k)
    l1_k_proposal: float = 0.0001
    plane_tv: float = 0.01
    plane_tv_proposal: float = 0.0001
    plane_tv_prob: float = 0.0001
    interlevel: float = 1.0
    distortion: float = 0.001
    appearance: float = 0.001  # pulls the appearance codes to identity (mean squared code per ray)


@dataclass
class TrainConfig:
    preset: str = "cpu"
    steps: int = 3000
    batch_rays: int = 1024
    lr: float = 0.02
    lr_final_ratio: float = 0.05
    warmup: int = 256
    keyframe_fraction: float = 0.1  # share of each ray batch drawn from frames with state labels
    error_rays: float = 0.5  # share of the other rays drawn where the colour error is (`data.ErrorMap`, 16-px tiles);
    # real laptop video, 10 min, two runs each: held-out 26.12 / 26.42 dB against 25.72 / 26.00 uniform. 0 = uniform
    measured_states: bool = True  # Lvar also holds each frame's state where `interreal motions` measured it from
    # the part's displacement (articulation.json `frame_states`), in place of that frame's label: eyeballed labels
    # are coarser than the geometry (the real laptop video: 0.25 apart on frames the geometry puts 14 deg apart)
    reg_every: int = 1  # plane regularisers every n steps (weight x n): they cost a full pass over every plane
    eval_every: int = 500
    log_every: int = 25
    ckpt_every: int = 500
    keep_checkpoints: int = 3
    holdout_every: int = 8  # every 8th frame is held out, never trained on
    holdout_offset: int = 4
    split: str = "ours"  # "official": hold out the official LiveScene eval frames instead (interreal.official)
    max_side: int = 0  # downscale images so the longer side is at most this (0 = as stored)
    eval_max_side: int = 160  # size of the periodic held-out eval render
    final_eval_frames: int = 4  # held-out frames averaged for the end-of-run PSNR (the low-fit warning reads it)
    final_eval_max_side: int = 640  # their render size: near full, as `livescene eval` renders
    seed: int = 0
    scene_box: list[float] = field(default_factory=list)  # x0 y0 z0 x1 y1 z1 world box (empty = from the dataset)
    max_divergence_retries: int = 3
    model: ModelConfig = field(default_factory=ModelConfig)
    sampler: SamplerConfig = field(default_factory=SamplerConfig)
    loss: LossConfig = field(default_factory=LossConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _update(obj: Any, values: Any, where: str) -> None:
    if values is None:
        return
    if not isinstance(values, dict):
        raise ConfigError(f"{where or 'the configuration'}: expected a group of settings (KEY: VALUE), got {values!r}")
    names = {f.name: f for f in fields(obj)}
    hints = typing.get_type_hints(type(obj))
    for key, value in values.items():
        path = f"{where}.{key}" if where else str(key)
        if key not in names:
            close = difflib.get_close_matches(str(key), names, n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise ConfigError(f"unknown setting '{path}'{hint}; known{' in ' + where if where else ''}: "
                              f"{', '.join(sorted(names))}")
        current = getattr(obj, key)
        if is_dataclass(current):
            _update(current, value, path)
        else:
            setattr(obj, key, _coerce(value, hints[key], path))


_TRUE, _FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")


def _coerce(value: Any, kind: Any, where: str) -> Any:
    """`value` as the field's annotated type (int, float, bool, str, list[int], list[float]); a value that is not
    one (0.5 for a count, "maybe" for a switch, NaN for a weight) is a ConfigError naming the setting."""
    if typing.get_origin(kind) is list:
        (item,) = typing.get_args(kind)
        items = value if isinstance(value, (list, tuple)) else [v for v in str(value).split(",") if v.strip()]
        return [_coerce(v, item, f"{where}[{i}]") for i, v in enumerate(items)]
    if kind is bool:
        if isinstance(value, bool):
            return value
        text = str(value).strip().lower()
        if text in _TRUE or text in _FALSE:
            return text in _TRUE
        raise ConfigError(f"{where}: {value!r} is not true or false")
    if kind is int:
        if isinstance(value, bool):
            raise ConfigError(f"{where}: expected a whole number, got {value!r}")
        if isinstance(value, int):
            return value
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}: expected a whole number, got {value!r}") from None
        if not math.isfinite(number) or number != int(number):
            raise ConfigError(f"{where}: expected a whole number, got {value!r}")
        return int(number)
    if kind is float:
        if isinstance(value, bool):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}: expected a number, got {value!r}") from None
        if not math.isfinite(number):
            raise ConfigError(f"{where}: {value!r} is not a finite number")
        return number
    if kind is str:
        if isinstance(value, bool):  # YAML 1.1 reads a bare off / on (no / yes) as a boolean: the word was meant
            return "on" if value else "off"
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected text, got {value!r}")
        return value
    return value


# allowed values and ranges, checked before training starts (`check_config`); a setting out of range would
# otherwise surface as "training diverged" or a crash deep inside the model
CHOICES: dict[str, tuple[str, ...]] = {
    "model.background_k": ("slice", "zero"),
    "model.mask_render": ("auto", "logits", "probs"),
    "model.mask_shapes": ("detach", "grad"),
    "model.motion": ("auto", "rigid", "none"),
    "model.part_k": ("rest", "state"),
    "model.background": ("white", "black", "learned"),
    "model.appearance": ("off", "gain", "affine"),
    "split": ("ours", "official"),
}
_POS, _NONNEG, _ONE, _UNIT = (0.0, None, True), (0.0, None, False), (1.0, None, False), (0.0, 1.0, False)
RANGES: dict[str, tuple[float | None, float | None, bool]] = {  # path: (low, high, low excluded)
    "steps": _ONE, "batch_rays": _ONE, "lr": _POS, "lr_final_ratio": _UNIT, "warmup": _NONNEG,
    "keyframe_fraction": _UNIT, "error_rays": _UNIT, "reg_every": _ONE, "eval_every": _NONNEG, "log_every": _ONE,
    "ckpt_every": _NONNEG, "keep_checkpoints": _ONE, "holdout_every": _NONNEG, "holdout_offset": _NONNEG,
    "max_side": _NONNEG, "eval_max_side": _ONE, "final_eval_frames": _NONNEG, "final_eval_max_side": _ONE,
    "seed": _NONNEG, "max_divergence_retries": _NONNEG,
    "model.resolution": _NONNEG, "model.scales": _ONE, "model.k_resolution": _NONNEG, "model.features": _ONE,
    "model.hidden": _ONE, "model.geo_features": _ONE, "model.sh_degree": (1.0, 4.0, False),
    "model.prob_resolution": _NONNEG, "model.prob_features": _ONE, "model.prob_hidden": _ONE,
    "model.proposal_resolutions": _NONNEG, "model.proposal_features": _ONE, "model.proposal_hidden": _ONE,
    "model.var_resolution": _NONNEG, "model.var_features": _ONE, "model.var_hidden": _ONE,
    "model.max_objects": _ONE, "model.reject_threshold": _UNIT, "model.capacity": _POS,
    "model.max_resolution": (8.0, None, False), "model.max_k_resolution": (2.0, None, False),
    "model.appearance_lr": _POS,
    "sampler.proposal_samples": _ONE, "sampler.samples": _ONE, "sampler.anneal_steps": _NONNEG,
    "sampler.anneal_slope": _POS, "sampler.near": _POS, "sampler.near_auto": _NONNEG,
    "loss.focal_alpha": _UNIT, "loss.trim": (0.0, 0.9, False),
}
# "0 = auto" sizes: 0, or at least 2 nodes (one node cannot interpolate)
AUTO_SIZES = ("model.resolution", "model.k_resolution", "model.prob_resolution", "model.proposal_resolutions",
              "model.var_resolution")


def _leaves(obj: Any, prefix: str = "") -> list[tuple[str, Any]]:
    out = []
    for f in fields(obj):
        value = getattr(obj, f.name)
        path = f"{prefix}{f.name}"
        out += _leaves(value, path + ".") if is_dataclass(value) else [(path, value)]
    return out


def check_config(cfg: TrainConfig) -> TrainConfig:
    """Every setting of the right type and in range (ConfigError naming the first that is not); returns cfg.

    Runs before training, so a bad setting is named instead of showing up as a diverged loss."""
    for path, value in _leaves(cfg):
        group, _, name = path.rpartition(".")
        owner = _resolve(cfg, group)
        kind = typing.get_type_hints(type(owner))[name]
        _coerce(value, kind, path)  # type (a preset or checkpoint may bypass the overrides' coercion)
        if path in CHOICES and value not in CHOICES[path]:
            raise ConfigError(f"setting {path} = {value!r}: choose one of {', '.join(CHOICES[path])}")
        items = value if isinstance(value, list) else [value]
        low, high, strict = RANGES.get(path, _NONNEG if kind in (float, int) or path.startswith("loss.") else
                                       (None, None, False))
        for v in items:
            if not isinstance(v, (int, float)) or isinstance(v, bool):
                continue
            if path in AUTO_SIZES and v == 1:
                raise ConfigError(f"setting {path} = {value}: use 0 (automatic) or at least 2")
            if (low is not None and (v < low or (strict and v == low))) or (high is not None and v > high):
                rng = (f"> {low:g}" if strict else f">= {low:g}") if high is None else f"in [{low:g}, {high:g}]"
                raise ConfigError(f"setting {path} = {value}: must be {rng}")
    if not cfg.model.scales:
        raise ConfigError("model.scales is empty: give at least one scale, e.g. [1, 2]")
    if len(cfg.sampler.proposal_samples) != len(cfg.model.proposal_resolutions) or not cfg.sampler.proposal_samples:
        raise ConfigError(f"sampler.proposal_samples {cfg.sampler.proposal_samples} needs one count per proposal "
                          f"level of model.proposal_resolutions {cfg.model.proposal_resolutions}")
    if cfg.scene_box:
        box = cfg.scene_box
        if len(box) != 6:
            raise ConfigError(f"scene_box needs 6 numbers (x0 y0 z0 x1 y1 z1), got {box}")
        if not all(lo < hi for lo, hi in zip(box[:3], box[3:])):
            raise ConfigError(f"scene_box {box}: each of x0 y0 z0 must be below x1 y1 z1")
    return cfg


def _resolve(cfg: Any, group: str) -> Any:
    for part in filter(None, group.split(".")):
        cfg = getattr(cfg, part)
    return cfg


def from_dict(values: dict[str, Any]) -> TrainConfig:
    cfg = TrainConfig()
    _update(cfg, values, "")
    return cfg


def preset_names() -> list[str]:
    return sorted(p.stem for p in PRESETS_DIR.glob("*.yaml"))


def load_preset(name: str | Path) -> TrainConfig:
    """A preset by name (`cpu`, `gpu`, `tiny`) or a YAML file path; unknown keys are an error."""
    path = Path(name)
    if not path.suffix:
        path = PRESETS_DIR / f"{name}.yaml"
    if not path.exists():
        raise LiveSceneError(f"preset {name!r} not found; choose from {', '.join(preset_names())} or give a YAML file")
    try:
        values = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise ConfigError(f"preset {path} is not readable YAML: {_one_line(exc)}") from exc
    if not isinstance(values, dict):
        raise ConfigError(f"preset {path}: expected settings (KEY: VALUE), got {type(values).__name__}")
    values.setdefault("preset", path.stem)
    try:
        return from_dict(values)
    except ConfigError as exc:
        raise ConfigError(f"preset {path}: {exc}") from exc


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def apply_overrides(cfg: TrainConfig, pairs: list[str]) -> TrainConfig:
    """`--set model.features=32 loss.var=0.5` style overrides."""
    for pair in pairs or []:
        if "=" not in pair:
            raise ConfigError(f"--set expects KEY=VALUE (e.g. model.features=32), got {pair!r}")
        key, value = pair.split("=", 1)
        nested: dict[str, Any] = {}
        node = nested
        parts = key.strip().split(".")
        if not all(parts):
            raise ConfigError(f"--set {pair!r}: {key!r} is not a setting name (e.g. model.features=32)")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        try:
            node[parts[-1]] = yaml.safe_load(value)
        except yaml.YAMLError:
            node[parts[-1]] = value  # not YAML: the setting's own type check names it
        try:
            _update(cfg, nested, "")
        except ConfigError as exc:
            raise ConfigError(f"--set {pair}: {exc}") from exc
    return cfg


# ----------------------------------------------------------------------------------------------------------------
# Scene-driven sizes
# ----------------------------------------------------------------------------------------------------------------
@dataclass
class SceneInfo:
    """What the auto sizes depend on."""

    width: int
    height: int
    focal: float
    extent: float  # longest side of the scene box (world units)
    distance: float  # median camera distance to the box centre
    n_frames: int  # frames of the dataset (time span of the per-frame variable)


def _round8(x: float) -> int:
    return max(8, int(round(x / 8.0)) * 8)


def resolve_sizes(cfg: ModelConfig, scene: SceneInfo) -> ModelConfig:
    """Concrete sizes for every `0 = auto` entry; returns a new ModelConfig.

    The finest spatial scale gets about one cell per image pixel at the typical viewing distance
    (pixels spanned by the box), times `capacity`, capped by `max_resolution`.
    """
    out = dataclasses.replace(cfg, scales=list(cfg.scales), proposal_resolutions=list(cfg.proposal_resolutions))
    top = max(out.scales)
    if out.resolution <= 0:
        pixels_across = scene.extent * scene.focal / max(scene.distance, 1e-6)
        pixels_across = min(pixels_across, 1.5 * max(scene.width, scene.height))
        finest = min(pixels_across * cfg.capacity, cfg.max_resolution * cfg.capacity)
        out.resolution = max(8, _round8(finest / top))
    if out.k_resolution <= 0:
        out.k_resolution = int(min(cfg.max_k_resolution, max(4, math.ceil(scene.n_frames / 10))))
    if out.prob_resolution <= 0:
        out.prob_resolution = out.resolution
    out.proposal_resolutions = [
        r if r > 0 else max(16, _round8(out.resolution * (0.5 if i == 0 else 1.0)))
        for i, r in enumerate(out.proposal_resolutions)
    ]
    if out.var_resolution <= 0:
        out.var_resolution = max(2, scene.n_frames // 2)
    if out.appearance != "off":  # one code per frame, whatever was asked: the table is indexed by frame
        out.appearance_frames = scene.n_frames
    return out


class SceneViews(Protocol):
    """What `resolve` reads of a dataset's views (`livescene.data.Views`)."""

    @property
    def n_objects(self) -> int: ...

    def scene_info(self) -> SceneInfo: ...

    def closest_depth(self) -> float | None: ...  # nearest SfM point any camera sees (None: no point cloud)


def resolve(cfg: TrainConfig, views: SceneViews) -> TrainConfig:
    """A copy of `cfg` with everything that follows the scene made concrete: the `0 = auto` sizes
    (`resolve_sizes`), the near plane (`sampler.near_auto` x the closest point depth, never below `near`) and
    enough object slots for the scene's objects. Resolving a resolved config changes nothing."""
    cfg = from_dict(cfg.to_dict())
    cfg.model = resolve_sizes(cfg.model, views.scene_info())
    if cfg.sampler.near_auto > 0:
        closest = views.closest_depth()
        if closest is not None:
            cfg.sampler.near = max(cfg.sampler.near, round(cfg.sampler.near_auto * closest, 4))
    n = views.n_objects
    if n > cfg.model.max_objects:
        # more objects than slots: widen the slots (only the probability field's and the variable's input and
        # output layers grow, a few hundred parameters per object) rather than refuse the scene
        print(f"livescene train: {n} objects > {cfg.model.max_objects} object slots: using {n} slots",
              file=sys.stderr)
        cfg.model.max_objects = n
    return cfg
