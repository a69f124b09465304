"""A part's own reconstruction re-posed by the known cameras: its tracks, the scene's cameras, the motion's model.

The part's own SfM (`part.map_part`) finds the part's cameras from the part's pixels alone. A small, nearly flat
part (a drawer's front) seen over a narrow arc leaves their rotation and translation traded against each other,
and the reconstruction can read the camera's own turn as the part's: a drawer then comes out as a hinge turning
with the camera and is refused (`fit.turns_with_camera`; 3 of the 6 textured simulated drawers). Its feature tracks
are sound; only its poses are not. And a slide's length is in the scene's units, which its own reconstruction
reaches only through a fitted scale. Where its own motion is refused, or is a slide (`part.posed_fit`):
1. the tracks seen over a stretch where the labels say the part rests (`pnp.reference_frames`) are triangulated with
   the known cameras: world units, and the baseline of that whole stretch of the capture;
2. every registered frame's camera relative to the resting part by PnP on those points (`pnp.solve_pnp`);
3. the kind from those free poses (`fit.choose`), then every frame's pose again with only the freedom that kind
   has: a slide's translation, a hinge's angle about its fitted axis (`first_poses`);
4. the tracks triangulated again through every located frame (the part turned or pulled out shows them from angles
   the resting stretch never did) and the frames they locate added (`grow`);
5. the axis, every frame's angle or distance and the points adjusted together to every frame's pixels, the cameras
   held (`adjust`). The measured states must then stay put over the resting stretch (`REST_SPREAD`): eyeballed
   labels can call a stretch at rest where the part moves, and the structure triangulated there moves with it (the
   real laptop's lid: 82 deg for 54); the next stretch is tried.
The result is what `fit.fit_motion` reads, in world units (scale 1).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix

from ..conventions import opengl_to_opencv
from ..dataset import Articulation
from .fit import Fit, axis_angle, basis, choose, fit_hinge, fit_motion, fit_slide, part_point
from .pnp import MAX_REPROJ_PX, MIN_INLIERS, MIN_RAY_DEG, PNP_PX, reference_frames, solve_pnp, views_of_poses

MIN_POINTS = 20      # a resting stretch that triangulates fewer of the tracks is not tried
MAX_REFERENCES = 3   # resting stretches tried, the labels' likeliest first
REST_SPREAD = 0.05   # measured states spreading more than this over the resting stretch: it did not rest there
PER_FRAME = 40       # points adjusted with the motion: each frame's this many most-seen (bounds the adjustment)
MAX_STEPS = 100      # ... and at most this many steps (one started from a stretch the part moved over wanders)
UNSETTLED = f"the motion and points adjusted together did not settle in {MAX_STEPS} steps"
ROBUST_PX = 2.0      # scale of the robust loss of the constrained poses (px)
MIN_FRAMES = 3       # fewer frames located: nothing to fit

Track = tuple[np.ndarray, np.ndarray]  # one frame's point ids (N,) and the pixels it sees them at (N, 2)
Located = tuple[np.ndarray, np.ndarray, np.ndarray]  # camera from the resting part (3x4), inliers' ids, pixels


def tracks(rec, ds) -> dict[int, Track]:
    """Per dataset position registered in the part's reconstruction `rec` (pycolmap): the ids of the points it
    sees and where (the dataset's pixels: the reconstruction holds the dataset's intrinsics fixed)."""
    by_name = {Path(f.file_path).name: i for i, f in enumerate(ds.frames)}
    out: dict[int, Track] = {}
    for im in rec.images.values():
        if not im.has_pose or im.name not in by_name:
            continue
        seen = [(p.point3D_id, p.xy) for p in im.points2D if p.has_point3D()]
        out[by_name[im.name]] = (np.array([a for a, _ in seen], np.int64),
                                 np.array([b for _, b in seen], np.float64).reshape(-1, 2))
    return out


def triangulate_tracks(obs: dict[int, Track], proj: dict[int, np.ndarray], k: np.ndarray, dist: np.ndarray
                       ) -> dict[int, np.ndarray]:
    """Points (3,) of the tracks seen in two or more of the frames `proj` names, through each one's camera (3x4, x
    = K (R X + t)): the known cameras where the part rests (it is then triangulated as the room would be), or the
    cameras relative to the resting part once it is located. Kept when in front of every camera, within
    MAX_REPROJ_PX of each sighting and seen under at least MIN_RAY_DEG between some two of them."""
    centre = {r: -m[:, :3].T @ m[:, 3] for r, m in proj.items()}
    seen: dict[int, list[tuple[int, np.ndarray]]] = {}
    for r in proj:
        ids, xy = obs[r]
        norm = cv2.undistortPoints(xy.reshape(-1, 1, 2), k, dist).reshape(-1, 2)
        for pid, n in zip(ids.tolist(), norm):
            seen.setdefault(pid, []).append((r, n))
    out = {}
    for pid, sights in seen.items():
        if len(sights) < 2:
            continue
        p = np.stack([proj[r] for r, _ in sights])  # (S, 3, 4)
        n = np.stack([v for _, v in sights])  # (S, 2)
        a = (n[:, :, None] * p[:, 2:3, :] - p[:, :2, :]).reshape(-1, 4)
        x = np.linalg.svd(a)[2][-1]
        if abs(x[3]) < 1e-12:
            continue
        x = x[:3] / x[3]
        cam = p[:, :, :3] @ x + p[:, :, 3]
        if (cam[:, 2] <= 1e-6).any():
            continue
        if (np.linalg.norm(cam[:, :2] / cam[:, 2:] - n, axis=1) * k[0, 0] > MAX_REPROJ_PX).any():
            continue
        rays = np.stack([x - centre[r] for r, _ in sights])
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        if np.degrees(np.arccos(np.clip((rays @ rays.T).min(), -1.0, 1.0))) >= MIN_RAY_DEG:
            out[pid] = x
    return out


def locate_all(obs: dict[int, Track], pts: dict[int, np.ndarray], k: np.ndarray, dist: np.ndarray
               ) -> dict[int, Located]:
    """Every frame that PnP locates against the resting part's points: its camera and the inliers."""
    out = {}
    for i, track in obs.items():
        ids, obj, xy = sighted(track, pts)
        hit = solve_pnp(obj, xy, k, dist)
        if hit is not None:
            out[i] = (hit[0], ids[hit[1]], xy[hit[1]])
    return out


def sighted(track: Track, pts: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ids (M,), points (M, 3), pixels (M, 2)) of the frame's sightings of the points `pts` has."""
    ids, xy = track
    keep = np.array([pid in pts for pid in ids.tolist()], bool).reshape(-1)
    return ids[keep], np.array([pts[int(q)] for q in ids[keep]]).reshape(-1, 3), xy[keep]


def camera(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rvec, tvec) of the known camera c2w (4x4, OpenCV axes), as `cv2.projectPoints` takes them."""
    w2c = np.linalg.inv(c2w)
    return cv2.Rodrigues(w2c[:3, :3])[0], w2c[:3, 3]


def motion_in_world(pose: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """4x4: where the part moved from rest (world -> world), from the camera relative to the resting part."""
    return c2w @ np.vstack([pose, [0.0, 0.0, 0.0, 1.0]])


def slide_pose(where: Located, pts: dict[int, np.ndarray], c2w: np.ndarray, mid: np.ndarray, k: np.ndarray,
               dist: np.ndarray) -> np.ndarray:
    """The frame's camera relative to the resting part (3x4) again, the part only translated (a slide's frame may
    stray a little off its line, never turn); started where its free pose puts the part's middle `mid`."""
    pose, ids, img = where
    obj = np.array([pts[int(p)] for p in ids])
    rvec, tvec = camera(c2w)
    free = motion_in_world(pose, c2w)

    def residual(x: np.ndarray) -> np.ndarray:
        return (cv2.projectPoints(obj + x, rvec, tvec, k, dist)[0].reshape(-1, 2) - img).ravel()

    x = least_squares(residual, free[:3, :3] @ mid + free[:3, 3] - mid, loss="soft_l1", f_scale=ROBUST_PX).x
    moved = np.eye(4)
    moved[:3, 3] = x
    return (np.linalg.inv(c2w) @ moved)[:3]


def best_angle(axis: np.ndarray, point: np.ndarray, obj: np.ndarray, img: np.ndarray,
               cam: tuple[np.ndarray, np.ndarray], k: np.ndarray, dist: np.ndarray) -> float:
    """The angle about the axis (1-deg grid, the whole turn) whose turned points land nearest their pixels
    (truncated at PNP_PX): a frame's free pose can be the mirror of the right one (a flat part), its angle far off."""
    angles = np.radians(np.arange(-180.0, 180.0, 1.0))
    turned = (obj - point)[None] @ axis_angle(axis, angles).transpose(0, 2, 1) + point  # (A, N, 3)
    seen = cv2.projectPoints(turned.reshape(-1, 3), cam[0], cam[1], k, dist)[0].reshape(len(angles), -1, 2)
    cost = np.minimum(np.linalg.norm(seen - img[None], axis=2), PNP_PX).sum(1)
    return float(angles[int(np.argmin(cost))])


def jacobian_sparsity(which: list[np.ndarray], point_columns: int) -> coo_matrix:
    """Which parameters each residual reads (rows: x and y of each frame's sightings in turn; columns: the axis's 4,
    one per frame, then 3 per point when the points move): every row the axis, its frame's value and its point."""
    f = len(which)
    rows, cols = [], []
    start = 0
    for j, w in enumerate(which):
        r = start + np.arange(2 * len(w))
        rows += [np.repeat(r, 4), r]
        cols += [np.tile(np.arange(4), len(r)), np.full(len(r), 4 + j)]
        if point_columns:
            rows.append(np.repeat(r, 3))
            cols.append((4 + f + 3 * np.repeat(np.repeat(w, 2), 3) + np.tile(np.arange(3), len(r))))
        start += len(r)
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    return coo_matrix((np.ones(len(rows), bool), (rows, cols)), shape=(start, 4 + f + point_columns))


def adjust(kind: str, axis: np.ndarray, point: np.ndarray, starts: list[float], located: dict[int, Located],
           pts: dict[int, np.ndarray], c2w: dict[int, np.ndarray], k: np.ndarray, dist: np.ndarray,
           move_points: bool = False) -> dict[int, np.ndarray] | None:
    """Every located frame's camera relative to the resting part (3x4), the part moved only as `kind` can: the
    axis (its direction and, for a hinge, where it passes), each frame's angle or distance (from `starts`, in frame
    order) and, with `move_points`, the part's points that two or more frames see, adjusted together to every
    frame's pixels with the cameras held (there is no gauge to fix); None when it does not settle in MAX_STEPS.
    An axis fitted to free poses and then held leaves each frame's angle to make up for its error, and points
    triangulated where the part rests carry that stretch's narrow baseline: the simulated fridge door read 88 deg
    for its 100 with both held, 97 with the points held, 99.9 with neither."""
    frames = sorted(located)
    counts: dict[int, int] = {}
    for i in frames:
        for q in located[i][1].tolist():
            counts[q] = counts.get(q, 0) + 1
    keep = {q for q, n in counts.items() if n >= 2 or not move_points}
    if move_points:  # each frame's most-seen points: the few parameters of the motion need hundreds, not thousands
        keep = {q for i in frames for q in sorted((q for q in located[i][1].tolist() if q in keep),
                                                  key=lambda q: (-counts[q], q))[:PER_FRAME]}
    col = {q: n for n, q in enumerate(sorted(keep))}
    points = np.array([pts[q] for q in col]).reshape(-1, 3)
    seen = [np.array([j for j, q in enumerate(located[i][1].tolist()) if q in col], int) for i in frames]
    which = [np.array([col[q] for q in located[i][1][j].tolist()], int) for i, j in zip(frames, seen)]
    pix = [located[i][2][j] for i, j in zip(frames, seen)]
    b, f = basis(axis), len(frames)
    rt = [camera(c2w[i]) for i in frames]

    def motions(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(F, 3, 3) rotations and (F, 3) translations of the part from rest."""
        a = axis + b @ x[:2]
        a /= np.linalg.norm(a)
        if kind == "slide":
            return np.broadcast_to(np.eye(3), (f, 3, 3)), np.outer(x[4:4 + f], a)
        r = axis_angle(a, x[4:4 + f])
        at = point + b @ x[2:4]
        return r, at - r @ at

    def residual(x: np.ndarray) -> np.ndarray:
        rots, shifts = motions(x)
        at = x[4 + f:].reshape(-1, 3) if move_points else points
        seen = (cv2.projectPoints(at[w] @ r.T + t, *c, k, dist)[0].reshape(-1, 2) - px
                for w, px, r, t, c in zip(which, pix, rots, shifts, rt))
        return np.concatenate([v.ravel() for v in seen])

    sparsity = jacobian_sparsity(which, 3 * len(col) if move_points else 0)
    x0 = np.concatenate([np.zeros(4), starts] + ([points.ravel()] if move_points else []))
    fit = least_squares(residual, x0, loss="soft_l1", f_scale=ROBUST_PX, jac_sparsity=sparsity, x_scale="jac",
                        max_nfev=MAX_STEPS)
    if not fit.success:  # it did not settle: a wandering adjustment is no measurement
        return None
    x = fit.x
    if move_points:
        pts.update({q: v for q, v in zip(col, x[4 + f:].reshape(-1, 3))})
    rots, shifts = motions(x)
    out = {}
    for r, t, i in zip(rots, shifts, frames):
        moved = np.eye(4)
        moved[:3, :3], moved[:3, 3] = r, t
        out[i] = (np.linalg.inv(c2w[i]) @ moved)[:3]
    return out


def grow(obs: dict[int, Track], poses: dict[int, np.ndarray], k: np.ndarray, dist: np.ndarray, rounds: int = 3
         ) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """The tracks triangulated from every located frame (the part turned or pulled out shows them from angles
    the resting stretch never did), and the frames those points locate that the resting part's did not (a door
    seen wide open shares few tracks with it closed), until none is added. Returns (points, poses)."""
    poses = dict(poses)
    for _ in range(rounds):
        pts = triangulate_tracks(obs, poses, k, dist)
        new = locate_all({i: v for i, v in obs.items() if i not in poses}, pts, k, dist)
        poses.update({i: v[0] for i, v in new.items()})
        if not new:
            break
    return pts, poses


def first_poses(fit: Fit, located: dict[int, Located], pts: dict[int, np.ndarray], c2w: dict[int, np.ndarray],
                mid: np.ndarray, k: np.ndarray, dist: np.ndarray) -> dict[int, np.ndarray] | None:
    """Every located frame's camera relative to the resting part, moved only as `fit`'s kind can, the points held:
    a hinge's angles from `best_angle` adjusted with its axis, a slide's frames each translated."""
    if fit.kind == "slide":
        return {i: slide_pose(v, pts, c2w[i], mid, k, dist) for i, v in located.items()}
    return adjust("hinge", fit.axis, fit.point, hinge_starts(fit, located, pts, c2w, k, dist), located, pts, c2w,
                  k, dist)


def hinge_starts(fit: Fit, located: dict[int, Located], pts: dict[int, np.ndarray], c2w: dict[int, np.ndarray],
                 k: np.ndarray, dist: np.ndarray) -> list[float]:
    """Each located frame's `best_angle` about `fit`'s axis, in frame order."""
    return [best_angle(fit.axis, fit.point, np.array([pts[int(q)] for q in located[i][1]]), located[i][2],
                       camera(c2w[i]), k, dist) for i in sorted(located)]


def adjusted_poses(kind: str, poses: dict[int, np.ndarray], located: dict[int, Located], pts: dict[int, np.ndarray],
                   c2w: dict[int, np.ndarray], mid: np.ndarray, k: np.ndarray, dist: np.ndarray
                   ) -> dict[int, np.ndarray] | None:
    """The poses, the motion and the points adjusted together (`adjust`), started from `poses`' own fit."""
    views = views_of_poses(poses, c2w, mid)
    fit = fit_hinge(views) if kind == "hinge" else fit_slide(views)
    if kind == "hinge":
        starts = hinge_starts(fit, located, pts, c2w, k, dist)
    else:  # the part's middle, not the world's origin: a free pose's turn noise swings that far
        moves = [motion_in_world(poses[i], c2w[i]) for i in sorted(located)]
        starts = [float((m[:3, :3] @ mid + m[:3, 3] - mid) @ fit.axis) for m in moves]
    return adjust(kind, fit.axis, fit.point, starts, located, pts, c2w, k, dist, move_points=True)


def relocate(obs: dict[int, Track], pts: dict[int, np.ndarray], poses: dict[int, np.ndarray], k: np.ndarray,
             dist: np.ndarray) -> dict[int, Located]:
    """Each frame's inliers among the points `pts` (the resting part's frame) under its pose: within PNP_PX."""
    out = {}
    for i, pose in poses.items():
        ids, obj, xy = sighted(obs[i], pts)
        seen = cv2.projectPoints(obj, cv2.Rodrigues(pose[:, :3])[0], pose[:, 3], k, dist)[0].reshape(-1, 2)
        ok = np.linalg.norm(seen - xy, axis=1) < PNP_PX
        if ok.sum() >= MIN_INLIERS:
            out[i] = (pose, ids[ok], xy[ok])
    return out


class Scene(NamedTuple):
    """What every reference shares: the reconstruction's tracks, the frames' known cameras (c2w, OpenCV axes), K."""

    obs: dict[int, Track]
    c2w: dict[int, np.ndarray]
    k: np.ndarray
    dist: np.ndarray


def from_reference(sc: Scene, ref: list[int], states: np.ndarray, known: np.ndarray, labelled: np.ndarray,
                   trust_labels: bool) -> tuple[Articulation | None, dict[str, Any]]:
    """The motion with the part taken to rest over the frames `ref`: its tracks there triangulated with the known
    cameras, every frame located by PnP, the kind from those free poses (`fit.choose`), the poses again with that
    kind's freedom only (`first_poses`), the points from every located frame (`grow`), then motion and points
    adjusted together (`adjusted_poses`). `rest_spread`: how far the measured states spread over `ref` (a share of
    the range); a stretch the part did not rest over (eyeballed labels) gives a structure that moves with it."""
    pts = triangulate_tracks(sc.obs, {r: np.linalg.inv(sc.c2w[r])[:3] for r in ref}, sc.k, sc.dist)
    located = locate_all(sc.obs, pts, sc.k, sc.dist) if len(pts) >= MIN_POINTS else {}
    fig: dict[str, Any] = {"known_points": len(pts), "known_reference": [int(r) for r in ref],
                           "known_located": len(located), "registered": len(located), "at_known_state": 0}
    if len(located) < MIN_FRAMES:
        return None, fig
    mid = part_point(np.array(list(pts.values())))
    free = views_of_poses({i: v[0] for i, v in located.items()}, sc.c2w, mid)
    chosen, _ = choose(fit_hinge(free), fit_slide(free), free)
    poses = first_poses(chosen, located, pts, sc.c2w, mid, sc.k, sc.dist)
    if poses is None:
        return None, dict(fig, known_reason=UNSETTLED)
    pts, poses = grow(sc.obs, poses, sc.k, sc.dist)
    located = relocate(sc.obs, pts, poses, sc.k, sc.dist)
    fig.update(known_points_all=len(pts), known_located_all=len(located), registered=len(located))
    if len(located) < MIN_FRAMES:
        return None, fig
    poses = adjusted_poses(chosen.kind, poses, located, pts, sc.c2w, mid, sc.k, sc.dist)
    if poses is None:
        return None, dict(fig, known_reason=UNSETTLED)
    # the cameras held, a turn the labels say did not happen is the part's (`rest_spread` judges it), never the
    # camera's read as the part's: no `fit.turns_with_camera` check
    views = replace(views_of_poses(poses, sc.c2w, mid), cam_rot=None)
    motion, out = fit_motion(views, states[views.frames], known[views.frames], labelled[views.frames], trust_labels)
    at_ref = [s for f, s in out.get("frame_states", []) if f in ref]
    out.update(fig, poses_from="known cameras", free_kind=chosen.kind, at_known_state=int(known[views.frames].sum()),
               rest_spread=round(float(np.ptp(at_ref)), 4) if len(at_ref) >= 2 else None)
    return motion, out


def known_camera_motion(rec, ds, states: np.ndarray, known: np.ndarray, labelled: np.ndarray,
                        trust_labels: bool = False) -> tuple[Articulation | None, dict[str, Any]]:
    """The motion from the part's reconstruction `rec` re-posed by the known cameras (states, known, labelled over
    the dataset's frames, as `fit.fit_motion` reads them): from the first of the labels' candidate resting
    stretches (`pnp.reference_frames`, at most MAX_REFERENCES) the geometry agrees the part rests over (its states
    there within REST_SPREAD); refused, with the stretches' spreads, when none does; None and its figures when too
    few frames locate."""
    obs = tracks(rec, ds)
    sc = Scene(obs, {i: opengl_to_opencv(ds.frames[i].c2w) for i in obs}, ds.intrinsics.K(), ds.intrinsics.dist())
    best: tuple[Articulation | None, dict[str, Any]] = (None, {"known_located": 0, "registered": 0,
                                                               "at_known_state": 0})
    spreads, least = [], np.inf
    for ref in reference_frames(sorted(obs), states, known, labelled)[:MAX_REFERENCES]:
        ref = [r for r in ref if r in obs]
        motion, fig = from_reference(sc, ref, states, known, labelled, trust_labels) if len(ref) >= 2 else (None, {})
        if motion is None:
            best = best if best[0] is not None or not fig else (None, fig)
            continue
        spread = fig["rest_spread"] if fig["rest_spread"] is not None else np.inf
        spreads.append(f"{spread:.2f} over frames {ref[0]}-{ref[-1]}" if np.isfinite(spread)
                       else f"frames {ref[0]}-{ref[-1]} not measured")
        if spread <= REST_SPREAD:
            return motion, fig
        if best[0] is None or spread < least:
            best, least = (motion, fig), spread
    if best[0] is not None:
        best[1].update(accepted=False, reason=f"the part moved where the labels say it rests: its measured states "
                                              f"spread {'; '.join(spreads)} (need {REST_SPREAD} or less)")
    return best
