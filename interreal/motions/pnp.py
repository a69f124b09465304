"""A part's per-frame poses without its own reconstruction: triangulate it once, then PnP every frame.

The part's own SfM (`motions.part`) must find the camera poses *and* the part's shape from the part's pixels
alone; a part with little texture (a grey cabinet door: 9 of 200 frames registered) gives it too little. Here the
camera poses are already known (transforms.json), so far less is needed:
1. a reference: a few frames where the part holds one state (frames labelled alike, or the frames nearest a
   labelled one); its masked SIFT features matched between those frames are triangulated with the known cameras
   (the part is static there, so this is plain two-view triangulation in world units, no scale to find);
2. every frame's masked features are matched to those points and its camera solved relative to the part (PnP
   with RANSAC); with the frame's world camera that is the part's rigid transform from the reference state.
The result is a `PartViews` with scale 1 that `fit.fit_motion` reads like the reconstruction's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from .fit import PartViews, part_point

RATIO = 0.8  # Lowe's ratio test
MAX_REPROJ_PX = 2.0  # a triangulated point must reproject within this in both frames
MIN_RAY_DEG = 2.0  # ... and be seen under at least this angle (depth from a tiny baseline is noise)
PNP_PX = 3.0  # RANSAC threshold of PnP
MIN_INLIERS = 12  # fewer PnP inliers: the frame is not registered


@dataclass
class Features:
    """SIFT keypoints (K, 2) px and descriptors (K, 128) inside one frame's part mask."""

    pts: np.ndarray
    desc: np.ndarray


def features(gray: np.ndarray, mask: np.ndarray, most: int = 2000) -> Features:
    sift = cv2.SIFT_create(nfeatures=most)
    kps, desc = sift.detectAndCompute(gray, mask.astype(np.uint8) * 255)
    if desc is None:
        return Features(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32))
    return Features(np.array([k.pt for k in kps], np.float32), desc.astype(np.float32))


def match(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(M, 2) index pairs of descriptors a -> b passing the ratio test and mutual (cross-checked)."""
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), int)
    bf = cv2.BFMatcher(cv2.NORM_L2)
    fwd = bf.knnMatch(a, b, k=2)
    back = {m.queryIdx: m.trainIdx for m in bf.match(b, a)}
    out = [(m.queryIdx, m.trainIdx) for m, n in (p for p in fwd if len(p) == 2)
           if m.distance < RATIO * n.distance and back.get(m.trainIdx) == m.queryIdx]
    return np.array(out, int).reshape(-1, 2)


def _normalised(pts: np.ndarray, k: np.ndarray, dist: np.ndarray) -> np.ndarray:
    return cv2.undistortPoints(pts.reshape(-1, 1, 2).astype(np.float64), k, dist).reshape(-1, 2)


def triangulate(fa: Features, fb: Features, pa: np.ndarray, pb: np.ndarray, k: np.ndarray,
                dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (P, 3) in the part's reference frame and their descriptors (P, 128) from two frames whose cameras
    relative to the part (pa, pb: 3x4, x = K (R X + t)) are known: matched, triangulated, kept when in front of
    both, seen under MIN_RAY_DEG and reprojecting within MAX_REPROJ_PX."""
    m = match(fa.desc, fb.desc)
    if len(m) < 8:
        return np.zeros((0, 3)), np.zeros((0, 128), np.float32)
    na, nb = _normalised(fa.pts[m[:, 0]], k, dist), _normalised(fb.pts[m[:, 1]], k, dist)
    x = cv2.triangulatePoints(pa, pb, na.T, nb.T)
    x = (x[:3] / np.where(np.abs(x[3]) < 1e-12, 1e-12, x[3])).T
    ok = np.ones(len(x), bool)
    rays = []
    for pm, n in ((pa, na), (pb, nb)):
        cam = x @ pm[:, :3].T + pm[:, 3]
        ok &= cam[:, 2] > 1e-6
        err = np.linalg.norm(cam[:, :2] / np.maximum(cam[:, 2:], 1e-6) - n, axis=1) * k[0, 0]
        ok &= err < MAX_REPROJ_PX
        rays.append(x + pm[:, :3].T @ pm[:, 3])  # point minus the camera centre
    cosang = np.sum(rays[0] * rays[1], 1) / np.maximum(np.linalg.norm(rays[0], axis=1)
                                                       * np.linalg.norm(rays[1], axis=1), 1e-12)
    ok &= cosang < np.cos(np.radians(MIN_RAY_DEG))
    return x[ok], fa.desc[m[ok, 0]]


def locate(f: Features, pts: np.ndarray, desc: np.ndarray, k: np.ndarray, dist: np.ndarray
           ) -> tuple[np.ndarray, int] | None:
    """(P 3x4, inliers): the camera relative to the reference-state part (x = K (R X + t)), or None."""
    m = match(f.desc, desc)
    if len(m) < MIN_INLIERS:
        return None
    hit = solve_pnp(pts[m[:, 1]], f.pts[m[:, 0]], k, dist)
    return None if hit is None else (hit[0], len(hit[1]))


def solve_pnp(obj: np.ndarray, img: np.ndarray, k: np.ndarray, dist: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray] | None:
    """(P 3x4, inlier indices) of the camera seeing points obj (N, 3) at pixels img (N, 2): SQPnP in RANSAC (a
    planar part's mirrored pose is not taken), refined on the inliers; None under MIN_INLIERS."""
    obj, img = np.asarray(obj, np.float64), np.asarray(img, np.float64)
    if len(obj) < MIN_INLIERS:
        return None
    ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, k, dist, iterationsCount=300, reprojectionError=PNP_PX,
                                             confidence=0.999, flags=cv2.SOLVEPNP_SQPNP)
    if not ok or inl is None or len(inl) < MIN_INLIERS:
        return None
    idx = inl.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(obj[idx], img[idx], k, dist, rvec, tvec)
    return np.concatenate([cv2.Rodrigues(rvec)[0], tvec.reshape(3, 1)], 1), idx


def _grow(order: list[int], located: dict[int, tuple[np.ndarray, int]], feats: dict[int, Features],
          k: np.ndarray, dist: np.ndarray, near: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Points triangulated from pairs of located frames next to the frames not located yet (each frame's camera
    relative to the part is known, moving or not): they reach states far from the reference. Only used for the
    frames the reference alone cannot locate, as their poses carry the located frames' errors."""
    pts, desc = [np.zeros((0, 3))], [np.zeros((0, 128), np.float32)]
    done: set[tuple[int, int]] = set()
    pos = {p: j for j, p in enumerate(order)}
    for i in order:
        if i in located:
            continue
        close = sorted((p for p in located if abs(pos[p] - pos[i]) <= near), key=lambda p: abs(pos[p] - pos[i]))
        if len(close) < 2:
            continue
        a = close[0]
        b = max(close[1:], key=lambda p: abs(pos[p] - pos[a]))  # the widest baseline near the frame
        if (a, b) in done:
            continue
        done.add((a, b))
        x, d = triangulate(feats[a], feats[b], located[a][0], located[b][0], k, dist)
        pts.append(x)
        desc.append(d)
    return np.concatenate(pts), np.concatenate(desc)


def reference_points(feats: dict[int, Features], refs: list[list[int]], c2w: dict[int, np.ndarray],
                     k: np.ndarray, dist: np.ndarray, enough: int = 200, pairs: int = 6
                     ) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """The part's points at the first candidate reference that triangulates `enough` of them (else the best):
    each reference's `pairs` most distant frame pairs, triangulated with the known cameras."""
    best: tuple[np.ndarray, np.ndarray, list[int]] = (np.zeros((0, 3)), np.zeros((0, 128), np.float32), [])
    for ref in refs:
        ref = [r for r in ref if r in feats]
        cam = {r: np.linalg.inv(c2w[r])[:3] for r in ref}  # at the reference state, the part's frame is the world's
        far = sorted(((a, b) for i, a in enumerate(ref) for b in ref[i + 1:]), key=lambda p: -abs(p[1] - p[0]))
        got = [triangulate(feats[a], feats[b], cam[a], cam[b], k, dist) for a, b in far[:pairs]]
        pts = np.concatenate([np.zeros((0, 3))] + [g[0] for g in got])
        desc = np.concatenate([np.zeros((0, 128), np.float32)] + [g[1] for g in got])
        if len(pts) > len(best[0]):
            best = (pts, desc, ref)
        if len(pts) >= enough:
            break
    return best


def pnp_views(grays: dict[int, np.ndarray], masks: dict[int, np.ndarray], c2w: dict[int, np.ndarray],
              k: np.ndarray, dist: np.ndarray, refs: list[list[int]], most: int = 1500, rounds: int = 3
              ) -> tuple[PartViews | None, dict[str, Any]]:
    """The part's pose at every frame it can be located in, relative to its state at a reference.

    grays, masks: per dataset position, the grey image and the part's (eroded, transient-free) pixels; c2w (4x4,
    OpenCV axes) the frame's known camera. Every frame is located against the points triangulated at the
    reference (SQPnP, so a planar part's mirrored pose is not taken); frames too far from it are retried against
    points triangulated from located frames near them (`_grow`, up to `rounds`). `refs`: candidate reference frame
    sets (`reference_frames`); the first that triangulates enough points is used. Returns the views (None when too
    few points or fewer than 3 frames located) and figures."""
    feats = {i: features(grays[i], masks[i], most) for i in grays}
    pts, desc, ref = reference_points(feats, refs, c2w, k, dist)
    point = part_point(pts)  # the path of the part's middle, not of the world's origin metres away
    fig: dict[str, Any] = {"route": "pnp", "reference_frames": [int(r) for r in ref], "points": int(len(pts))}
    order = sorted(feats)
    located: dict[int, tuple[np.ndarray, int]] = {}
    for r in range(rounds):
        if len(pts) < MIN_INLIERS:
            break
        for i in order:
            if i not in located:
                hit = locate(feats[i], pts, desc, k, dist)
                if hit is not None:
                    located[i] = hit
        fig[f"located_round_{r}"] = len(located)
        if len(located) == len(order) or not located:
            break
        pts, desc = _grow(order, located, feats, k, dist)
    frames = sorted(located)
    fig.update(located=len(frames), median_inliers=int(np.median([located[i][1] for i in frames])) if frames else 0)
    if len(frames) < 3:
        return None, fig
    return views_of_poses({i: located[i][0] for i in frames}, c2w, point), fig


def views_of_poses(poses: dict[int, np.ndarray], c2w: dict[int, np.ndarray], point: np.ndarray) -> PartViews:
    """`PartViews` (scale 1) from each frame's camera relative to the part at its reference state (3x4, x = K (R X
    + t), X in the world as the part rests) and the frame's known camera (c2w 4x4, OpenCV axes); `point`: the
    part's middle at rest, whose path is followed."""
    frames = sorted(poses)
    cam = np.stack([c2w[i][:3, :3] for i in frames])
    pose = np.stack([poses[i] for i in frames])  # (F, 3, 4)
    rot = cam @ pose[:, :, :3]
    u = np.einsum("fij,fj->fi", cam, pose[:, :, :3] @ point + pose[:, :, 3])
    centre = np.stack([c2w[i][:3, 3] for i in frames])
    return PartViews(np.asarray(frames), rot, u, centre, cam)


def reference_frames(positions: list[int], states: np.ndarray, known: np.ndarray, labelled: np.ndarray,
                     most: int = 8, near: int = 6) -> list[list[int]]:
    """Candidate references, best first: sets of frames (dataset positions among `positions`, the frames that show
    the part) where the part likely holds one state. The largest group of known frames with one state (within
    0.02), then each labelled frame (those at the ends of the labelled range first: parts rest at their ends) with
    its `near` nearest shown frames on each side: wide enough for a baseline; a pair of them across which the part
    moved triangulates no point (it breaks the known cameras' epipolar geometry), so a wrong guess costs points,
    not accuracy."""
    out = []
    groups: dict[int, list[int]] = {}
    for p in positions:
        if known[p]:
            groups.setdefault(int(round(states[p] / 0.02)), []).append(p)
    best = max(groups.values(), key=len) if groups else []
    if len(best) >= 3:
        out.append([best[i] for i in np.linspace(0, len(best) - 1, min(most, len(best))).round().astype(int)])
    lab = [p for p in positions if labelled[p]]
    if lab:
        lo, hi = float(states[lab].min()), float(states[lab].max())
        for p in sorted(lab, key=lambda q: min(abs(states[q] - lo), abs(states[q] - hi))):
            j = positions.index(p)
            out.append(positions[max(0, j - near): j + near + 1])
    return out
