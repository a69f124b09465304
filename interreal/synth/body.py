"""The simulator's arm: a sleeved forearm from the image edge and a hand with a palm, four fingers and a thumb.

Why a hand of rounded parts: a hand detector (the transient layer's seed, `interreal.transients.hands`) finds a palm
with fingers, not a skin-coloured box; drawn this way the simulated hand is one it can find, so the transient layer is
measured on the simulator as it is on real video. Sizes are an adult's times `ARM_SCALE`: the simulator's camera
stands 2-3 m from the parts, about twice as far as a phone held while the other hand opens a drawer, so the arm is
drawn twice as large to show as large as it does there (the hand model finds an adult-sized hand here on 16 % of a
960x720 capture's frames, a twice-sized one on 87 %, `--hard` seed 1).
"""

from __future__ import annotations

import numpy as np

from .render import OCCLUDER, Prims

ARM_SCALE = 2.0
HAND_LENGTH = 0.19  # metres, wrist to the middle fingertip (an adult's)
FOREARM_HALF = 0.04  # the sleeve's half width and depth (not scaled: it hides no more of the parts than before)
# fingers across the palm (index .. little): offset across in palm widths, length in hand lengths
FINGERS = ((-0.36, 0.40), (-0.12, 0.46), (0.12, 0.43), (0.36, 0.34))
PALM = (0.54, 0.46, 0.14)  # palm length, width, thickness in hand lengths


def arm_prims(shoulder: np.ndarray, grasp: np.ndarray, to_camera: np.ndarray, skin: int, sleeve: int,
              scale: float = ARM_SCALE) -> Prims:
    """A sleeve from `shoulder` to the wrist and a hand whose fingertips reach `grasp`, its back toward `to_camera`
    (a world direction), as a hand on a handle is seen by whoever films it."""
    axis = grasp - shoulder
    length = float(np.linalg.norm(axis))
    axis = axis / max(length, 1e-9)
    back = to_camera - axis * float(to_camera @ axis)
    back = back / np.linalg.norm(back) if np.linalg.norm(back) > 1e-6 else _any_normal(axis)
    across = np.cross(back, axis)
    hand = HAND_LENGTH * scale
    wrist = grasp - axis * hand
    forearm = max(0.05, float((wrist - shoulder) @ axis) + 0.02)  # into the hand a little: no gap at the cuff
    frame = np.stack([axis, across, back], axis=1)  # local x along the arm, y across the palm, z out of its back
    boxes = [(frame, shoulder + axis * forearm / 2, (forearm / 2, FOREARM_HALF, FOREARM_HALF), sleeve, False)]
    palm_len, palm_w, palm_t = (v * hand for v in PALM)
    boxes.append((frame, wrist + axis * palm_len / 2, (palm_len / 2 * 1.1, palm_w / 2, palm_t / 2), skin, True))
    knuckles = wrist + axis * palm_len * 0.92
    finger_w = palm_w * 0.21
    for off, flen in FINGERS:
        L = flen * hand
        c = knuckles + across * off * palm_w + axis * L / 2
        boxes.append((frame, c, (L / 2, finger_w / 2, finger_w / 2.4), skin, True))
    thumb_dir = _unit(axis * 0.55 - across * 0.85)  # out from the palm's index side, toward the fingers
    thumb_frame = np.stack([thumb_dir, np.cross(back, thumb_dir), back], axis=1)
    t_len = 0.30 * hand
    thumb_base = wrist + axis * palm_len * 0.3 - across * palm_w * 0.38
    boxes.append((thumb_frame, thumb_base + thumb_dir * t_len / 2, (t_len / 2, finger_w * 0.6, finger_w / 2.2), skin,
                  True))
    n = len(boxes)
    return Prims(R=np.stack([b[0] for b in boxes]), c=np.array([b[1] for b in boxes]),
                 h=np.array([b[2] for b in boxes], float), inst=np.full(n, OCCLUDER, np.uint8),
                 tile=np.array([[b[3]] * 6 for b in boxes], np.int64), scale=np.full((n, 6), 0.8),
                 offset=np.zeros((n, 6, 2)), inverted=np.zeros(n, bool), rounded=np.array([b[4] for b in boxes]))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _any_normal(axis: np.ndarray) -> np.ndarray:
    side = np.cross(axis, [0.0, 0.0, 1.0])
    return _unit(side) if np.linalg.norm(side) > 1e-6 else np.array([1.0, 0.0, 0.0])
