"""Sub-pixel agreement of each track's keypoints before the final bundle adjustment.

SIFT places a keypoint in each image on its own, so the observations of one 3-D point disagree by a few tenths of
a pixel more than the images do (mean reprojection error 0.38 px on the simulator's sharp frames). Aligning each
observation's patch to the same patch in one reference view of the track (Lucas-Kanade, translation only) makes the
observations agree with each other, which is what bundle adjustment needs: the idea of pixel-perfect SfM, with
image patches instead of learned features. A small window keeps the translation-only model valid between views of
different angle (on the simulator: 7 px beat 9, 11, 15 and 21). An observation whose alignment fails, moves
further than a keypoint's plausible error or leaves the patches unlike, keeps its SIFT position.

Measured (recipes/bench_poses.py, same features and matches): simulator, 300 frames at 640x480, rotation error
0.0562 -> 0.046 deg (rotation gauge), camera centres 0.037 -> 0.033 % of the path, in 10 s (0.5 s of it the
alignment itself: one call on tiled patches, not one per image pair); fox (50 real photos
around an object, wide baselines, 28 % of observations aligned) unchanged within its run-to-run spread. Limiting
the alignment to views within 3-8 deg of the reference lost the simulator's gain: what helps is that a whole track
agrees with one view, not that neighbouring views agree.

SIFT also misses most of the views a point is seen in: on the simulator a track has 22 views, and aligned patches
find its point in 44 more within 30 frames of its ends. `extend_tracks` projects every point into the views near
its track, aligns the patch there to the track's reference the same way, and adds what agrees as new
observations. Tracks triple, each camera is held by three times as many points, and the final BA's camera
centres err 40 % less (same model: 0.031 -> 0.017 % of the path, rotation 0.045 -> 0.025 deg in the
rotation-fitted gauge) for ~12 s of alignment and a longer BA.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pycolmap

from .errors import StageError

LK_WINDOW = 7  # px, on the images' own resolution
LK_MAX_SHIFT = 1.5  # px: further than this is a different texture, not a better estimate of the same point
LK_MAX_RESIDUAL = 8.0  # mean absolute grey-level difference left after alignment: above it the patches differ
# (lighting, occlusion, a large change of view) and the translation is not to be trusted
HALF = 7  # block half-size: window radius + largest shift + the gradient's support, with a margin
PATCH = 2 * HALF + 1
EDGE = LK_WINDOW // 2 + 3  # px from the image border a point needs for its alignment to read only real pixels
EXTEND_BATCH = 1_000_000  # candidates aligned at once by `extend_tracks` (~0.5 GB of image blocks)
TRACK_WINDOW = 30  # frames (name order) beyond a track's first and last view where `extend_tracks` looks for it
LK_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-3)


def _sorted_tracks(rec) -> tuple[list[int], dict[int, list[tuple[int, int, int]]]]:
    """Registered image ids in name order (the video's order for a sequential capture), and each 3-D point's
    observations as (position in that order, image id, point2D index), sorted by position."""
    ids = sorted(rec.reg_image_ids(), key=lambda i: rec.images[i].name)
    pos = {iid: k for k, iid in enumerate(ids)}
    tracks = {int(pid): sorted((pos.get(e.image_id, -1), e.image_id, e.point2D_idx) for e in p.track.elements)
              for pid, p in rec.points3D.items()}
    return ids, tracks


def _observations(rec) -> np.ndarray:
    """Every observation that is not its track's reference, with that reference: (N, 4) int rows of
    (reference image id, its point2D index, image id, point2D index).

    The reference is the track's middle view in name order (the middle of the video for a sequential capture), so
    the furthest view is half a track away."""
    rows: list[tuple[int, int, int, int]] = []
    for els in _sorted_tracks(rec)[1].values():
        if len(els) < 2:
            continue
        _, ref, ref_idx = els[len(els) // 2]
        rows.extend((ref, ref_idx, iid, idx) for _, iid, idx in els if iid != ref)
    return np.asarray(rows, dtype=np.int64).reshape(-1, 4)


def _rows_by_image(ids: np.ndarray) -> dict[int, np.ndarray]:
    """Row positions of each image id in ids (N,), one sort instead of a scan per image."""
    order = np.argsort(ids, kind="stable")
    keys, starts = np.unique(ids[order], return_index=True)
    return dict(zip(keys.tolist(), np.split(order, starts[1:])))


def _patches(img: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PATCH x PATCH pixel blocks of img around uv (N, 2; OpenCV pixel centres), edge pixels repeated where a block
    overhangs: (patches (N, P, P), origin (N, 2) int, inside (N,) = what the alignment reads lies in the image)."""
    h, w = img.shape
    o = np.rint(uv).astype(np.int64) - HALF
    r = EDGE - HALF  # the window, its largest shift and the gradient's support stay in the image
    inside = (o[:, 0] >= r) & (o[:, 1] >= r) & (o[:, 0] + PATCH + r <= w) & (o[:, 1] + PATCH + r <= h)
    k = np.arange(PATCH)
    ys = np.clip(o[:, 1, None] + k, 0, h - 1)
    xs = np.clip(o[:, 0, None] + k, 0, w - 1)
    return img[ys[:, :, None], xs[:, None, :]], o, inside


def _mosaic(patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tile (N, P, P) patches into one image: (mosaic, top-left corner (N, 2) of each tile as x, y)."""
    n = len(patches)
    cols = max(1, int(np.ceil(np.sqrt(n))))
    rows = -(-n // cols)
    tiles = np.zeros((rows * cols, PATCH, PATCH), patches.dtype)
    tiles[:n] = patches
    mosaic = tiles.reshape(rows, cols, PATCH, PATCH).transpose(0, 2, 1, 3).reshape(rows * PATCH, cols * PATCH)
    idx = np.arange(n)
    return np.ascontiguousarray(mosaic), np.stack([idx % cols, idx // cols], 1) * PATCH


def align_patches(ref: np.ndarray, tgt: np.ndarray, ref_uv: np.ndarray, tgt_uv: np.ndarray,
                  window: int = LK_WINDOW) -> tuple[np.ndarray, np.ndarray]:
    """Lucas-Kanade of many points at once: ref / tgt (N, P, P) blocks, ref_uv / tgt_uv (N, 2) the points within
    them. One call on two tiled images instead of one per image pair (whose cost is the whole-image gradients).
    Returns (aligned tgt_uv (N, 2), status (N,), mean absolute grey-level residual (N,))."""
    m_ref, corner = _mosaic(ref)
    m_tgt, _ = _mosaic(tgt)
    p0 = (corner + ref_uv).astype(np.float32).reshape(-1, 1, 2)
    p1 = (corner + tgt_uv).astype(np.float32).reshape(-1, 1, 2)
    out, status, err = cv2.calcOpticalFlowPyrLK(m_ref, m_tgt, p0, p1, winSize=(window, window), maxLevel=0,
                                                criteria=LK_CRITERIA, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    return out.reshape(-1, 2).astype(np.float64) - corner, status.ravel().astype(bool), err.ravel()


def align_points(ref_img: np.ndarray, img: np.ndarray, ref_xy: np.ndarray, xy: np.ndarray,
                 window: int = LK_WINDOW) -> tuple[np.ndarray, np.ndarray]:
    """Move xy (N, 2) in img onto the patches around ref_xy in ref_img (grey uint8; COLMAP pixel convention, centre
    of the first pixel at 0.5). Returns (aligned xy (N, 2), status (N,)); the batch form is `refine_tracks`."""
    rb, ro, rin = _patches(ref_img, ref_xy - 0.5)
    tb, to, tin = _patches(img, xy - 0.5)
    uv, st, _ = align_patches(rb, tb, ref_xy - 0.5 - ro, xy - 0.5 - to, window)
    return uv + to + 0.5, st & rin & tin


def _align_rows(names: dict[int, str], image_dir: Path, ref_id: np.ndarray, ref_xy: np.ndarray, tgt_id: np.ndarray,
                tgt_xy: np.ndarray, *, window: int, max_shift: float, max_residual: float, chunk: int,
                bar: Any = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Align the points tgt_xy (N, 2) of images tgt_id (N,) onto the patches around ref_xy in images ref_id (COLMAP
    pixel convention), reading each image once and cutting its blocks for every row it serves.
    Returns (aligned xy (N, 2), accepted (N,), shift (N,) px)."""
    n = len(ref_id)
    ref_blk = np.empty((n, PATCH, PATCH), np.uint8)
    tgt_blk = np.empty((n, PATCH, PATCH), np.uint8)
    ref_o = np.empty((n, 2), np.int64)
    tgt_o = np.empty((n, 2), np.int64)
    inside = np.ones(n, bool)
    none = np.zeros(0, np.int64)
    as_ref, as_tgt = _rows_by_image(ref_id), _rows_by_image(tgt_id)
    for iid in sorted(set(as_ref) | set(as_tgt)):
        img = cv2.imread(str(image_dir / names[iid]), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise StageError(f"{image_dir / names[iid]} is not readable: re-run `interreal frames`")
        for rows, xy, blk, org in ((as_ref.get(iid, none), ref_xy, ref_blk, ref_o),
                                   (as_tgt.get(iid, none), tgt_xy, tgt_blk, tgt_o)):
            if rows.size:
                blk[rows], org[rows], ok = _patches(img, xy[rows] - 0.5)
                inside[rows] &= ok
        if bar is not None:
            bar.update(1)
    new = tgt_xy.astype(np.float64).copy()
    ok = inside.copy()
    resid = np.zeros(n)
    for a in range(0, n, chunk):  # COLMAP pixel centres are at +0.5, OpenCV's at 0
        s = slice(a, a + chunk)
        uv, st, res = align_patches(ref_blk[s], tgt_blk[s], ref_xy[s] - 0.5 - ref_o[s], tgt_xy[s] - 0.5 - tgt_o[s],
                                    window)
        new[s] = uv + tgt_o[s] + 0.5
        resid[s] = np.nan_to_num(res, nan=np.inf)
        ok[s] &= st
    shift = np.linalg.norm(new - tgt_xy, axis=1)
    ok &= np.isfinite(new).all(1) & (shift <= max_shift) & (resid <= max_residual)
    return new, ok, shift


def refine_tracks(rec, image_dir: Path, *, window: int = LK_WINDOW, max_shift: float = LK_MAX_SHIFT,
                  max_residual: float = LK_MAX_RESIDUAL, chunk: int = 200_000, bar: Any = None) -> dict[str, Any]:
    """Align every track's observations to its reference view, in place (rec's 2-D points move; run a bundle
    adjustment after). bar: a progress bar (tqdm-like) advanced once per image read. Returns counts and the median
    shift for the report."""
    t0 = time.perf_counter()
    obs = _observations(rec)  # (n, 4): ref image, ref point2D idx, image, point2D idx
    n = len(obs)
    if n == 0:
        return {"observations": 0, "refined": 0, "refined_frac": 0.0, "median_shift_px": 0.0, "wall_s": 0.0}
    images = {iid: rec.images[iid] for iid in np.unique(obs[:, [0, 2]]).tolist()}
    ref_xy = np.array([images[int(i)].points2D[int(k)].xy for i, k in obs[:, :2]])
    xy = np.array([images[int(i)].points2D[int(k)].xy for i, k in obs[:, 2:]])
    new, ok, shift = _align_rows({i: im.name for i, im in images.items()}, image_dir, obs[:, 0], ref_xy, obs[:, 2],
                                 xy, window=window, max_shift=max_shift, max_residual=max_residual, chunk=chunk,
                                 bar=bar)
    for k in np.nonzero(ok)[0]:
        images[int(obs[k, 2])].points2D[int(obs[k, 3])].xy = new[k]
    return {"observations": n, "refined": int(ok.sum()), "refined_frac": round(float(ok.mean()), 4),
            "median_shift_px": round(float(np.median(shift[ok])), 4) if ok.any() else 0.0,
            "wall_s": round(time.perf_counter() - t0, 2)}


def _unmasked(mask_dir: Path | None, name: str, uv: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(N,) True where the COLMAP mask of image `name` (<name>.png, 0 = object pixels SfM must not use) allows uv
    (N, 2; COLMAP pixels of an image of size (w, h)); all True without a mask."""
    if mask_dir is None:
        return np.ones(len(uv), bool)
    mask = cv2.imread(str(mask_dir / f"{name}.png"), cv2.IMREAD_GRAYSCALE)
    if mask is None:
        return np.ones(len(uv), bool)
    sx, sy = mask.shape[1] / size[0], mask.shape[0] / size[1]
    u = np.clip((uv[:, 0] * sx).astype(np.int64), 0, mask.shape[1] - 1)
    v = np.clip((uv[:, 1] * sy).astype(np.int64), 0, mask.shape[0] - 1)
    return mask[v, u] > 0


def extend_tracks(rec, image_dir: Path, mask_dir: Path | None = None, *, window: int = TRACK_WINDOW,
                  max_shift: float = LK_MAX_SHIFT, max_residual: float = LK_MAX_RESIDUAL, chunk: int = 200_000,
                  batch: int = EXTEND_BATCH, bar: Any = None) -> dict[str, Any]:
    """Add each 3-D point to the registered views where it projects but SIFT did not find or match it, in place.

    Candidates: views within `window` frames (name order) of the track's first and last view, where the point
    lies in front of the camera, inside the image and off the object masks. Each candidate's patch is aligned to
    the track's reference view (Lucas-Kanade from the projection); it becomes an observation when the alignment
    converges within max_shift of the projection, off the masks, and the patches agree (an occluded or unlike view
    fails that).
    Candidates are aligned in batches of consecutive views of up to `batch` candidates (each holds two image
    blocks, ~0.5 KB), so memory stays bounded on long captures; a view's candidates are never split.
    Run a bundle adjustment after. bar: advanced once per view. Returns counts for the report."""
    t0 = time.perf_counter()
    ids, tracks = _sorted_tracks(rec)
    tracks = {pid: els for pid, els in tracks.items() if els and els[0][0] >= 0}

    def report(candidates: int, added: int, before: int) -> dict[str, Any]:
        n = max(1, len(tracks))
        return {"candidates": candidates, "added": added, "added_frac": round(added / max(1, candidates), 4),
                "observations_before": before, "track_length_before": round(before / n, 2),
                "track_length_after": round((before + added) / n, 2), "wall_s": round(time.perf_counter() - t0, 2)}

    if not tracks or not ids:
        return report(0, 0, 0)
    pids = np.fromiter(tracks, np.int64, len(tracks))
    lo = np.array([els[0][0] for els in tracks.values()])
    hi = np.array([els[-1][0] for els in tracks.values()])
    ref = np.array([els[len(els) // 2][1:] for els in tracks.values()], np.int64)  # (P, 2): image id, point2D idx
    xyz = np.stack([rec.points3D[int(p)].xyz for p in pids])
    seen: dict[int, list[int]] = {iid: [] for iid in ids}
    for k, els in enumerate(tracks.values()):
        for _, iid, _ in els:
            seen[iid].append(k)
    n_before = sum(len(v) for v in seen.values())
    images = {iid: rec.images[iid] for iid in ids}
    cand_k, cand_img, cand_xy = [], [], []  # per view in `ids` order (empty where none)
    for j, iid in enumerate(ids):
        im = images[iid]
        cam = rec.cameras[im.camera_id]
        sel = np.nonzero((lo - window <= j) & (j <= hi + window))[0]
        sel = sel[~np.isin(sel, seen[iid])]
        pose = im.cam_from_world().matrix()
        xc = xyz[sel] @ pose[:, :3].T + pose[:, 3]
        front = xc[:, 2] > 1e-9
        sel, xc = sel[front], xc[front]
        uv = np.asarray(cam.img_from_cam(xc), np.float64).reshape(-1, 2) if sel.size else np.zeros((0, 2))
        ok = np.isfinite(uv).all(1) & (uv[:, 0] >= EDGE) & (uv[:, 1] >= EDGE) \
            & (uv[:, 0] <= cam.width - EDGE) & (uv[:, 1] <= cam.height - EDGE)
        if ok.any():
            ok[ok] &= _unmasked(mask_dir, im.name, uv[ok], (cam.width, cam.height))
        cand_k.append(sel[ok])
        cand_img.append(np.full(int(ok.sum()), iid, np.int64))
        cand_xy.append(uv[ok])
    if not sum(len(c) for c in cand_k):
        return report(0, 0, n_before)
    names = {iid: im.name for iid, im in images.items()}
    track_ref_xy = np.array([images[int(i)].points2D[int(x)].xy for i, x in ref])  # once per track, not per candidate
    n_cand = added = 0
    start = 0
    while start < len(ids):  # consecutive views up to `batch` candidates (at least one view)
        stop, rows = start + 1, len(cand_k[start])
        while stop < len(ids) and rows + len(cand_k[stop]) <= batch:
            rows += len(cand_k[stop])
            stop += 1
        k_all = np.concatenate(cand_k[start:stop])
        tgt_id, xy = np.concatenate(cand_img[start:stop]), np.concatenate(cand_xy[start:stop])
        if len(k_all):
            new, ok, _ = _align_rows(names, image_dir, ref[k_all, 0], track_ref_xy[k_all], tgt_id, xy,
                                     window=LK_WINDOW, max_shift=max_shift, max_residual=max_residual, chunk=chunk)
            for iid in np.unique(tgt_id[ok]):  # the alignment may move a projection onto an object: drop it there
                rows_i = np.nonzero(ok & (tgt_id == iid))[0]
                cam = rec.cameras[images[int(iid)].camera_id]
                ok[rows_i] = _unmasked(mask_dir, names[int(iid)], new[rows_i], (cam.width, cam.height))
            for c in np.nonzero(ok)[0]:
                pts = images[int(tgt_id[c])].points2D
                pts.append(pycolmap.Point2D(new[c]))
                rec.add_observation(int(pids[k_all[c]]), pycolmap.TrackElement(int(tgt_id[c]), len(pts) - 1))
            n_cand, added = n_cand + len(k_all), added + int(ok.sum())
        if bar is not None:
            bar.update(stop - start)
        start = stop
    return report(n_cand, added, n_before)
