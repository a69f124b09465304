"""Which (camera, state) pairs no training view supports, for the parts whose motion was not measured.

A part with a measured rigid motion (`articulation.json`, `model.motion`) is moved as one body, so any state is
drawn from what any view saw. A part without one is only what the capture showed near each camera at each state:
from a camera whose nearby training views all had the drawer open, "closed" was never seen and comes out blurred or
not at all. `eval` and the demo list those pairs (`render` and `view` warn per render through
`render.warn_unseen`), so a user reads "door at 0.00: cameras 00012, 00020" instead of trusting a wrong picture.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .render import UNSEEN_TOL, learned_frame_states, unseen_states

SWEEP_STATES = (0.0, 0.5, 1.0)  # the ends and the middle of a state sweep


def parts_without_motion(run) -> list[int]:
    """Object ids the run moves with no measured rigid motion (every object when the run has none)."""
    motions = getattr(run.model, "motions", None)
    m = run.model.n_objects
    if motions is None:
        return list(range(m))
    kinds = motions.kind.detach().cpu().numpy()
    return [o for o in range(m) if int(kinds[o]) == 0]


def unsupported_pairs(run, frames: list[int], states: tuple[float, ...] = SWEEP_STATES,
                      tol: float = UNSEEN_TOL) -> list[dict[str, Any]]:
    """Per part without a measured motion and per state: the cameras (dataset frame positions `frames`) whose nearby
    training views never showed it within `tol` of that state, with the states those views did show."""
    learned = learned_frame_states(run)
    views = run.views
    out = []
    for o in parts_without_motion(run):
        name = run.names[o]
        for v in states:
            cams, shown = [], []
            for i in frames:
                near = unseen_states(run, learned, views.c2w_gl[i], {name: float(v)}, tol)
                if name in near:
                    cams.append(views.dataset.frames[i].fid)
                    shown.append(round(near[name], 2))
            if cams:
                out.append({"object": name, "state": float(v), "cameras": cams, "of": len(frames),
                            "nearest_seen": shown})
    return out


def support_lines(pairs: list[dict[str, Any]], most: int = 6) -> list[str]:
    """One warning line per (part, state) that some camera cannot support."""
    lines = []
    for p in pairs:
        cams = ", ".join(p["cameras"][:most]) + (" ..." if len(p["cameras"]) > most else "")
        seen = sorted(set(p["nearest_seen"]))
        lines.append(f"warning: '{p['object']}' has no measured motion, and near {len(p['cameras'])} of {p['of']} "
                     f"cameras ({cams}) no training view showed it at state {p['state']:.2f} (they show "
                     f"{', '.join(f'{s:.2f}' for s in seen[:4])}): rendered there it is a guess (blurred or missing); "
                     f"film it at that state from there, or measure its motion (`interreal motions`)")
    return lines


def sweep_frames(views, count: int = 8) -> list[int]:
    """Cameras to check: the held-out ones (else training ones), evenly spread, at most `count`."""
    pool = list(views.held_out) or list(views.train)
    if len(pool) <= count:
        return pool
    return [pool[int(j)] for j in np.linspace(0, len(pool) - 1, count).round().astype(int)]
