"""Each frame's state along a video by dynamic programming: the grid position per frame that maximises the summed
evidence (overlap curves) less what moving between neighbouring frames costs, frames at one labelled end held
together. Why one place: the edge route's angles, the prism route's pulls and `reach`'s carried angles all follow
a part that moves smoothly, and a frame whose mask lost it follows its neighbours, not a guess from that mask.
"""

from __future__ import annotations

import numpy as np

SMOOTH = 0.01         # overlap given up per degree the leaf turns between neighbouring frames (dynamic programming)
STILL = 10.0          # ... this many times more between frames the labels say rest at one state


def smooth_path(curves: np.ndarray, angles: np.ndarray, still: np.ndarray | None = None) -> np.ndarray:
    """Grid positions (F,) maximising the summed overlap less `SMOOTH` per degree turned between neighbours
    (Viterbi over frames in order; angles wrap); `still` (F,): frame f and f-1 rest at one labelled state, where a
    turn costs `STILL` times more. Why the labels' stillness: a leaf and its mirror image about the plane through its
    axis and the camera cast nearly one silhouette, and the mirror turns as the camera moves; where the part rests,
    only the true leaf stays put."""
    return viterbi(curves, SMOOTH * turn_degrees(angles), np.zeros(len(curves), bool) if still is None else still)[0]


def turn_degrees(angles: np.ndarray) -> np.ndarray:
    """(A, A) degrees between the grid's angles, the short way round."""
    n = len(angles)
    diff = np.abs(np.arange(n)[:, None] - np.arange(n)[None, :])
    return np.degrees(angles[1] - angles[0]) * np.minimum(diff, n - diff)


def viterbi(curves: np.ndarray, jump: np.ndarray, still: np.ndarray) -> tuple[np.ndarray, float]:
    """`smooth_path`'s grid positions and their total score; `jump` (A, A): what a turn between neighbours costs."""
    n = curves.shape[1]
    score = curves[0].copy()
    back = np.zeros(curves.shape, int)
    for f in range(1, len(curves)):
        total = score[:, None] - jump * (STILL if still[f] else 1.0)  # from (rows) -> to (cols)
        back[f] = np.argmax(total, axis=0)
        score = total[back[f], np.arange(n)] + curves[f]
    path = np.zeros(len(curves), int)
    path[-1] = int(np.argmax(score))
    for f in range(len(curves) - 1, 0, -1):
        path[f - 1] = back[f, path[f]]
    return path, float(score.max())


def anchored_path(curves: np.ndarray, angles: np.ndarray, still: np.ndarray, ends: list[np.ndarray],
                  jump: np.ndarray | None = None) -> np.ndarray:
    """`smooth_path` where the frames of each of `ends` (bool (F,) each: the frames labelled closed, those labelled
    fully open) share one angle, give or take what a turn between neighbours at rest costs: every grid angle tried
    as the first end's, the best total kept, then the next end's with it. Why: the mirror image turns with the
    camera, so it cannot sit at one angle in frames at one end filmed from different places, however far apart in
    time (a door closed at the start, in the middle and at the end). jump (A, A): what a move between neighbours
    costs (default: `SMOOTH` per degree turned; a slide passes its own)."""
    jump = SMOOTH * turn_degrees(angles) if jump is None else jump
    away = STILL * jump  # (A, A): from the shared angle (rows)
    held = curves.copy()
    path = viterbi(curves, jump, still)[0]
    for end in ends:
        if end.sum() < 2:
            continue
        best: tuple[float, int, np.ndarray] = (-np.inf, 0, path)
        for c in range(len(angles)):
            trial = held.copy()
            trial[end] -= away[c]
            p, score = viterbi(trial, jump, still)
            if score > best[0]:
                best = (score, c, p)
        held[end] -= away[best[1]]
        path = best[2]
    return path


def refine(curve: np.ndarray, j: int, angles: np.ndarray) -> float:
    """The angle at grid position j moved to the top of a parabola through it and its (wrapped) neighbours."""
    a, b, c = curve[j - 1], curve[j], curve[(j + 1) % len(curve)]
    den = a - 2 * b + c
    shift = 0.5 * (a - c) / den if den < 0 else 0.0
    return float(angles[j] + np.clip(shift, -0.5, 0.5) * (angles[1] - angles[0]))
