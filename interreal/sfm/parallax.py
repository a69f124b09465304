"""Is there parallax at all? A check of seconds, run on the SIFT features (object pixels already masked out)
before any matching for mapping, so that a camera that only turned in place or stood still is refused with that
cause instead of a generic "registered only 16/89 frames" after minutes of retries.

Why a homography: when the camera only rotates (or stays put), every match obeys x2 = K R K^-1 x1 whatever the
depth, so one homography explains all of them, to the keypoint noise and the lens distortion it leaves out (a
fraction of a pixel to a few pixels), and that homography is conjugate to a rotation. When the camera moves,
neither holds: points at different depths shift by different amounts, and a plane's homography R + t n^T / d is no
rotation. So, per well-separated frame pair, from the matches that pass Lowe's ratio test and a robust
fundamental-matrix fit:
- the dominant homography (robust fit, then least squares on its inliers), and the median transfer residual
  |x2 - H x1| of all consistent matches as an angle (atan(residual / f)): depth differences seen from the baseline,
  |t| (1/d1 - 1/d2), in a 3-D scene;
- that homography's deviation from a rotation, (s1 - s3) / s2 of the singular values of K^-1 H K, which is |t| / d
  for a plane at distance d: the baseline seen from the plane, when most matches lie on one (a floor, a wall).
The pair's parallax is the larger of the two; the capture's is its LARGEST pair, since one good pair is enough for
the mapper to start, and it is refused when that is under the angle at which COLMAP's mapper keeps a 3-D point at
all (`triangulation.min_angle`, 1.5 deg): with less, nothing triangulates. Both parts are lower bounds of the
triangulation angle |t| / d the mapper would see.

Focal lengths: the given K (`--intrinsics`) when there is one. Else the residual's angle uses COLMAP's own prior
(1.2 x the long side, where the mapper starts; a phone's f is ~0.75-0.9 x, so it reads angles up to ~1.5x low),
and the rotation test the ONE focal length under which the pairs' homographies are most like rotations
(`fit_focal`): a phone that only turned is recognised whatever its lens (the fit recovers its f to a few %).

Measured (largest pair): turned in place 0.27-0.32 deg (the simulated room, 16 and 24 frames; a real photo warped
by K R K^-1), held still 0.04 deg; the simulator's arc 26-52 deg, the shared phone capture (fox) 43 deg, the
laptop video 45 deg. So the 1.5 deg line sits 5x above the one and 17x below the other.
A capture with too few matches to judge (textureless, unrelated images) is not refused here: the mapper's own
failure explains it better.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

MIN_ANGLE_DEG = 1.5  # COLMAP's triangulation.min_angle / mapper.filter_min_tri_angle: points under it are dropped
PRIOR_FOCAL = 1.2  # x the long side: COLMAP's ImageReaderOptions.default_focal_length_factor (the mapper's start)
FOCAL_RANGE = (0.35, 1.5)  # x the long side, when f is unknown: 37-110 deg across, phones' main and ultra-wide lenses
MIN_INLIERS = 30  # COLMAP's mapper.abs_pose_min_num_inliers: fewer consistent matches do not place a frame
RATIO = 0.8  # Lowe's ratio test, as COLMAP's matcher (max_ratio 0.8)
MAX_ANCHORS = 6  # frames each paired with partners at growing gaps: <= 24 pairs, a second or two of matching
GAP_FRACTIONS = (1 / 16, 1 / 8, 1 / 4, 1 / 2)  # partner gaps as fractions of the capture: short gaps still match
# on a fast pan, long ones carry the baseline of a walk around the object


@dataclass
class PairParallax:
    """One frame pair: positions in name order, consistent matches, median homography residual (px, deg)."""

    a: int
    b: int
    inliers: int
    residual_px: float
    residual_deg: float  # the residual as an angle: depth differences seen from a baseline (3-D scenes)
    plane_deg: float  # the homography's deviation from a rotation: the baseline seen from the plane it fits

    @property
    def parallax_deg(self) -> float:
        """The pair's parallax: the larger of the two (a scene is either 3-D, or its matches lie on one plane)."""
        return max(self.residual_deg, self.plane_deg)


@dataclass
class ParallaxResult:
    """What the check measured: the pairs judged, the focal length used, the capture's parallax (largest pair)."""

    pairs: list[PairParallax] = field(default_factory=list)
    tried: int = 0
    focal_px: float = 0.0
    focal_source: str = "prior"
    rotation_focal_px: float = 0.0  # f unknown: the focal length under which the pairs look most like rotations
    wall_s: float = 0.0

    @property
    def parallax_deg(self) -> float | None:
        """The largest per-pair parallax (None when no pair had enough matches to judge)."""
        return max((p.parallax_deg for p in self.pairs), default=None)

    @property
    def median_deg(self) -> float | None:
        return float(np.median([p.parallax_deg for p in self.pairs])) if self.pairs else None

    def low(self, min_deg: float = MIN_ANGLE_DEG) -> bool:
        """Whether every judged pair is under `min_deg` (False when nothing could be judged)."""
        best = self.parallax_deg
        return best is not None and best < min_deg

    def figures(self) -> dict[str, Any]:
        """For the stage report."""
        best = max(self.pairs, key=lambda p: p.parallax_deg, default=None)
        return {"parallax_deg_max": None if best is None else round(best.parallax_deg, 3),
                "parallax_deg_median": None if self.median_deg is None else round(self.median_deg, 3),
                "best_pair": None if best is None else [best.a, best.b],
                "pairs_judged": len(self.pairs), "pairs_tried": self.tried,
                "focal_px": round(self.focal_px, 1), "focal_source": self.focal_source,
                "rotation_focal_px": round(self.rotation_focal_px, 1),
                "min_deg": MIN_ANGLE_DEG, "wall_s": round(self.wall_s, 3)}

    def finding(self, names: list[str]) -> str:
        """What was measured, against what is needed."""
        best = max(self.pairs, key=lambda p: p.parallax_deg)
        return (f"the largest parallax between {len(self.pairs)} well-separated frame pairs is "
                f"{best.parallax_deg:.2f} deg ({names[best.a]} / {names[best.b]}; median {self.median_deg:.2f} deg), "
                f"while poses need >= ~{MIN_ANGLE_DEG} deg (the smallest triangulation angle at which SfM keeps a "
                "point)")

    def message(self, names: list[str]) -> str:
        """The refusal: the cause, what was measured, what to do."""
        found = self.finding(names)
        return (f"the camera barely moved: it turned in place or stood still. {found[0].upper() + found[1:]}. "
                "Film again walking around the object (move the phone, do not only turn it), or pass "
                "--allow-low-parallax to try anyway")


def sample_pairs(n: int) -> list[tuple[int, int]]:
    """Well-separated pairs (positions in name order): up to MAX_ANCHORS evenly spread frames, each with the
    frames GAP_FRACTIONS of the capture later (at least one frame)."""
    gaps = sorted({max(1, round(n * f)) for f in GAP_FRACTIONS})
    anchors = sorted({int(round(x)) for x in np.linspace(0, n - 1, min(MAX_ANCHORS, n))})
    return sorted({(a, a + g) for a in anchors for g in gaps if a + g < n})


def rotation_deviation(H: np.ndarray, K: np.ndarray) -> float:
    """How far a homography is from a pure rotation, in radians: (s1 - s3) / s2 of the singular values of
    K^-1 H K. A rotation has three equal singular values; a plane at distance d seen from cameras a baseline t
    apart gives K^-1 H K = R + t n^T / d, whose s1 - s3 is |t| / d: the angle the baseline subtends at the plane."""
    s = np.linalg.svd(np.linalg.inv(K) @ H @ K, compute_uv=False)
    return float((s[0] - s[2]) / s[1])


def pinhole(f: float, size: tuple[int, int]) -> np.ndarray:
    """K of focal length f (px) with the principal point at the image centre."""
    w, h = size
    return np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])


def fit_focal(hs: list[np.ndarray], size: tuple[int, int]) -> float:
    """The ONE focal length (within FOCAL_RANGE) under which the pairs' homographies are closest to rotations (the
    median deviation): what a phone that only turned would have, so a rotation is recognised whatever its lens.
    One f for all pairs, not one per pair: a single pair of a sideways step plus a pan can pass for a rotation
    under some focal length (a 25 deg pan with a step of 1/10 of the distance reads 1.7 deg instead of 5.7 deg),
    pairs of different motions cannot all. A grid, then a golden-section search around its best point."""
    long_side = max(size)

    def cost(log_f: float) -> float:
        K = pinhole(long_side * 2.0 ** log_f, size)
        return float(np.median([rotation_deviation(H, K) for H in hs]))

    step, (f_lo, f_hi) = 1 / 8, np.log2(FOCAL_RANGE)
    grid = np.arange(f_lo, f_hi + step / 2, step)
    lo = float(grid[max(0, int(np.argmin([cost(x) for x in grid])) - 1)])
    hi = min(float(grid[-1]), lo + 2 * step)
    g = (math.sqrt(5) - 1) / 2
    for _ in range(30):  # the bracket shrinks to 2 step * 0.618^30, far below the grid's spacing
        a, b = hi - g * (hi - lo), lo + g * (hi - lo)
        lo, hi = (lo, b) if cost(a) < cost(b) else (a, hi)
    return long_side * 2.0 ** ((lo + hi) / 2)


def pair_parallax(k1: np.ndarray, d1: np.ndarray, k2: np.ndarray, d2: np.ndarray,
                  noise_px: float) -> tuple[int, float, np.ndarray | None] | None:
    """(consistent matches, median homography residual in px, that homography (None: no homography explains even
    a plane of them)) of one pair of SIFT keypoints (x, y first) and descriptors; None when fewer than MIN_INLIERS matches
    are consistent. `noise_px`: the keypoints' noise scale (the epipolar threshold is twice it)."""
    if len(k1) < MIN_INLIERS or len(k2) < MIN_INLIERS:
        return None
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1.astype(np.float32), d2.astype(np.float32), k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < RATIO * m[1].distance]
    if len(good) < MIN_INLIERS:
        return None
    p1 = np.float64([k1[m.queryIdx, :2] for m in good])
    p2 = np.float64([k2[m.trainIdx, :2] for m in good])
    _, inl = cv2.findFundamentalMat(p1, p2, cv2.USAC_MAGSAC, 2.0 * noise_px, 0.999, 10000)
    if inl is None or int(inl.sum()) < MIN_INLIERS:
        return None
    p1, p2 = p1[inl.ravel() > 0], p2[inl.ravel() > 0]
    # the dominant homography, robustly (a camera at rest makes F degenerate, so F's inliers may hold mismatches),
    # then refitted in least squares on its own inliers
    H, hin = cv2.findHomography(p1, p2, cv2.USAC_MAGSAC, 2.0 * noise_px, maxIters=10000, confidence=0.999)
    if H is None or int(hin.sum()) < MIN_INLIERS // 2:
        return len(p1), math.inf, None  # no homography explains even a plane of the matches: parallax
    on = hin.ravel() > 0
    H_ls, _ = cv2.findHomography(p1[on], p2[on], 0)
    H = H_ls if H_ls is not None else H
    proj = cv2.perspectiveTransform(p1.reshape(-1, 1, 2), H).reshape(-1, 2)
    return len(p1), float(np.median(np.linalg.norm(proj - p2, axis=1))), H / H[2, 2]


def measure(pc, db: Path, names: list[str], size: tuple[int, int], noise_px: float,
            K: np.ndarray | None = None) -> ParallaxResult:
    """The parallax of a capture from the SIFT features in `db` (its images named `names`, in capture order, of
    `size` (w, h)). `K`: known intrinsics (pixels of this size), else COLMAP's prior focal length is used."""
    t0 = time.perf_counter()
    focal = float(K[0, 0]) if K is not None else PRIOR_FOCAL * max(size)
    res = ParallaxResult(focal_px=focal, focal_source="given" if K is not None else "prior")
    pairs = sample_pairs(len(names))
    res.tried = len(pairs)
    feats: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    with pc.Database.open(str(db)) as d:
        ids = {im.name: im.image_id for im in d.read_all_images()}
        for pos in sorted({i for p in pairs for i in p}):
            iid = ids.get(names[pos])
            if iid is not None:
                feats[pos] = (np.asarray(d.read_keypoints(iid)), np.asarray(d.read_descriptors(iid).data))
    judged = []
    for a, b in pairs:
        if a in feats and b in feats:
            got = pair_parallax(*feats[a], *feats[b], noise_px)
            if got is not None:
                judged.append((a, b, *got))
    hs = [H for *_, H in judged if H is not None]
    if K is None and hs:
        res.rotation_focal_px = fit_focal(hs, size)
    Kr = K if K is not None else pinhole(res.rotation_focal_px, size)
    for a, b, n, resid, H in judged:
        dev = math.inf if H is None else rotation_deviation(H, Kr)
        res.pairs.append(PairParallax(a, b, n, round(min(resid, 1e9), 3),
                                      round(math.degrees(math.atan2(resid, focal)), 4),
                                      round(math.degrees(math.atan(dev)), 4)))
    res.wall_s = time.perf_counter() - t0
    return res
