"""Vectorised CPU ray caster for scenes made of oriented boxes (and ellipsoids inscribed in some of them).

Why boxes: a room, its furniture, doors, drawers, lids and a blocky person are all boxes, and the ray/box slab test
is exact, cheap and vectorises in numpy. A hand is not: a hand detector finds a palm and fingers only where they are
round (`rounded` boxes are drawn as the ellipsoid inscribed in them, shaded by its own normal).
The lens distortion is handled exactly: every pixel centre is undistorted once per intrinsics (`cv2.undistortPoints`,
iterated to 1e-12), so the ray through pixel (u, v) is the ray that the OpenCV model projects back onto
(u + 0.5, v + 0.5). Pixel centres sit at +0.5, as in nerfstudio and COLMAP, so
`Intrinsics.scaled` stays exact.

Rays are written d = R_cam @ (x_n, y_n, 1): the ray parameter t is the z-depth along the optical axis.
Each box is only tested against the pixels inside its projected bounding rectangle.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..dataset import Intrinsics

NEAR = 0.02  # metres: boxes closer than this to the camera plane are not drawn
OCCLUDER = 255


@dataclass
class Prims:
    """Boxes in world coordinates (struct of arrays). Box 0 is the room, seen from inside.

    Face f = 2 * axis + (1 if on the + side else 0); tile/scale/offset describe the texture of each face:
    texel = (local metres / scale + offset) * tile size, mirrored-repeat.
    """

    R: np.ndarray  # (P, 3, 3) local -> world rotation (columns = local axes in world)
    c: np.ndarray  # (P, 3) centre
    h: np.ndarray  # (P, 3) half extents
    inst: np.ndarray  # (P,) uint8 instance index (0 static, k object k-1, 255 occluder)
    tile: np.ndarray  # (P, 6) int atlas tile per face
    scale: np.ndarray  # (P, 6) metres per tile
    offset: np.ndarray  # (P, 6, 2) tile-unit offset
    inverted: np.ndarray  # (P,) bool: seen from inside (the room)
    rounded: np.ndarray | None = None  # (P,) bool: the ellipsoid inscribed in the box (None: no box is)

    def __post_init__(self) -> None:
        if self.rounded is None:
            self.rounded = np.zeros(len(self.c), bool)

    def __len__(self) -> int:
        return len(self.c)


@dataclass
class Lighting:
    """Lambertian: ambient + a directional light + a ceiling point light with soft falloff (no shadows)."""

    ambient: float = 0.42
    sun_dir: tuple[float, float, float] = (0.35, -0.55, 0.76)  # towards the light, world (z up)
    sun: float = 0.38
    point: tuple[float, float, float] = (0.0, 0.5, 2.6)
    point_gain: float = 0.45
    point_range: float = 3.5


class RayCaster:
    """Casts the rays of one Intrinsics; reuse it for every frame with that camera."""

    def __init__(self, intr: Intrinsics, offsets: tuple[float, float] = (0.5, 0.5)):
        self.intr = intr
        w, h = intr.w, intr.h
        u, v = np.meshgrid(np.arange(w, dtype=np.float64) + offsets[0], np.arange(h, dtype=np.float64) + offsets[1])
        pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
        if intr.has_distortion():
            crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 60, 1e-12)
            n = cv2.undistortPoints(pts, intr.K(), intr.dist(), None, None, criteria=crit).reshape(h, w, 2)
        else:
            n = np.stack([(u - intr.cx) / intr.fl_x, (v - intr.cy) / intr.fl_y], axis=-1)
        self.xn = np.ascontiguousarray(n[..., 0], dtype=np.float32)
        self.yn = np.ascontiguousarray(n[..., 1], dtype=np.float32)
        # monotone per-column / per-row bounds for the screen-rectangle culling
        self.col_min = np.minimum.accumulate(self.xn.min(0)[::-1])[::-1]
        self.col_max = np.maximum.accumulate(self.xn.max(0))
        self.row_min = np.minimum.accumulate(self.yn.min(1)[::-1])[::-1]
        self.row_max = np.maximum.accumulate(self.yn.max(1))

    # ------------------------------------------------------------------------------------------------------------
    def _rect(self, corners_cam: np.ndarray) -> tuple[int, int, int, int] | None:
        """Pixel rectangle (r0, r1, c0, c1) that may see a convex body with these camera-frame corners."""
        z = corners_cam[:, 2]
        if np.all(z <= NEAR):
            return None
        h, w = self.xn.shape
        if np.any(z <= NEAR):
            return 0, h, 0, w
        x = corners_cam[:, 0] / z
        y = corners_cam[:, 1] / z
        c0 = int(np.searchsorted(self.col_max, x.min(), "left"))
        c1 = int(np.searchsorted(self.col_min, x.max(), "right"))
        r0 = int(np.searchsorted(self.row_max, y.min(), "left"))
        r1 = int(np.searchsorted(self.row_min, y.max(), "right"))
        if c0 >= c1 or r0 >= r1:
            return None
        return r0, r1, c0, c1

    def cast(self, c2w_cv: np.ndarray, prims: Prims) -> tuple[np.ndarray, np.ndarray]:
        """(t, pid): z-depth (H, W) float32 and the hit box (H, W) int16."""
        Rc = np.asarray(c2w_cv[:3, :3], np.float64)
        o = np.asarray(c2w_cv[:3, 3], np.float64)
        h, w = self.xn.shape
        zbuf = np.empty((h, w), np.float32)
        pid = np.zeros((h, w), np.int16)
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for b in range(len(prims)):
                if b == 0:
                    rect = (0, h, 0, w)
                else:
                    corners = prims.c[b] + (signs * prims.h[b]) @ prims.R[b].T
                    rect = self._rect((corners - o) @ Rc)
                    if rect is None:
                        continue
                r0, r1, c0, c1 = rect
                X, Y = self.xn[r0:r1, c0:c1], self.yn[r0:r1, c0:c1]
                M = (prims.R[b].T @ Rc).astype(np.float32)
                ol = (prims.R[b].T @ (o - prims.c[b])).astype(np.float32)
                hb = prims.h[b].astype(np.float32)
                if b == 0:  # the room, seen from inside: every ray leaves it
                    zbuf[:] = _slab_hits(M, ol, hb, X, Y, exit_only=True)[1]
                    continue
                tnear, tfar = (_ellipsoid_hits if prims.rounded[b] else _slab_hits)(M, ol, hb, X, Y)
                zs = zbuf[r0:r1, c0:c1]
                hit = (tnear <= tfar) & (tnear > NEAR) & (tnear < zs)
                np.copyto(zs, tnear, where=hit)
                pid[r0:r1, c0:c1][hit] = b
        return zbuf, pid

    # ------------------------------------------------------------------------------------------------------------
    def shade(self, c2w_cv: np.ndarray, prims: Prims, t: np.ndarray, pid: np.ndarray, atlas_image: np.ndarray,
              tile_y0: np.ndarray, tile_size: np.ndarray, light: Lighting) -> np.ndarray:
        """Linear RGB float32 (H, W, 3): texture albedo times Lambertian shading.

        Fully vectorised over the image: per-box quantities are small tables gathered by the hit-box index.
        """
        Rc = np.asarray(c2w_cv[:3, :3], np.float64)
        o = np.asarray(c2w_cv[:3, 3], np.float64)
        h, w = t.shape
        n_p = len(prims)
        # per box: local ray direction matrix M = R_b^T R_cam, local origin, 1 / half extents: one packed table,
        # gathered by the hit-box index in a single take (rows come out contiguous)
        M = np.einsum("pji,jk->pik", prims.R, Rc).reshape(n_p, 9)
        ol = np.einsum("pji,pj->pi", prims.R, o[None] - prims.c)
        box_tab = np.concatenate([M, ol, 1.0 / prims.h], axis=1).T.astype(np.float32)  # (15, P)
        g = np.take(box_tab, pid.astype(np.intp), axis=1)  # (15, H, W)
        X, Y = self.xn, self.yn
        L = [g[9 + k] + t * (g[3 * k] * X + g[3 * k + 1] * Y + g[3 * k + 2]) for k in range(3)]
        q = [np.abs(L[k]) * g[12 + k] for k in range(3)]
        del g
        a0 = (q[0] >= q[1]) & (q[0] >= q[2])
        a2 = ~a0 & (q[2] > q[1])
        u = np.where(a0, L[1], L[0])
        v = np.where(a2, L[1], L[2])
        l_axis = np.where(a0, L[0], np.where(a2, L[2], L[1]))
        axis = a2.astype(np.intp) * 2 + (~a0 & ~a2)
        face = pid.astype(np.intp) * 6 + axis * 2 + (l_axis > 0)
        # per (box, face) tables: texture tile, scale, offset; Lambertian terms of the face normal
        tiles = prims.tile.reshape(-1)
        normals = np.empty((n_p, 6, 3))
        for f in range(6):
            normals[:, f] = prims.R[:, :, f // 2] * (1.0 if f % 2 else -1.0)
        normals[prims.inverted] *= -1.0
        normals = normals.reshape(-1, 3)
        sun = np.asarray(light.sun_dir, np.float64)
        sun = sun / np.linalg.norm(sun)
        lp = np.asarray(light.point, np.float64)
        # n . (lp - P) with P = o + t * R_cam d_cam  ->  (n . lp - n . o) - t * (n R_cam) . d_cam
        n_rc = normals @ Rc
        face_tab = np.stack([
            tile_size[tiles], 1.0 / prims.scale.reshape(-1), prims.offset.reshape(-1, 2)[:, 0],
            prims.offset.reshape(-1, 2)[:, 1], tile_y0[tiles],
            light.ambient + light.sun * np.clip(normals @ sun, 0, None),
            normals @ lp - normals @ o, n_rc[:, 0], n_rc[:, 1], n_rc[:, 2],
        ]).astype(np.float32)  # (10, P * 6)
        f = np.take(face_tab, face, axis=1)  # (10, H, W)
        s_face = f[0]
        tx = _mirror((u * f[1] + f[2]) * s_face, s_face)
        mapy = f[4] + _mirror((-v * f[1] + f[3]) * s_face, s_face)
        n_dot_l = f[6] - t * (f[7] * X + f[8] * Y + f[9])
        D = [np.float32(Rc[j, 0]) * X + np.float32(Rc[j, 1]) * Y + np.float32(Rc[j, 2]) for j in range(3)]
        d2 = sum((np.float32(lp[j] - o[j]) - t * D[j]) ** 2 for j in range(3))
        point = np.maximum(n_dot_l, 0) / np.maximum(np.sqrt(d2), 1e-6) / (1.0 + d2 * np.float32(1.0 / light.point_range ** 2))
        gain = f[5] + np.float32(light.point_gain) * point
        if prims.rounded.any():
            _round_gain(gain, prims, pid, L, light, o, D, t)
        albedo = cv2.remap(atlas_image, tx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return albedo * gain[..., None]


def _slab_hits(M: np.ndarray, ol: np.ndarray, hb: np.ndarray, X: np.ndarray, Y: np.ndarray,
               exit_only: bool = False) -> tuple[np.ndarray | None, np.ndarray]:
    """(tnear, tfar) of the rays (X, Y, 1) with a box (its local ray matrix M, local origin ol, half extents hb) by
    the slab test; tnear > tfar where a ray misses. `exit_only`: tfar alone (tnear None), for the room."""
    tnear = tfar = None
    for k in range(3):
        inv = 1.0 / (M[k, 0] * X + M[k, 1] * Y + M[k, 2])
        ta = (-hb[k] - ol[k]) * inv
        tb = (hb[k] - ol[k]) * inv
        hi = np.maximum(ta, tb)
        tfar = hi if tfar is None else np.minimum(tfar, hi, out=tfar)
        if not exit_only:
            lo = np.minimum(ta, tb, out=ta)
            tnear = lo if tnear is None else np.maximum(tnear, lo, out=tnear)
    return tnear, tfar


def _ellipsoid_hits(M: np.ndarray, ol: np.ndarray, hb: np.ndarray, X: np.ndarray,
                    Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(tnear, tfar) of the rays (X, Y, 1) with the ellipsoid inscribed in a box (its local ray matrix M, local
    origin ol, half extents hb); tnear > tfar where a ray misses."""
    d = [(M[k, 0] * X + M[k, 1] * Y + M[k, 2]) / hb[k] for k in range(3)]
    o = ol / hb
    a = d[0] ** 2 + d[1] ** 2 + d[2] ** 2
    b = o[0] * d[0] + o[1] * d[1] + o[2] * d[2]
    disc = b * b - a * (float(o @ o) - 1.0)
    root = np.sqrt(np.maximum(disc, 0))
    miss = disc < 0
    tnear = np.where(miss, np.float32(np.inf), (-b - root) / a)
    tfar = np.where(miss, np.float32(-np.inf), (-b + root) / a)
    return tnear, tfar


def _round_gain(gain: np.ndarray, prims: Prims, pid: np.ndarray, L: list[np.ndarray], light: Lighting,
                o: np.ndarray, D: list[np.ndarray], t: np.ndarray) -> None:
    """Lambertian shading of the pixels on rounded boxes by the ellipsoid's normal at each hit (in place): a box
    face's single normal would draw it flat."""
    sel = prims.rounded[pid]
    if not sel.any():
        return
    p = pid[sel].astype(np.intp)
    n_loc = np.stack([L[k][sel] / prims.h[p, k] ** 2 for k in range(3)], axis=1)
    n = np.einsum("pij,pj->pi", prims.R[p], n_loc)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    sun = np.asarray(light.sun_dir, np.float64)
    sun = sun / np.linalg.norm(sun)
    hit = o[None] + t[sel][:, None] * np.stack([D[j][sel] for j in range(3)], axis=1)
    to_light = np.asarray(light.point, np.float64)[None] - hit
    d2 = np.sum(to_light ** 2, axis=1)
    point = np.maximum(np.sum(n * to_light, axis=1), 0) / np.maximum(np.sqrt(d2), 1e-6) / (
        1.0 + d2 / light.point_range ** 2)
    gain[sel] = light.ambient + light.sun * np.clip(n @ sun, 0, None) + light.point_gain * point


def _mirror(x: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Mirrored repeat of texel coordinate x into [0, size - 1] (continuous: no seams)."""
    period = 2.0 * size
    m = np.abs(x - period * np.floor(x / period + 0.5))  # distance to the nearest even multiple of size: [0, size]
    return np.clip(m - 0.5, 0.0, size - 1.0, out=m)
