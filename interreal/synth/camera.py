"""The handheld phone: intrinsics with mild radial distortion and a smooth arc around the furniture with hand shake.

The path is a continuous function of time (in frames), so motion blur can render sub-frame poses and `fast`
motion simply sweeps the same arc back and forth more often. The arc spans ~140 degrees around the furniture
group at 1.2-3 m (times `room_scale`, at least 0.85), which gives structure-from-motion a wide baseline while the parts stay in view.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..conventions import opencv_to_opengl
from ..dataset import Intrinsics
from .config import SynthConfig

WORLD_UP = np.array([0.0, 0.0, 1.0])
MIN_RADIUS_SCALE = 0.85  # a smaller arc would run the phone into the open fridge door (room_scale < 0.85)


def phone_intrinsics(cfg: SynthConfig) -> Intrinsics:
    """Pinhole with the configured horizontal FOV, square pixels, centred principal point, OpenCV k1/k2."""
    fx = 0.5 * cfg.width / np.tan(np.radians(cfg.hfov_deg) / 2.0)
    return Intrinsics(w=cfg.width, h=cfg.height, fl_x=float(fx), fl_y=float(fx), cx=cfg.width / 2.0,
                      cy=cfg.height / 2.0, k1=cfg.k1, k2=cfg.k2, camera_model="OPENCV")


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world rotation, OpenCV axes (x right, y down, z forward), no roll w.r.t. world up (z)."""
    f = target - position
    f = f / np.linalg.norm(f)
    right = np.cross(f, WORLD_UP)
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    return np.stack([right, down, f], axis=1)


def _rot(axis: int, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


@dataclass
class CameraPath:
    """Arc around `centre` (world x, y) from angle a0 to a1, with slow radius/height/target wander and shake."""

    frames: int
    fps: float
    centre: np.ndarray
    radius: float
    a0: float
    a1: float
    height: float
    target: np.ndarray
    speed: float
    wander_phase: np.ndarray  # (4,) phases of the slow radius / height / target wander
    shake_freq: np.ndarray  # (6, 3) Hz, per dof (x, y, z, yaw, pitch, roll), 3 sinusoids each
    shake_phase: np.ndarray  # (6, 3)
    shake_pos: float  # metres
    shake_rot: float  # radians

    @classmethod
    def make(cls, cfg: SynthConfig, rng: np.random.Generator, centre: np.ndarray, target: np.ndarray) -> "CameraPath":
        span = np.radians(rng.uniform(125.0, 145.0))
        mid = np.radians(-90.0 + rng.uniform(-8.0, 8.0))
        if rng.random() < 0.5:  # left-to-right or right-to-left
            a0, a1 = mid - span / 2, mid + span / 2
        else:
            a0, a1 = mid + span / 2, mid - span / 2
        return cls(
            frames=cfg.frames, fps=cfg.fps, centre=np.asarray(centre, float),
            radius=float(rng.uniform(1.8, 2.0)) * max(cfg.room_scale, MIN_RADIUS_SCALE),
            a0=float(a0), a1=float(a1), height=float(rng.uniform(1.35, 1.55)), target=np.asarray(target, float),
            speed=cfg.speed, wander_phase=rng.uniform(0, 2 * np.pi, 4),
            shake_freq=rng.uniform(0.6, 3.5, (6, 3)), shake_phase=rng.uniform(0, 2 * np.pi, (6, 3)),
            shake_pos=0.006 * cfg.jitter, shake_rot=np.radians(0.35) * cfg.jitter,
        )

    def progress(self, time: np.ndarray | float) -> np.ndarray:
        """Arc parameter in [0, 1]: eases in and out; with speed > 1 it sweeps back and forth."""
        x = np.asarray(time, float) / max(1, self.frames - 1)
        return 0.5 - 0.5 * np.cos(np.pi * self.speed * x)

    def pose_cv(self, time: float) -> np.ndarray:
        """Camera-to-world (4, 4), OpenCV axes, at fractional frame `time`."""
        x = time / max(1, self.frames - 1)
        u = float(self.progress(time))
        a = self.a0 + (self.a1 - self.a0) * u
        ph = self.wander_phase
        r = self.radius + 0.15 * np.sin(2 * np.pi * 0.7 * x + ph[0])
        z = self.height + 0.12 * np.sin(2 * np.pi * 0.9 * x + ph[1])
        pos = np.array([self.centre[0] + r * np.cos(a), self.centre[1] + r * np.sin(a), z])
        tgt = self.target + np.array([0.35 * np.sin(2 * np.pi * 0.5 * x + ph[2]), 0.0,
                                      0.12 * np.sin(2 * np.pi * 0.8 * x + ph[3])])
        secs = time / self.fps
        shake = np.sum(np.sin(2 * np.pi * self.shake_freq * secs + self.shake_phase), axis=1) / 3.0  # (6,)
        pos = pos + self.shake_pos * shake[:3]
        R = look_at(pos, tgt)
        R = R @ _rot(1, self.shake_rot * shake[3]) @ _rot(0, self.shake_rot * shake[4]) @ _rot(2, self.shake_rot * shake[5])
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = R, pos
        return c2w

    def poses_gl(self) -> np.ndarray:
        """(N, 4, 4) camera-to-world, OpenGL axes (the transforms.json convention), one per frame."""
        return np.stack([opencv_to_opengl(self.pose_cv(float(i))) for i in range(self.frames)])
