"""The hand model that ships in mediapipe 0.10.21's wheel (palm detection + 21 landmarks), run over a capture.

Why this model: it installs beside numpy 2 (`.ci/setup`: `--no-deps` plus protobuf 4.25, flatbuffers, absl-py,
attrs), needs no download, and finds where a hand is on 95-100 % of the frames of real door and drawer videos. It
never finds the forearm or the sleeve: its hands are the seeds of the transient layer (`auto`), not the layer.

Two passes: tracking mode over the frames in order (it keeps a hand seen side-on), then static mode at a low
palm-detection confidence on the frames tracking missed (on the shared laptop video it finds a real hand on 15 of
the 85 missed frames, a false one on none). Short gaps left between two frames with as many hands are filled by
interpolating the landmarks (`fill_gaps`).
"""

from __future__ import annotations

import os
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable, Iterator, TextIO

import numpy as np
from tqdm import tqdm

MEDIAPIPE_VERSION = "0.10.21"  # the last release whose wheel carries the hand model (later ones download it)
INSTALL = (f'pip install --no-deps mediapipe=={MEDIAPIPE_VERSION} "protobuf>=4.25.3,<5" flatbuffers absl-py attrs '
           f"matplotlib")
STATIC_CONFIDENCE = 0.2  # palm-detection confidence of the second (static) pass: low, it only looks where tracking lost
MAX_GAP = 4  # frames: a hand missed on at most this many frames between two finds is interpolated
MAX_JUMP = 2.0  # ... when its wrist moved at most this many hand lengths across the gap (else two hands, not one)
N_LANDMARKS = 21
WRIST, MIDDLE_MCP, INDEX_MCP, PINKY_MCP = 0, 9, 5, 17  # mediapipe's landmark indices


@dataclass
class HandTrack:
    """Per frame, the hands found: (k, 21, 2) landmark pixels (x, y); `how` per frame: "tracked", "static",
    "filled" or "" (none)."""

    hands: list[np.ndarray]
    how: list[str]
    seconds: dict[str, float] = field(default_factory=dict)

    def found_share(self) -> float:
        return float(np.mean([len(h) > 0 for h in self.hands])) if self.hands else 0.0


def model_problem() -> str | None:
    """One line on why the hand model cannot run here (not installed, or a broken install), None when it can."""
    try:
        import mediapipe as mp  # optional extra: installed by .ci/setup, not by pip install -e .

        with _quiet():
            mp.solutions.hands.Hands(static_image_mode=True, max_num_hands=1).close()
    except Exception as exc:  # an ImportError, or protobuf >= 5 ("'FieldDescriptor' object has no attribute 'label'")
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        return f"the hand model (mediapipe {MEDIAPIPE_VERSION}) does not run here ({why}); install it with: {INSTALL}"
    return None


def find_hands(load: Callable[[int], np.ndarray], n: int, *, max_hands: int = 2, progress: bool = False,
               clock: Callable[[], float] | None = None) -> HandTrack:
    """Hands on frames 0..n-1 (`load(pos)` -> (H, W, 3) uint8 RGB): tracking, then static on the misses, then
    `fill_gaps`. Raises ImportError when mediapipe is missing (callers check `model_problem` first)."""
    import mediapipe as mp  # optional extra

    clock = clock or time.perf_counter
    hands: list[np.ndarray] = [np.zeros((0, N_LANDMARKS, 2))] * n
    how = [""] * n
    seconds = {"tracking": 0.0, "static": 0.0}
    # TensorFlow Lite's start-up notes go to stderr from C++ (not the user's business); the bar to the real one
    with _quiet() as stderr:
        with mp.solutions.hands.Hands(static_image_mode=False, max_num_hands=max_hands, model_complexity=1) as tracker:
            for pos in tqdm(range(n), desc="hands", unit="frame", disable=not progress, file=stderr):
                img = load(pos)
                t = clock()
                hands[pos] = _landmarks(tracker.process(np.ascontiguousarray(img)), img.shape)
                seconds["tracking"] += clock() - t
                how[pos] = "tracked" if len(hands[pos]) else ""
        missed = [p for p in range(n) if not how[p]]
        if missed:
            with mp.solutions.hands.Hands(static_image_mode=True, max_num_hands=max_hands, model_complexity=1,
                                          min_detection_confidence=STATIC_CONFIDENCE) as finder:
                for pos in missed:
                    img = load(pos)
                    t = clock()
                    hands[pos] = _landmarks(finder.process(np.ascontiguousarray(img)), img.shape)
                    seconds["static"] += clock() - t
                    how[pos] = "static" if len(hands[pos]) else ""
    hands, how = fill_gaps(hands, how)
    return HandTrack(hands, how, {k: round(v, 3) for k, v in seconds.items()})


@contextmanager
def _quiet() -> Iterator[TextIO]:
    """Standard error silenced at the file-descriptor level (mediapipe's C++ logging ignores Python's streams);
    yields a stream to the real one (for a progress bar). Where fd 2 cannot be swapped (no real stderr), as is."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):
        yield sys.stderr
        return
    real = os.fdopen(os.dup(saved), "w", buffering=1)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            yield real
    finally:
        real.close()
        os.dup2(saved, 2)
        os.close(saved)


def _landmarks(result, shape: tuple[int, ...]) -> np.ndarray:
    found = result.multi_hand_landmarks or []
    h, w = shape[:2]
    return np.array([[(p.x * w, p.y * h) for p in hand.landmark] for hand in found],
                    dtype=np.float64).reshape(-1, N_LANDMARKS, 2)


def fill_gaps(hands: list[np.ndarray], how: list[str], max_gap: int = MAX_GAP) -> tuple[list[np.ndarray], list[str]]:
    """Interpolate the landmarks across a gap of at most `max_gap` frames whose two sides hold as many hands (paired
    by nearest wrist, none moved over `MAX_JUMP` hand lengths): the hand and the camera move little in that time,
    and a frame the model missed (motion blur, a hand side-on) is as much in the way as its neighbours."""
    hands, how = list(hands), list(how)
    found = [p for p in range(len(hands)) if len(hands[p])]
    for a, b in zip(found, found[1:]):
        if not 1 < b - a <= max_gap + 1 or len(hands[a]) != len(hands[b]):
            continue
        order = _pair(hands[a], hands[b])
        jump = max(float(np.linalg.norm(hands[b][j, WRIST] - h[WRIST])) / hand_length(h)
                   for h, j in zip(hands[a], order))
        if jump > MAX_JUMP:  # one hand let go and another took hold: nothing between them is either
            continue
        for pos in range(a + 1, b):
            w = (pos - a) / (b - a)
            hands[pos] = (1 - w) * hands[a] + w * hands[b][order]
            how[pos] = "filled"
    return hands, how


def _pair(a: np.ndarray, b: np.ndarray) -> list[int]:
    """For each hand of `a`, the hand of `b` with the nearest wrist (greedy; two hands at most)."""
    left = list(range(len(b)))
    order = []
    for hand in a:
        j = min(left, key=lambda k: float(np.linalg.norm(b[k, WRIST] - hand[WRIST])))
        order.append(j)
        left.remove(j)
    return order


def hand_scale(hand: np.ndarray) -> float:
    """A hand's size in pixels: the palm's width (index to pinky knuckle), at least its wrist-to-knuckle length / 2
    (a palm seen side-on is narrow)."""
    palm = float(np.linalg.norm(hand[INDEX_MCP] - hand[PINKY_MCP]))
    length = float(np.linalg.norm(hand[MIDDLE_MCP] - hand[WRIST]))
    return max(palm, 0.5 * length, 1.0)


def hand_length(hand: np.ndarray) -> float:
    """Wrist to middle knuckle in pixels: a hand's size whichever way it turns (its palm's width is not, side-on)."""
    return max(float(np.linalg.norm(hand[MIDDLE_MCP] - hand[WRIST])), 1.0)


def shares(track: HandTrack) -> dict[str, float]:
    """Share of the frames with a hand, by how it was found."""
    n = max(len(track.how), 1)
    return {k: round(sum(h == k for h in track.how) / n, 4) for k in ("tracked", "static", "filled")}

