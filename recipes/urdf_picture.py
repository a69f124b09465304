"""An exported URDF in a simulator, as one picture: pybullet loads the folder `livescene export RUN --format urdf`
wrote (a check in itself: its joints, their types and limits are read back from the simulator and printed), sets
each movable joint at its lower limit, the middle and its upper limit (the other joints at their lower limits), and
renders each with pybullet's software renderer (ER_TINY_RENDERER in DIRECT mode: no OpenGL, no display), from the view
around the part's swept box that shows its motion best (the most pixels that change between the two limits, the open
part in sight, the static scene in front of it cut away). One row per joint, each part in its own colour, one
palette PNG.

pybullet is an optional extra of this recipe only (`pip install pybullet`, or the `sim` extra of pyproject.toml).

    livescene export out/room.run --format urdf --out out/room_urdf
    .venv/bin/python recipes/urdf_picture.py out/room_urdf --out docs/demo_urdf.png
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import cv2
import numpy as np

STATIC_RGBA = (0.80, 0.78, 0.74, 1.0)  # the base link (the static scene)
PART_RGBA = [(0.95, 0.45, 0.10, 1.0), (0.15, 0.45, 0.85, 1.0), (0.20, 0.70, 0.30, 1.0), (0.80, 0.20, 0.60, 1.0),
             (0.60, 0.40, 0.20, 1.0), (0.10, 0.70, 0.75, 1.0)]  # one colour per moving link, in joint order
KINDS = {0: "revolute", 1: "prismatic", 2: "spherical", 3: "planar", 4: "fixed"}  # pybullet's JOINT_* values
SEARCH_SIZE = (128, 96)  # the view search renders this small; the picture at --width


def import_pybullet() -> ModuleType | None:
    try:
        import pybullet
    except ImportError:
        return None
    return pybullet


@dataclass
class Joint:
    """A movable joint as pybullet reads it: `link` is its child link's index (pybullet numbers a joint and its
    child link alike), limits in radians (revolute) or the URDF's length unit (prismatic)."""

    index: int
    name: str
    kind: str
    lower: float
    upper: float
    link: str

    def at(self, t: float) -> float:
        return self.lower + t * (self.upper - self.lower)

    def describe(self, value: float) -> str:
        return f"{math.degrees(value):.0f} deg" if self.kind == "revolute" else f"{value:.3g}"


@dataclass
class Camera:
    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov_deg: float
    near: float
    far: float


def find_urdf(path: Path) -> Path:
    """The URDF of an export folder (export.json names it; else scene.urdf or the folder's one *.urdf), or a file."""
    if path.is_file():
        return path
    if not path.is_dir():
        raise FileNotFoundError(f"{path} is neither a URDF file nor an export folder")
    report = path / "export.json"
    if report.is_file():
        name = json.loads(report.read_text()).get("urdf", {}).get("urdf")
        if name and (path / name).is_file():
            return path / name
    found = sorted(path.glob("*.urdf"))
    if not found:
        raise FileNotFoundError(f"no *.urdf in {path} (make one with `livescene export RUN --format urdf --out DIR`)")
    return path / "scene.urdf" if (path / "scene.urdf").is_file() else found[0]


class Scene:
    """One URDF loaded in a pybullet DIRECT client, its base fixed, each link coloured (the exported meshes' vertex
    colours are not drawn by pybullet's renderer); `close()` disconnects."""

    def __init__(self, pb: ModuleType, urdf: Path):
        self.pb = pb
        self.client = pb.connect(pb.DIRECT)
        try:
            self.body = pb.loadURDF(str(urdf), useFixedBase=True, physicsClientId=self.client)
        except pb.error as e:
            pb.disconnect(self.client)
            raise ValueError(f"pybullet could not load {urdf}: {e}") from None
        self.joints: list[Joint] = []
        self.fixed: list[str] = []
        for j in range(pb.getNumJoints(self.body, physicsClientId=self.client)):
            info = pb.getJointInfo(self.body, j, physicsClientId=self.client)
            name, kind, lower, upper = info[1].decode(), KINDS.get(info[2], str(info[2])), info[8], info[9]
            if kind in ("revolute", "prismatic"):
                self.joints.append(Joint(j, name, kind, float(lower), float(upper), info[12].decode()))
            else:
                self.fixed.append(name)
        pb.changeVisualShape(self.body, -1, rgbaColor=STATIC_RGBA, physicsClientId=self.client)
        for i, joint in enumerate(self.joints):
            pb.changeVisualShape(self.body, joint.index, rgbaColor=PART_RGBA[i % len(PART_RGBA)],
                                 physicsClientId=self.client)

    def close(self) -> None:
        self.pb.disconnect(self.client)

    def set(self, values: dict[int, float]) -> None:
        """Every movable joint at its lower limit, except those in `values` (joint index -> position)."""
        for joint in self.joints:
            self.pb.resetJointState(self.body, joint.index, values.get(joint.index, joint.lower),
                                    physicsClientId=self.client)

    def show_base(self, shown: bool) -> None:
        """Draw the static scene or not (the software renderer skips a fully transparent link)."""
        self.pb.changeVisualShape(self.body, -1, rgbaColor=STATIC_RGBA if shown else (1.0, 1.0, 1.0, 0.0),
                                  physicsClientId=self.client)

    def read(self, joint: Joint) -> float:
        return float(self.pb.getJointState(self.body, joint.index, physicsClientId=self.client)[0])

    def link_box(self, link: int) -> np.ndarray:
        """(2, 3) axis-aligned box of a link (-1: the base) where it is now."""
        return np.array(self.pb.getAABB(self.body, link, physicsClientId=self.client), dtype=float)

    def render(self, cam: Camera, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) uint8 colours and (H, W) int link indices (-1 the base, -2 nothing) from `cam`."""
        pb, (w, h) = self.pb, size
        view = pb.computeViewMatrix(cam.eye.tolist(), cam.target.tolist(), cam.up.tolist())
        proj = pb.computeProjectionMatrixFOV(cam.fov_deg, w / h, cam.near, cam.far)
        light = (cam.eye - cam.target) + 0.6 * np.linalg.norm(cam.eye - cam.target) * cam.up
        _, _, rgba, _, seg = pb.getCameraImage(
            w, h, view, proj, renderer=pb.ER_TINY_RENDERER, lightDirection=light.tolist(), shadow=0,
            flags=pb.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX, physicsClientId=self.client)
        rgb = np.reshape(np.asarray(rgba, dtype=np.uint8), (h, w, 4))[:, :, :3]
        seg = np.reshape(np.asarray(seg, dtype=np.int64), (h, w))
        links = np.where(seg >= 0, (seg >> 24) - 1, -2)  # objectUid + (linkIndex + 1) << 24
        return np.ascontiguousarray(rgb), links


def swept_box(scene: Scene, joint: Joint) -> np.ndarray:
    """(2, 3) box of the joint's child link over its range (lower, middle, upper)."""
    boxes = []
    for t in (0.0, 0.5, 1.0):
        scene.set({joint.index: joint.at(t)})
        boxes.append(scene.link_box(joint.index))
    scene.set({})
    b = np.stack(boxes)
    return np.stack([b[:, 0].min(0), b[:, 1].max(0)])


def candidate_cameras(box: np.ndarray, up: np.ndarray, fov_deg: float = 50.0) -> list[Camera]:
    """Cameras aimed at the box's centre from around it (12 azimuths about `up`, 3 elevations, 2 distances that
    frame the box's sphere with some room). The near plane cuts away what lies between the camera and the box's
    sphere, the far plane what lies well behind it: the static scene in front of a part (a wall, the far side of the
    room) does not hide it, and the clutter far behind does not crowd it."""
    up = up / np.linalg.norm(up)
    centre, radius = box.mean(0), max(0.5 * float(np.linalg.norm(box[1] - box[0])), 1e-6)
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    fit = radius / math.sin(math.radians(fov_deg) / 2)
    cams = []
    for k in (1.1, 1.6):
        for elev in (15.0, 35.0, 55.0):
            for az in range(0, 360, 30):
                e, z = math.radians(elev), math.radians(az)
                d = math.cos(e) * (math.cos(z) * a + math.sin(z) * b) + math.sin(e) * up
                near = max(k * fit - 1.05 * radius, 0.02 * radius)
                cams.append(Camera(centre + k * fit * d, centre, up, fov_deg, near, k * fit + 2.0 * radius))
    return cams


def view_score(scene: Scene, joint: Joint, cam: Camera, size: tuple[int, int] = SEARCH_SIZE) -> tuple[int, int, float]:
    """What a view shows of a joint: the part's pixels, at either limit, that show something else at the other
    limit; the part's pixels at its upper limit (open); and the share of the part the static scene leaves in sight
    at the middle or the upper limit, whichever is less (the base drawn, then hidden). The lower limit's share is
    not asked: a closed drawer rests inside its cabinet."""
    seg, shown = {}, []
    for t in (0.0, 0.5, 1.0):
        scene.set({joint.index: joint.at(t)})
        seg[t] = scene.render(cam, size)[1]
        if t > 0.0:
            scene.show_base(False)
            whole = int((scene.render(cam, size)[1] == joint.index).sum())
            scene.show_base(True)
            shown.append(int((seg[t] == joint.index).sum()) / max(whole, 1))
    scene.set({})
    part = (seg[0.0] == joint.index) | (seg[1.0] == joint.index)
    return int((part & (seg[0.0] != seg[1.0])).sum()), int((seg[1.0] == joint.index).sum()), min(shown)


def best_view(scene: Scene, joint: Joint, up: np.ndarray) -> tuple[Camera, float]:
    """The candidate camera that shows the joint's motion best: the most pixels that change between its limits
    plus the open part's pixels (the part swung or pulled out in full view), weighed by the share of the part in
    sight (a part half hidden by the static scene counts half); and the share of the image that changes there."""
    cams = candidate_cameras(swept_box(scene, joint), up)
    scores = [view_score(scene, joint, cam) for cam in cams]
    i = int(np.argmax([(changed + opened) * shown for changed, opened, shown in scores]))
    return cams[i], scores[i][0] / (SEARCH_SIZE[0] * SEARCH_SIZE[1])


def caption(im: np.ndarray, text: str) -> None:
    """White text on a darkened band across the top of the tile."""
    im[:24] = (im[:24] * 0.35).astype(np.uint8)
    cv2.putText(im, text, (6, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)


def joint_row(scene: Scene, joint: Joint, cam: Camera, states: tuple[float, ...], width: int) -> list[np.ndarray]:
    """The joint at each state (0 lower limit .. 1 upper limit), rendered at twice the size and shrunk (the software
    renderer does not anti-alias), each captioned with the position pybullet reads back."""
    height = round(width * 3 / 4)
    tiles = []
    for t in states:
        scene.set({joint.index: joint.at(t)})
        rgb, _ = scene.render(cam, (2 * width, 2 * height))
        tile = np.ascontiguousarray(cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA))
        caption(tile, f"{joint.name} {joint.describe(scene.read(joint))}")
        tiles.append(tile)
    scene.set({})
    return tiles


def picture(urdf_dir: Path, states: tuple[float, ...] = (0.0, 0.5, 1.0), width: int = 240,
            up: tuple[float, float, float] = (0.0, 0.0, 1.0), pb: ModuleType | None = None,
            log=print) -> tuple[np.ndarray, list[Joint], list[float]]:
    """The strip (rows: joints; columns: states) of the URDF in pybullet, its movable joints as read back, and each
    joint's share of image pixels that change between its limits in its chosen view."""
    pb = pb or import_pybullet()
    if pb is None:
        raise ImportError("pybullet is not installed")
    urdf = find_urdf(urdf_dir)
    scene = Scene(pb, urdf)
    try:
        log(f"pybullet loaded {urdf}: {len(scene.joints)} movable joints, {len(scene.fixed)} fixed")
        for joint in scene.joints:
            log(f"  {joint.name}: {joint.kind}, limits {joint.lower:.6g} .. {joint.upper:.6g} "
                f"({joint.describe(joint.lower)} .. {joint.describe(joint.upper)}), moves link {joint.link}")
        if not scene.joints:
            raise ValueError(f"{urdf} has no movable joint (a run without motions exports fixed links only)")
        rows, shares = [], []
        for joint in scene.joints:
            cam, share = best_view(scene, joint, np.asarray(up, dtype=float))
            log(f"  {joint.name}: view from {np.round(cam.eye, 2).tolist()}, {100 * share:.1f} % of pixels change")
            rows.append(np.hstack(joint_row(scene, joint, cam, states, width)))
            shares.append(share)
        return np.vstack(rows), scene.joints, shares
    finally:
        scene.close()


def write_palette_png(path: Path, image: np.ndarray, colours: int = 128) -> int:
    """`image` (H, W, 3 RGB) as an 8-bit palette PNG; returns its size in bytes."""
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).quantize(colors=colours, method=Image.Quantize.MEDIANCUT).save(path, optimize=True)
    return path.stat().st_size


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n")[-1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("urdf", type=Path, help="export folder of `livescene export --format urdf` (or a .urdf file)")
    p.add_argument("--out", type=Path, default=Path("urdf_picture.png"), help="PNG to write (default %(default)s)")
    p.add_argument("--states", default="0,0.5,1",
                   help="joint positions, 0 lower limit .. 1 upper (default %(default)s)")
    p.add_argument("--width", type=int, default=240, help="pixels per picture across (default %(default)s)")
    p.add_argument("--up", default="0,0,1", help="the scene's up direction x,y,z (default %(default)s)")
    args = p.parse_args(argv)
    pb = import_pybullet()
    if pb is None:
        print("urdf_picture: needs pybullet: .venv/bin/pip install pybullet (or pip install -e '.[sim]')",
              file=sys.stderr)
        return 2
    try:
        states = tuple(float(s) for s in args.states.split(","))
        up = tuple(float(s) for s in args.up.split(","))
        if len(up) != 3 or not any(up) or not all(0.0 <= s <= 1.0 for s in states):
            raise ValueError("--states are numbers in 0..1 and --up is three numbers, not all 0")
        strip, _, _ = picture(args.urdf, states, args.width, up, pb)
    except (ValueError, FileNotFoundError) as e:
        print(f"urdf_picture: {e}", file=sys.stderr)
        return 1
    size = write_palette_png(args.out, strip)
    print(f"{args.out}: {strip.shape[1]}x{strip.shape[0]}, {size / 1024:.0f} KB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
