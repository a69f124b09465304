"""The simulated room: geometry, interactive parts, textures, the person-like occluder, and `Scene.render`.

World frame: metres, z up, the room spans x in [-3, 3], y in [-2.5, 2.5], z in [0, 2.8]; the furniture stands
along the back wall (y = 2.5) and the back of the side walls, the camera moves in the front half.
`room_scale` s resizes the room about the back wall (x in [-3s, 3s], y in [2.5 - 5s, 2.5], ceiling 2.8 max(1, s))
and the camera's distance; furniture keeps its real size: the back-wall group stays put, side-wall furniture
moves with its wall, and furniture that no longer fits (s < 1) is left out (see `_fit_room`).
Every part is a small set of boxes moved rigidly by its state: a hinge rotates about an axis through a pivot,
a slide translates. All ten parts always exist; the first `cfg.parts` of them move (the others stay closed and
are static scenery), so `--parts` changes what is interactive, not the room.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property

import cv2
import numpy as np

from ..conventions import opencv_to_opengl, opengl_to_opencv
from ..dataset import Articulation, Intrinsics
from ..errors import InputError
from .body import arm_prims
from .camera import CameraPath, phone_intrinsics
from .config import SynthConfig
from .render import OCCLUDER, Lighting, Prims, RayCaster
from .schedule import PartSchedule, make_schedules
from .textures import TILE, Atlas, TextureMaker

ROOM_MIN = np.array([-3.0, -2.5, 0.0])
ROOM_MAX = np.array([3.0, 2.5, 2.8])
GROUP_TARGET = np.array([-0.15, 2.05, 0.9])  # what the camera looks at (centre of the furniture group)
ARC_CENTRE = np.array([0.0, 1.45])


@dataclass
class BoxSpec:
    """An axis-aligned box (in its rest pose) with a texture per face (-x, +x, -y, +y, -z, +z)."""

    lo: np.ndarray
    hi: np.ndarray
    tile: np.ndarray  # (6,) int
    scale: np.ndarray  # (6,) metres per tile
    offset: np.ndarray  # (6, 2)
    wall: str = "back"  # the wall it stands against: back | left | right (it moves with that wall, `_fit_room`)

    @property
    def centre(self) -> np.ndarray:
        return (self.lo + self.hi) / 2

    @property
    def half(self) -> np.ndarray:
        return (self.hi - self.lo) / 2


@dataclass
class Part:
    """An interactive part: boxes moved by state s in [0, 1] (hinge: angle s*max about axis; slide: s*max along axis)."""

    name: str
    description: str
    kind: str  # "hinge" | "slide"
    boxes: list[BoxSpec]
    pivot: np.ndarray
    axis: np.ndarray  # unit vector: rotation axis (right-hand rule) or slide direction
    max_motion: float  # radians or metres

    @property
    def motion(self) -> Articulation:
        """The motion in the `articulation.json` convention (the simulator's world frame)."""
        return Articulation(self.kind, self.axis, self.pivot, self.max_motion)

    def pose(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) such that a rest-pose point p moves to R @ p + t."""
        return self.motion.pose(s)


@dataclass
class RenderResult:
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32 metric z-depth along the optical axis
    instance: np.ndarray  # (H, W) uint8: 0 static, k object k-1, 255 occluder


@dataclass
class Occluder:
    """A blocky person walking across the view during a few passes."""

    passes: list[tuple[float, float, np.ndarray, np.ndarray, float]] = field(default_factory=list)
    # (start time, end time, base point (3,), walking direction (3,), half span metres)

    def placement(self, time: float) -> tuple[np.ndarray, np.ndarray] | None:
        for start, end, base, direction, half_span in self.passes:
            if start <= time <= end:
                u = (time - start) / max(1e-9, end - start)
                return base + direction * (2 * u - 1) * half_span, direction
        return None


# ----------------------------------------------------------------------------------------------------------------
# Building the room
# ----------------------------------------------------------------------------------------------------------------
class _Builder:
    """Creates textures and boxes with a seeded random generator, in a fixed order (determinism)."""

    def __init__(self, cfg: SynthConfig):
        self.cfg = cfg
        self.atlas = Atlas()
        self.stream(0)

    def stream(self, k: int) -> None:
        """Switch to random stream k: the room, the furniture and the person draw from separate streams, so
        changing the wall texture option does not change the furniture (and vice versa)."""
        self.rng = np.random.default_rng([self.cfg.seed, 100 + k])
        self.tm = TextureMaker(self.rng, self.cfg.texture_contrast)

    def tex(self, name: str, tile: np.ndarray) -> int:
        return self.atlas.add(name, tile)

    def photo(self, photo: str, tint=None) -> int:
        return self.tex(f"{photo}#{len(self.atlas.names)}", self.tm.crop(photo, TILE, tint))

    def plain(self, photo: str, tint=None) -> int:
        """The photo's mean colour, flat (a painted surface): the crop is still drawn, so every later random draw,
        and so the rest of the scene, stays what the photo version gives."""
        crop = self.tm.crop(photo, TILE, tint)
        return self.tex(f"plain {photo}#{len(self.atlas.names)}", self.tm.flat(tuple(crop.reshape(-1, 3).mean(0))))

    def box(self, lo, hi, tile: int | dict[int, int], scale: float | None = None, wall: str = "back") -> BoxSpec:
        """Box with `tile` on every face (or {face: tile} with key -1 as the default)."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        if isinstance(tile, dict):
            tiles = np.array([tile.get(f, tile[-1]) for f in range(6)])
        else:
            tiles = np.full(6, tile)
        size = float(np.clip(np.max(hi - lo), 0.3, 1.6)) if scale is None else scale
        offset = self.rng.uniform(0.0, 1.0, (6, 2))
        return BoxSpec(lo, hi, tiles, np.full(6, size), offset, wall)

    # -- room ---------------------------------------------------------------------------------------------------
    def room(self) -> BoxSpec:
        cfg, tm = self.cfg, self.tm
        mosaics = [["astronaut", "brick", "coffee", "moon"], ["rocket", "gravel", "chelsea", "camera"],
                   ["hubble_deep_field", "brick", "coins", "grass"], ["immunohistochemistry", "text", "retina", "cell"]]
        if cfg.texture == "photo":
            walls = [self.tex(f"wall{i}", tm.mosaic(m)) for i, m in enumerate(mosaics)]
            floor = self.tex("floor", tm.mosaic(["gravel", "grass", "gravel", "brick"]) * np.float32([0.95, 0.8, 0.62]))
            ceiling = self.tex("ceiling", tm.low((0.86, 0.86, 0.84)))
        elif cfg.texture == "low":
            bases = [(0.78, 0.74, 0.66), (0.70, 0.76, 0.80), (0.80, 0.72, 0.70), (0.74, 0.78, 0.70)]
            walls = [self.tex(f"wall{i}", tm.low(b)) for i, b in enumerate(bases)]
            floor = self.tex("floor", tm.low((0.55, 0.42, 0.30)))
            ceiling = self.tex("ceiling", tm.low((0.86, 0.86, 0.84)))
        else:
            bases = [(0.78, 0.74, 0.66), (0.70, 0.76, 0.80), (0.80, 0.72, 0.70), (0.74, 0.78, 0.70)]
            walls = [self.tex(f"wall{i}", tm.flat(b)) for i, b in enumerate(bases)]
            floor = self.tex("floor", tm.flat((0.55, 0.42, 0.30)))
            ceiling = self.tex("ceiling", tm.flat((0.86, 0.86, 0.84)))
        lo, hi = room_bounds(cfg.room_scale)
        spec = self.box(lo, hi, {0: walls[1], 1: walls[2], 2: walls[3], 3: walls[0], 4: floor, 5: ceiling,
                                             -1: walls[0]}, scale=3.0)
        return spec

    # -- furniture and parts ------------------------------------------------------------------------------------
    def furniture(self) -> tuple[list[BoxSpec], list[Part]]:
        cfg = self.cfg
        a = cfg.articulation
        P = self.photo if cfg.furniture == "photo" else self.plain
        wood = lambda: P("gravel", (0.72, 0.52, 0.34))  # noqa: E731
        dark = self.tex("handle", self.tm.flat((0.12, 0.12, 0.13)))
        static: list[BoxSpec] = []
        parts: list[Part] = []

        def hinge_max(deg: float) -> float:
            return float(np.radians(min(160.0, deg * a)))

        def slide_max(metres: float, depth: float) -> float:
            return float(min(0.9 * depth, metres * a))

        # fridge: tall body, full-height door hinged on its right edge (it swings away from the camera's arc)
        static.append(self.box([-1.6, 1.83, 0.0], [-0.85, 2.48, 1.85], {2: P("immunohistochemistry", None),
                                                                         -1: P("cell", (0.9, 0.92, 0.95))}))
        door = self.box([-1.6, 1.77, 0.03], [-0.85, 1.83, 1.83], {2: P("astronaut"), -1: P("cell", (0.9, 0.92, 0.95))})
        handle = self.box([-1.53, 1.72, 0.8], [-1.49, 1.77, 1.4], dark)
        parts.append(Part("fridge door", "the thing that keeps food cold", "hinge", [door, handle],
                          np.array([-0.85, 1.77, 0.0]), np.array([0.0, 0.0, 1.0]), hinge_max(100)))
        # cabinet with two drawers
        static.append(self.box([-0.05, 1.93, 0.0], [1.05, 2.48, 0.95], wood()))
        top = self.box([0.0, 1.91, 0.6], [1.0, 2.42, 0.91], {2: P("chelsea"), -1: wood()})
        top_h = self.box([0.4, 1.88, 0.74], [0.6, 1.91, 0.78], dark)
        low = self.box([0.0, 1.91, 0.08], [1.0, 2.42, 0.55], {2: P("rocket"), -1: wood()})
        low_h = self.box([0.4, 1.88, 0.44], [0.6, 1.91, 0.48], dark)
        top_part = Part("top drawer", "the top drawer of the wooden cabinet, where the cutlery is kept", "slide",
                        [top, top_h], np.zeros(3), np.array([0.0, -1.0, 0.0]), slide_max(0.35, 0.51))
        low_part = Part("bottom drawer", "the deep bottom drawer of the wooden cabinet, for pots and pans", "slide",
                        [low, low_h], np.zeros(3), np.array([0.0, -1.0, 0.0]), slide_max(0.32, 0.51))
        # microwave on the cabinet, door hinged on its left edge
        static.append(self.box([0.1, 2.05, 0.95], [0.65, 2.45, 1.27], {2: P("camera", (0.6, 0.6, 0.62)),
                                                                       -1: P("moon", (0.85, 0.85, 0.88))}))
        mw = self.box([0.1, 2.02, 0.97], [0.52, 2.05, 1.25], {2: P("hubble_deep_field"), -1: dark})
        mw_part = Part("microwave door", "the thing that heats food quickly", "hinge", [mw],
                       np.array([0.1, 2.02, 0.0]), np.array([0.0, 0.0, -1.0]), hinge_max(95))
        # oven between fridge and cabinet, door hinged at the bottom
        static.append(self.box([-0.8, 1.9, 0.0], [-0.1, 2.48, 0.9], {-1: P("coins", (0.75, 0.75, 0.78))}))
        ov = self.box([-0.76, 1.87, 0.1], [-0.14, 1.9, 0.7], {2: P("retina"), -1: dark})
        ov_h = self.box([-0.7, 1.83, 0.62], [-0.2, 1.87, 0.65], dark)
        ov_part = Part("oven door", "the door of the oven that bakes bread", "hinge", [ov, ov_h],
                       np.array([0.0, 1.87, 0.1]), np.array([1.0, 0.0, 0.0]), hinge_max(85))
        # wall cupboard above the cabinet, door hinged on its right edge
        static.append(self.box([-0.05, 2.12, 1.5], [1.05, 2.48, 2.2], wood()))
        cd = self.box([-0.03, 2.09, 1.52], [1.03, 2.12, 2.18], {2: P("coffee"), -1: wood()})
        cd_h = self.box([0.0, 2.05, 1.6], [0.04, 2.09, 1.8], dark)
        cd_part = Part("cupboard door", "the door of the wall cupboard above the cabinet, where the cups are", "hinge",
                       [cd, cd_h], np.array([1.03, 2.09, 0.0]), np.array([0.0, 0.0, 1.0]), hinge_max(100))
        # storage chest against the left wall, lid hinged along the wall
        static.append(self.box([-2.95, 1.2, 0.0], [-2.35, 2.3, 0.6], {-1: P("clock", (0.8, 0.6, 0.45))}, wall="left"))
        lid = self.box([-2.95, 1.2, 0.6], [-2.35, 2.3, 0.66], {5: P("colorwheel"), -1: P("brick", (0.7, 0.5, 0.35))},
                       wall="left")
        lid_part = Part("chest lid", "the lid of the storage chest where the toys are", "hinge", [lid],
                        np.array([-2.95, 0.0, 0.66]), np.array([0.0, -1.0, 0.0]), hinge_max(100))
        # wardrobe against the right wall, two doors hinged on their outer edges
        static.append(self.box([2.4, 1.3, 0.0], [2.95, 2.45, 2.0], wood(), wall="right"))
        wl = self.box([2.37, 1.875, 0.05], [2.4, 2.43, 1.95], {0: P("grass", (0.5, 0.7, 0.5)), -1: wood()}, wall="right")
        wr = self.box([2.37, 1.32, 0.05], [2.4, 1.875, 1.95], {0: P("page", (0.8, 0.7, 0.9)), -1: wood()}, wall="right")
        wl_part = Part("wardrobe left door", "the left door of the wardrobe where the clothes hang", "hinge", [wl],
                       np.array([2.37, 2.43, 0.0]), np.array([0.0, 0.0, -1.0]), hinge_max(95))
        wr_part = Part("wardrobe right door", "the right door of the wardrobe where the coats are", "hinge", [wr],
                       np.array([2.37, 1.32, 0.0]), np.array([0.0, 0.0, 1.0]), hinge_max(95))
        # nightstand with one drawer
        static.append(self.box([1.12, 2.03, 0.0], [1.52, 2.48, 0.55], wood()))
        ns = self.box([1.15, 2.0, 0.32], [1.49, 2.4, 0.52], {2: P("text", (0.9, 0.8, 0.6)), -1: wood()})
        ns_part = Part("nightstand drawer", "the small drawer of the bedside table", "slide", [ns],
                       np.zeros(3), np.array([0.0, -1.0, 0.0]), slide_max(0.25, 0.4))
        # static scenery: bookshelf (back-left corner) and a rug
        static.append(self.box([-2.3, 2.15, 0.0], [-1.68, 2.48, 1.9], {2: self.tex("books", self.tm.mosaic(
            ["text", "page", "coins", "clock"])), -1: wood()}))
        static.append(self.box([-1.3, 0.2, 0.0], [1.3, 1.6, 0.012], {-1: P("retina", (0.9, 0.8, 0.8))}, scale=1.4))
        parts = [parts[0], top_part, mw_part, ov_part, low_part, cd_part, lid_part, wl_part, wr_part, ns_part]
        return static, parts

    def occluder_tiles(self) -> tuple[int, int, int]:
        shirt = self.tex("shirt", self.tm.low((0.75, 0.25, 0.2)))
        trousers = self.tex("trousers", self.tm.low((0.15, 0.2, 0.4)))
        skin = self.tex("skin", self.tm.low((0.85, 0.65, 0.52)))
        return shirt, trousers, skin

    def sleeve_tile(self) -> int:
        """The arm's sleeve: another colour than the skin (a green jumper), made only when the arm is on (the
        other tiles and so every render without it stay as they were)."""
        return self.tex("sleeve", self.tm.low((0.2, 0.45, 0.25)))


ARM_REACH = 0.03  # share of the capture's frames before and after a part's motion that the hand holding it is in view


def room_bounds(room_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """The room box for `room_scale` s: scaled about the back wall's foot (x = 0, y = 2.5), ceiling never lower."""
    s = float(room_scale)
    if s == 1.0:
        return ROOM_MIN.copy(), ROOM_MAX.copy()
    back = ROOM_MAX[1]
    lo = np.array([ROOM_MIN[0] * s, back - (ROOM_MAX[1] - ROOM_MIN[1]) * s, 0.0])
    hi = np.array([ROOM_MAX[0] * s, back, ROOM_MAX[2] * max(1.0, s)])
    return lo, hi


def _fit_room(cfg: SynthConfig, static: list[BoxSpec], parts: list[Part]) -> tuple[list[BoxSpec], list[Part]]:
    """Place the furniture in a room of `cfg.room_scale`: side-wall furniture moves with its wall (x); in a room
    narrower than the default it no longer fits beside the back-wall group and is left out, as is back-wall
    furniture the side walls would cut. A left-out part that is interactive (id < cfg.parts) is an InputError.
    Returns (static boxes, parts) with left-out parts set to None (ids keep their meaning)."""
    s = float(cfg.room_scale)
    if s == 1.0:
        return static, parts
    lo, hi = room_bounds(s)
    shift = {"back": 0.0, "left": lo[0] - ROOM_MIN[0], "right": hi[0] - ROOM_MAX[0]}

    def moved(bx: BoxSpec) -> BoxSpec:
        d = np.array([shift[bx.wall], 0.0, 0.0])
        return replace(bx, lo=bx.lo + d, hi=bx.hi + d)

    def fits(bx: BoxSpec) -> bool:
        return (s >= 1.0 or bx.wall == "back") and bool(np.all(bx.lo[:2] >= lo[:2]) and np.all(bx.hi[:2] <= hi[:2]))

    static = [moved(bx) for bx in static]
    static = [bx for bx in static if fits(bx)]
    placed: list[Part] = []
    for k, part in enumerate(parts):
        boxes = [moved(bx) for bx in part.boxes]
        if all(fits(bx) for bx in boxes):
            pivot = part.pivot + np.array([shift[part.boxes[0].wall], 0.0, 0.0])
            placed.append(replace(part, boxes=boxes, pivot=pivot))
        elif k < cfg.parts:
            raise InputError(f"room_scale {s:g} leaves no room for the {part.name!r} (object {k}): "
                             f"use --room-scale >= 1 or --parts <= {k}")
        else:
            placed.append(None)  # type: ignore[arg-type]
    return static, placed


def _plan_occluder(cfg: SynthConfig, path: CameraPath, rng: np.random.Generator) -> Occluder:
    """Passes of a walking person between the camera and the furniture, covering ~cfg.occluder of the frames."""
    occ = Occluder()
    if cfg.occluder <= 0:
        return occ
    total = cfg.occluder * cfg.frames
    n_pass = max(1, int(round(total / 75.0)))
    length = total / n_pass
    for j in range(n_pass):
        mid = (j + 0.5) * cfg.frames / n_pass
        start, end = mid - length / 2, mid + length / 2
        cam = path.pose_cv(float(np.clip(mid, 0, cfg.frames - 1)))
        fwd = cam[:3, 2] * np.array([1, 1, 0])
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, [0, 0, 1.0])
        dist = float(rng.uniform(1.1, 1.5))
        base = cam[:3, 3] * np.array([1, 1, 0]) + fwd * dist
        half_span = dist * np.tan(np.radians(cfg.hfov_deg) / 2) + 0.5
        direction = right if rng.random() < 0.5 else -right
        occ.passes.append((start, end, base, direction, half_span))
    return occ


# ----------------------------------------------------------------------------------------------------------------
# The scene
# ----------------------------------------------------------------------------------------------------------------
class Scene:
    """A built room plus its capture plan (camera path, part schedules, occluder, camera effects)."""

    def __init__(self, cfg: SynthConfig):
        self.cfg = cfg.check()
        b = _Builder(cfg)
        b.stream(1)
        self._room = b.room()
        b.stream(2)
        self._static, all_parts = _fit_room(cfg, *b.furniture())
        b.stream(3)
        self._occ_tiles = b.occluder_tiles()
        self._sleeve = b.sleeve_tile() if cfg.arm else None
        self.atlas = b.atlas.build()
        self.parts = all_parts[: cfg.parts]
        self._fixed_parts = [p for p in all_parts[cfg.parts:] if p is not None]  # closed, static scenery
        # separate streams: a stress option never changes the camera path or the schedules
        self.path = CameraPath.make(cfg, np.random.default_rng([cfg.seed, 1]), ARC_CENTRE, GROUP_TARGET)
        self.schedules: list[PartSchedule] = make_schedules(cfg.parts, cfg.frames, np.random.default_rng([cfg.seed, 2]))
        self.occluder = _plan_occluder(cfg, self.path, np.random.default_rng([cfg.seed, 3]))
        self._exposure_phase = np.random.default_rng([cfg.seed, 4]).uniform(0, 2 * np.pi, 2)
        self.lighting = Lighting()
        self.intrinsics: Intrinsics = phone_intrinsics(cfg)
        self._casters: dict[Intrinsics, RayCaster] = {}
        self._static_prims = self._to_prims([self._room] + self._static + [bx for p in self._fixed_parts for bx in p.boxes],
                                            inst=0)

    # -- public API ---------------------------------------------------------------------------------------------
    @property
    def object_names(self) -> list[str]:
        return [p.name for p in self.parts]

    @property
    def descriptions(self) -> dict[str, str]:
        return {p.name: p.description for p in self.parts}

    def camera_path(self) -> np.ndarray:
        """(N, 4, 4) camera-to-world, OpenGL axes."""
        return self._poses_gl.copy()

    @cached_property
    def _poses_gl(self) -> np.ndarray:
        return self.path.poses_gl()

    def states(self) -> np.ndarray:
        """(N, M) part states in [0, 1] per frame."""
        t = np.arange(self.cfg.frames, dtype=float)
        return np.stack([s.value(t) for s in self.schedules], axis=1) if self.schedules else np.zeros((len(t), 0))

    def states_at(self, time: float) -> np.ndarray:
        return np.array([float(s.value(time)) for s in self.schedules])

    def caster(self, intrinsics: Intrinsics | None = None) -> RayCaster:
        intr = intrinsics or self.intrinsics
        if intr not in self._casters:
            self._casters[intr] = RayCaster(intr)
        return self._casters[intr]

    def render(self, c2w_gl: np.ndarray, states, intrinsics: Intrinsics | None = None,
               frame: int | None = None, supersample: int = 1) -> RenderResult:
        """Render any camera (OpenGL c2w) at any states. frame=None: the clean scene (no occluder, no sensor
        effects); frame=i: with the occluder where it is at frame i and frame i's exposure and noise.

        supersample=s renders at s times the size and averages s x s blocks (INTER_AREA), as `truth_dataset` does
        when it shrinks the 640x480 video to 320x240; depth and instance are the sample nearest each pixel centre.
        """
        lin, depth, inst = self.render_linear(np.asarray(c2w_gl, float), states, intrinsics,
                                              None if frame is None else float(frame), supersample)
        return RenderResult(self._sensor(lin, frame), depth, inst)

    def render_frame(self, i: int) -> RenderResult:
        """Video frame i as the phone records it (motion blur, exposure, noise) with the truth at mid-exposure."""
        cfg = self.cfg
        ss = cfg.supersample
        lin, depth, inst = self.render_linear(self._poses_gl[i], self.states_at(i), None, float(i), ss)
        if cfg.motion_blur > 0 and cfg.blur_samples > 1:
            n = cfg.blur_samples
            offsets = [cfg.motion_blur * (k / (n - 1) - 0.5) for k in range(n)]
            acc = lin.copy()
            for dt in offsets:
                if abs(dt) > 1e-9:  # the centre sample is the truth render above
                    pose = opencv_to_opengl(self.path.pose_cv(i + dt))
                    acc += self.render_linear(pose, self.states_at(i + dt), None, i + dt, ss)[0]
            lin = acc / (1 + sum(abs(dt) > 1e-9 for dt in offsets))
        return RenderResult(self._sensor(lin, i), depth, inst)

    # -- internals ----------------------------------------------------------------------------------------------
    def render_linear(self, c2w_gl: np.ndarray, states, intrinsics: Intrinsics | None, time: float | None,
                      supersample: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rgb float32 in ~[0, 1], z-depth, instance) before any sensor effect."""
        intr = intrinsics or self.intrinsics
        if supersample > 1:
            lin, depth, inst = self.render_linear(c2w_gl, states, intr.scaled(intr.w * supersample,
                                                                              intr.h * supersample), time)
            size = (intr.w, intr.h)
            return (cv2.resize(lin, size, interpolation=cv2.INTER_AREA),
                    cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST_EXACT),
                    cv2.resize(inst, size, interpolation=cv2.INTER_NEAREST_EXACT))
        caster = self.caster(intr)
        c2w_cv = opengl_to_opencv(c2w_gl)
        prims = self.primitives(states, time)
        t, pid = caster.cast(c2w_cv, prims)
        lin = caster.shade(c2w_cv, prims, t, pid, self.atlas.image, self.atlas.y0, self.atlas.size, self.lighting)
        return lin, t, prims.inst[pid]

    def primitives(self, states, time: float | None = None) -> Prims:
        """World boxes at these part states (and the occluder at frame `time`, when given and enabled).

        `states`: one value per object in id order, or {name: value} (objects not named stay closed)."""
        if isinstance(states, Mapping):
            unknown = sorted(set(states) - set(self.object_names))
            if unknown:
                raise ValueError(f"unknown object(s) {unknown}; this scene has {self.object_names}")
            states = [float(states.get(name, 0.0)) for name in self.object_names]
        states = np.asarray(states, float).reshape(-1)
        if len(states) != len(self.parts):
            raise ValueError(f"expected {len(self.parts)} states ({self.object_names}), got {len(states)}")
        groups = [self._static_prims]
        for k, (part, s) in enumerate(zip(self.parts, states)):
            R, t = part.pose(float(np.clip(s, 0.0, 1.0)))
            groups.append(self._to_prims(part.boxes, inst=k + 1, R=R, t=t))
        if time is not None:
            place = self.occluder.placement(time)
            if place is not None:
                groups.append(self._person(*place))
            if self._sleeve is not None:
                groups += [self._arm(time, self.parts[k], states[k]) for k in self.moving(time)]
        return Prims(**{f: np.concatenate([getattr(g, f) for g in groups]) for f in Prims.__dataclass_fields__})

    def _to_prims(self, boxes: list[BoxSpec], inst: int, R: np.ndarray | None = None,
                  t: np.ndarray | None = None) -> Prims:
        R = np.eye(3) if R is None else R
        t = np.zeros(3) if t is None else t
        n = len(boxes)
        return Prims(
            R=np.repeat(R[None], n, axis=0),
            c=np.array([R @ bx.centre + t for bx in boxes]).reshape(n, 3),
            h=np.array([bx.half for bx in boxes]).reshape(n, 3),
            inst=np.full(n, inst, np.uint8),
            tile=np.array([bx.tile for bx in boxes], np.int64).reshape(n, 6),
            scale=np.array([bx.scale for bx in boxes]).reshape(n, 6),
            offset=np.array([bx.offset for bx in boxes]).reshape(n, 6, 2),
            inverted=np.array([bx is self._room for bx in boxes], bool),
        )

    def _person(self, foot: np.ndarray, direction: np.ndarray) -> Prims:
        shirt, trousers, skin = self._occ_tiles
        up = np.array([0.0, 0.0, 1.0])
        R = np.stack([direction, np.cross(up, direction), up], axis=1)
        parts = [((0.18, 0.11, 0.43), 0.43, trousers), ((0.23, 0.13, 0.31), 1.17, shirt), ((0.1, 0.11, 0.13), 1.63, skin)]
        n = len(parts)
        return Prims(
            R=np.repeat(R[None], n, axis=0),
            c=np.array([foot * np.array([1, 1, 0]) + up * z for _, z, _ in parts]),
            h=np.array([hh for hh, _, _ in parts], float),
            inst=np.full(n, OCCLUDER, np.uint8),
            tile=np.array([[tile] * 6 for _, _, tile in parts], np.int64),
            scale=np.full((n, 6), 0.8),
            offset=np.zeros((n, 6, 2)),
            inverted=np.zeros(n, bool),
        )

    def moving(self, time: float) -> list[int]:
        """Parts the hand holds at `time`: those whose schedule moves within `ARM_REACH` of the capture of it (the
        hand arrives before the motion and leaves after it)."""
        out = []
        reach = ARM_REACH * self.cfg.frames
        for k, sch in enumerate(self.schedules):
            ts = np.linspace(time - reach, time + reach, 9)
            if float(np.ptp(sch.value(ts))) > 1e-4:
                out.append(k)
        return out

    def _arm(self, time: float, part: Part, state: float) -> Prims:
        """A hand at the part's grasp point (its box centre, pushed out of it toward the camera) and a sleeved
        forearm from there to a shoulder to the right of the camera, so it enters from the image's right edge and is
        seen from the side, not along its length (`body.arm_prims`)."""
        cam = self.path.pose_cv(float(np.clip(time, 0, self.cfg.frames - 1)))
        eye, right, down = cam[:3, 3], cam[:3, 0], cam[:3, 1]
        R, t = part.pose(float(np.clip(state, 0.0, 1.0)))
        lo = np.min([bx.lo for bx in part.boxes], axis=0)
        hi = np.max([bx.hi for bx in part.boxes], axis=0)
        centre, half = (lo + hi) / 2, (hi - lo) / 2
        d_rest = R.T @ (eye - (R @ centre + t))  # toward the camera, in the part's rest frame
        d_rest /= np.linalg.norm(d_rest)
        exit_t = float(np.min(half / np.maximum(np.abs(d_rest), 1e-9)))
        grasp = R @ (centre + d_rest * (exit_t + 0.06)) + t
        shoulder = eye + 0.35 * down + 0.9 * right + 0.2 * cam[:3, 2]
        return arm_prims(shoulder, grasp, eye - grasp, skin=self._occ_tiles[2], sleeve=self._sleeve)

    def exposure(self, frame: int | float | None) -> float:
        if frame is None or self.cfg.exposure_drift <= 0:
            return 1.0
        x = float(frame) / max(1, self.cfg.frames - 1)
        ph = self._exposure_phase
        wave = 0.65 * np.sin(2 * np.pi * 0.8 * x + ph[0]) + 0.35 * np.sin(2 * np.pi * 2.3 * x + ph[1])
        return float(1.0 + self.cfg.exposure_drift * wave)

    def _sensor(self, lin: np.ndarray, frame: int | float | None) -> np.ndarray:
        """Exposure gain, sensor noise (seeded by seed and frame), 8-bit quantisation."""
        img = lin * (255.0 * self.exposure(frame))
        if frame is not None and self.cfg.noise > 0:
            rng = np.random.default_rng([self.cfg.seed, 5, int(round(float(frame) * 1000))])
            img = img + rng.standard_normal(img.shape, dtype=np.float32) * np.float32(self.cfg.noise)
        return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def build_scene(cfg: SynthConfig) -> Scene:
    """The scene for `cfg` (deterministic: same cfg, same scene, bit-identical renders)."""
    return Scene(cfg)
