"""When each part opens and closes: smooth ramps between holds, staggered across parts.

Every part opens fully at least once and closes again, and the parts move at different times, so the frames
cover many combinations of states (what an interactive radiance field must disentangle).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Ramp:
    start: float  # frame time the motion starts
    end: float  # frame time it reaches `to`
    to: float


@dataclass
class PartSchedule:
    ramps: list[Ramp]
    initial: float = 0.0

    def value(self, time: np.ndarray | float) -> np.ndarray:
        t = np.asarray(time, float)
        v = np.full(t.shape, self.initial)
        for r in self.ramps:
            s = np.clip((t - r.start) / max(1e-9, r.end - r.start), 0.0, 1.0)
            s = s * s * (3 - 2 * s)  # smoothstep: a hand accelerates and stops
            v = np.where(t >= r.start, v + (r.to - v) * s, v)
        return np.clip(v, 0.0, 1.0)


def make_schedules(n_parts: int, frames: int, rng: np.random.Generator) -> list[PartSchedule]:
    """Four motions per part (open fully, close, open part-way, close or stay), staggered by part index."""
    out = []
    slot = frames / 4.0
    for k in range(n_parts):
        phase = (k + rng.uniform(0.15, 0.85)) / n_parts  # where in each quarter this part moves
        partial = float(rng.uniform(0.35, 0.75))
        targets = [1.0, 0.0, partial, 0.0 if rng.random() < 0.5 else 1.0]
        ramps = []
        for j, to in enumerate(targets):
            length = slot * rng.uniform(0.3, 0.45)
            start = slot * j + phase * (slot - length)
            ramps.append(Ramp(start=start, end=start + length, to=to))
        out.append(PartSchedule(ramps))
    return out


def states_at(schedules: list[PartSchedule], time: float) -> np.ndarray:
    return np.array([float(s.value(time)) for s in schedules], dtype=np.float64)
