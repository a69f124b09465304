"""A part's motion from its silhouettes against the known cameras: the route for parts too plain to reconstruct.

A grey cabinet door or a plain drawer front gives SfM and PnP nothing to match (9 of 200 frames registered on a
real door; seeds 4 and 6 of the simulator: no drawer motion at all), but its masks are good: colour separates it
from its surroundings. Its front is a flat quadrilateral, so:
1. the front's four corners are found in each frame whose known state is the reference state (lines fitted to
   the mask's outline, intersected) and triangulated with the known cameras (frames at other known states join
   as `corner + state x D` when the part slides; with too few, a run of frames where the front rests, at a state
   no label gives); `FACE_PX` and `MAX_TILT_DEG` refuse a front the views do not pin down;
2. each candidate motion (a slide along the front's normal; a hinge about each of its four edges) predicts the
   part's silhouette at any displacement: a slid drawer shows the prism between its front at rest and its front
   moved (the hull of the two), a turned door its turned front;
3. every frame's displacement is the one whose predicted silhouette overlaps the mask best (IoU), and the
   candidate with the best mean overlap is the motion: the geometry decides hinge or slide, the labels only
   orient it (`fit.articulate`).
`recipes/bench_motions.py` measures it alone and in the stage: on simulated drawers 0.4-1.8 deg and states within
0.023 where it answers, and it is the only route for seed 6's plain drawer; a door's edge and inside spoil its
silhouettes (its states 0.14-0.37 off), so the gates and the labels refuse most doors, and the sfm route stays first.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, NamedTuple

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..conventions import opengl_to_opencv
from ..dataset import Articulation
from ..transients import has_transients, read_transient
from .fit import Fit, articulate

FACE_PX = 2.0          # the front's corners must reproject within this (median, full-size pixels) ...
MAX_TILT_DEG = 3.0     # ... and its normal turn less than this when its corners move by their scatter (median
MIN_NOISE_PX = 0.25    # reprojection, at least this: a mask's pixel grid)
MIN_QUADS = 6          # frames whose mask gave four corners, at least
REST_RUN = 8           # ... or this many in a row (within 1.5x as many frames) where the front rests
QUAD_IOU = 0.95        # ... a quadrilateral that covers the mask this well (else the mask is some other shape)
# the chosen motion's silhouettes must overlap the masks this well on average: on seven simulated captures the
# drawers measured right overlapped 0.86-0.90; a door at 0.75 (its edge and inside in view) was 0.28 off in state
MIN_IOU = 0.8
# a frame whose best silhouette overlaps its mask less than this is not measured (the door turned edge-on, its inside
# in view: no displacement of the flat front explains the mask, and the best one is a guess)
MIN_FRAME_IOU = 0.7
SIDE = 480             # masks are compared at most this large (long side)
SLIDE_REACH = 2.0      # slide displacements searched, in lengths of the front's diagonal
HINGE_SPAN_DEG = 120.0    # hinge angles searched, either way
STEPS = 45             # grid points of the per-frame search (then refined by a parabola)


@dataclass
class Views:
    """Per frame: the part's mask (h, w) bool, world -> camera (4, 4) in OpenCV axes; one K (3, 3) and OpenCV
    distortion (k1, k2, p1, p2[, k3]; None: a pinhole); `occluders`: per frame what is known to stand in front of
    everything (a hand, an arm, a person: the transient layer), or None."""

    masks: list[np.ndarray]
    w2c: np.ndarray
    K: np.ndarray
    dist: np.ndarray | None = None
    occluders: list[np.ndarray | None] | None = None
    images: Callable[[int], np.ndarray] | None = None  # frame i's RGB image (any size), for the routes that read it

    def occluder(self, i: int) -> np.ndarray | None:
        return None if self.occluders is None else self.occluders[i]

    def image(self, i: int) -> np.ndarray:
        if self.images is None:
            raise ValueError("these views carry no images")
        return self.images(i)


def front_corners(mask: np.ndarray) -> np.ndarray | None:
    """(4, 2) corners of a mask that is one quadrilateral (clockwise from the top left), sub-pixel: lines fitted to
    the middle of each side of its outline, intersected. None when it touches the border or has no four sides."""
    m = mask.astype(np.uint8)
    if m.sum() < 100 or m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any():
        return None
    contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    outline = max(contours, key=cv2.contourArea)
    hull = cv2.convexHull(outline)
    quad = None
    for eps in (0.02, 0.03, 0.05, 0.08):
        q = cv2.approxPolyDP(hull, eps * cv2.arcLength(hull, True), True).reshape(-1, 2).astype(float)
        if len(q) == 4:
            quad = q
            break
    if quad is None:
        return None
    mid = quad.mean(0)
    quad = quad[np.argsort(np.arctan2(quad[:, 1] - mid[1], quad[:, 0] - mid[0]))]
    quad = np.roll(quad, -int(np.argmin(quad.sum(1))), 0)
    pts = outline.reshape(-1, 2).astype(float)
    lines = []
    for e in range(4):
        a, b = quad[e], quad[(e + 1) % 4]
        length = float(np.linalg.norm(b - a))
        u = (b - a) / length
        along, across = (pts - a) @ u, (pts - a) @ np.array([-u[1], u[0]])
        sel = (along > 0.15 * length) & (along < 0.85 * length) & (np.abs(across) < max(2.0, 0.05 * length))
        if sel.sum() < 5:
            return None
        vx, vy, x0, y0 = cv2.fitLine(pts[sel].astype(np.float32), cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
        lines.append(np.cross([x0, y0, 1.0], [x0 + vx, y0 + vy, 1.0]))
    corners = np.array([c[:2] / c[2] for c in (np.cross(lines[e - 1], lines[e]) for e in range(4))])
    fill = np.zeros_like(m)
    cv2.fillConvexPoly(fill, np.round(corners * 16).astype(np.int32), 1, shift=4)
    inter, union = int((fill & m).sum()), int((fill | m).sum())
    return corners if union and inter / union >= QUAD_IOU else None  # else: no quadrilateral (an open drawer's box)


def _same_order(quads: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """One corner order for all frames: each frame's cyclic shift closest to the previous frame's."""
    out, prev = {}, None
    for i in sorted(quads):
        q = quads[i]
        if prev is not None:
            q = min((np.roll(q, -r, 0) for r in range(4)), key=lambda z: float(np.linalg.norm(z - prev)))
        out[i] = prev = q
    return out


def triangulate_front(quads: dict[int, np.ndarray], proj: dict[int, np.ndarray], states: dict[int, float],
                      slide: bool) -> np.ndarray:
    """(4, 3) corners at state 0: linear least squares over the frames' corners; with `slide`, frames at other
    states add `state x D` to every corner (D solved with them), else all frames must show the same state."""
    n = 15 if slide else 12
    rows, rhs = [], []
    for i, q in quads.items():
        m, p4 = proj[i][:, :3], proj[i][:, 3]
        for c in range(4):
            for coord, k in ((q[c, 0], 0), (q[c, 1], 1)):
                a = coord * m[2] - m[k]
                r = np.zeros(n)
                r[3 * c:3 * c + 3] = a
                if slide:
                    r[12:] = states[i] * a
                rows.append(r)
                rhs.append(-(coord * p4[2] - p4[k]))
    sol = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
    return sol[:12].reshape(4, 3)


def _reprojection(face: np.ndarray, q: np.ndarray, proj: np.ndarray) -> np.ndarray:
    p = (proj @ np.c_[face, np.ones(4)].T).T
    return np.linalg.norm(p[:, :2] / p[:, 2:3] - q, axis=1)


def _fit_front(views: Views, use: dict[int, np.ndarray], proj: dict[int, np.ndarray], shifted: dict[int, float],
               slide: bool) -> tuple[np.ndarray, float, float, int]:
    """(corners, median reprojection px, tilt per pixel of corner noise (deg), frames kept) from `use`'s corners, frames
    whose corners miss by more than 3x the median dropped (twice at most)."""
    for _ in range(3):
        face = triangulate_front(use, proj, shifted, slide)
        err = {i: float(_reprojection(face, use[i], proj[i]).max()) for i in use}
        keep = {i: q for i, q in use.items() if err[i] <= max(3.0, 3.0 * np.median(list(err.values())))}
        if len(keep) == len(use) or len(keep) < MIN_QUADS:
            break
        use = keep
    face = triangulate_front(use, proj, shifted, slide)
    med = float(np.median([_reprojection(face, use[i], proj[i]) for i in use]))
    # how far the front's normal turns when every corner moves by a pixel: views too close together leave its depth,
    # and so its tilt, free (a front triangulated from views 1 deg apart sits anywhere along the rays)
    rng = np.random.default_rng(0)
    normal = _normal(face)
    turns = [np.degrees(np.arccos(min(1.0, abs(float(normal @ _normal(triangulate_front(
        {i: q + rng.normal(0, 1.0, q.shape) for i, q in use.items()}, proj, shifted, slide))))))) for _ in range(4)]
    return face, med, float(max(turns)), len(use)


def view_spread_deg(point: np.ndarray, w2c: np.ndarray) -> float:
    """The widest angle (degrees) between two cameras (w2c (F, 4, 4), OpenCV) as seen from `point` (3,)."""
    centres = -np.einsum("fji,fj->fi", w2c[:, :3, :3], w2c[:, :3, 3])
    rays = centres - point
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
    return float(np.degrees(np.arccos(np.clip((rays @ rays.T).min(), -1.0, 1.0)))) if len(rays) else 0.0


def _normal(face: np.ndarray) -> np.ndarray:
    n = np.cross(face[2] - face[0], face[3] - face[1])
    return n / max(float(np.linalg.norm(n)), 1e-12)


def find_front(views: Views, states: np.ndarray, known: np.ndarray) -> tuple[np.ndarray | None, dict[str, Any]]:
    """The front's corners (4, 3) in the world, and at which state (`front_state` in the figures; None: a state no
    label gives); None and the reason when the views do not fix it.

    From the frames at known states first (at state 0 for a slide: its other known states join); else from a run of
    consecutive frames where the front rests, at whatever state (a capture labelled on a few isolated frames)."""
    quads = _same_order({i: q for i in range(len(views.masks)) if (q := front_corners(views.masks[i])) is not None})
    if views.dist is not None and np.any(views.dist):  # triangulated as a pinhole K would have seen them
        quads = {i: cv2.undistortPoints(q.reshape(-1, 1, 2), views.K, views.dist, P=views.K).reshape(-1, 2)
                 for i, q in quads.items()}
    proj = {i: views.K @ views.w2c[i][:3] for i in quads}
    known_quads = {i: q for i, q in quads.items() if known[i]}
    st = {i: float(states[i]) for i in known_quads}
    options = []
    if st:
        ref = min(set(st.values()), key=lambda v: (-sum(s == v for s in st.values()), v))  # the most shown state
        for slide in (True, False):  # a slide's frames at other states help; a hinge's only its reference state's
            use = dict(known_quads) if slide else {i: q for i, q in known_quads.items() if st[i] == ref}
            if len(use) >= MIN_QUADS and (not slide or len(set(st[i] for i in use)) >= 2):
                shifted = {i: st[i] - (0.0 if slide else ref) for i in use}
                options.append((*_fit_front(views, use, proj, shifted, slide), 0.0 if slide else ref))
    keys = sorted(quads)
    for a in range(max(0, len(keys) - REST_RUN + 1)):  # runs where the front rests, at an unknown state
        run = keys[a:a + REST_RUN]
        if run[-1] - run[0] < 1.5 * REST_RUN:
            options.append((*_fit_front(views, {i: quads[i] for i in run}, proj, dict.fromkeys(run, 0.0), False),
                            None))
    if not options:
        return None, {"silhouette_reason": f"the part's front showed four corners in {len(quads)} frames, "
                                           f"{len(known_quads)} at a known state (need {MIN_QUADS} at one state, or "
                                           f"{REST_RUN} running)", "front_frames": len(known_quads)}

    def rank(o: tuple) -> tuple:
        face, med, per_px, n, at = o
        tilt = per_px * max(med, MIN_NOISE_PX)  # how far its corners' own scatter may tilt it
        # pinned down, then known state, then closest: corners that agree best are a flat front (an open drawer's box
        # can pass for a quadrilateral in a view, but it is no flat one, and its corners scatter more)
        return med > FACE_PX or tilt > MAX_TILT_DEG, at is None, med

    face, med, per_px, n, at = min(options, key=rank)
    tilt = per_px * max(med, MIN_NOISE_PX)
    fig = {"front_frames": n, "front_px": round(med, 2), "front_tilt_deg": round(tilt, 2), "front_state": at}
    if rank((face, med, per_px, n, at))[0]:
        spread = view_spread_deg(face.mean(0), views.w2c[sorted(quads)])
        fig["view_spread_deg"] = round(spread, 1)
        why = []
        if med > FACE_PX:
            why.append(f"its corners reproject within {med:.2f} px of the masks' corners, need {FACE_PX} (the "
                       f"outline is not one flat quadrilateral in every view)")
        if tilt > MAX_TILT_DEG:
            why.append(f"that scatter may tilt it {tilt:.1f} deg, need {MAX_TILT_DEG}, with the {len(quads)} views "
                       f"spanning {spread:.0f} deg around it")
        fig["silhouette_reason"] = "the part's front is not pinned down by the views: " + "; ".join(why)
        return None, fig
    return face, fig


@dataclass
class Candidate:
    """A motion to try: a slide along `axis`, or a hinge about `axis` through `point`."""

    kind: str
    axis: np.ndarray
    point: np.ndarray

    def moved(self, face: np.ndarray, x: float) -> np.ndarray:
        """The points whose projections' hull is the part's silhouette at displacement x (world units or rad)."""
        if self.kind == "slide":
            return np.concatenate([face, face + x * self.axis])
        rot = Rotation.from_rotvec(self.axis * x).as_matrix()
        return (face - self.point) @ rot.T + self.point


def candidates(face: np.ndarray, w2c: np.ndarray) -> list[Candidate]:
    """A slide along the front's normal (towards the cameras) and a hinge about each of its edges."""
    normal = np.cross(face[1] - face[0], face[3] - face[0])
    normal /= np.linalg.norm(normal)
    cams = np.array([np.linalg.inv(m)[:3, 3] for m in w2c]).mean(0)
    if normal @ (cams - face.mean(0)) < 0:
        normal = -normal
    out = [Candidate("slide", normal, face.mean(0))]
    for e in range(4):
        edge = face[(e + 1) % 4] - face[e]
        out.append(Candidate("hinge", edge / np.linalg.norm(edge), face[e].copy()))
    return out


class Crop(NamedTuple):
    """One frame's box around the part, with what `Silhouettes.iou` needs of it made once: the camera's depth row, the
    box's corner (x0, y0) and clipping bound, the mask and the pixels an occluder hides in it as 0/1 bytes (the
    occluded ones None where nothing is), the mask's area."""

    depth: np.ndarray
    depth_at: float
    corner: np.ndarray
    big: int
    mask: np.ndarray
    area: int
    hidden: np.ndarray | None


class Silhouettes:
    """Each frame's mask at most `SIDE` large, cropped to the part with a margin: the overlap of a predicted
    silhouette is counted in the crop only (a part is a small share of the image)."""

    def __init__(self, views: Views, frames: list[int], side: int = SIDE):
        h, w = views.masks[0].shape
        self.scale = min(1.0, side / max(h, w))
        self.k = views.K.copy()
        self.k[:2] *= self.scale
        self.dist = np.zeros(5) if views.dist is None else np.asarray(views.dist, float)
        self.pose = {i: (cv2.Rodrigues(views.w2c[i][:3, :3])[0], views.w2c[i][:3, 3]) for i in frames}
        self.crop: dict[int, Crop] = {}  # the frames the part shows in
        for i in frames:
            m = self.small(views.masks[i])
            ys, xs = np.nonzero(m)
            if not len(xs):
                continue
            mx, my = (np.ptp(xs) + 1) // 2 + 2, (np.ptp(ys) + 1) // 2 + 2
            x0, y0 = max(0, xs.min() - mx), max(0, ys.min() - my)
            box = np.s_[y0:ys.max() + 1 + my, x0:xs.max() + 1 + mx]
            m, occ, hidden = m[box], views.occluder(i), None
            if occ is not None and occ.any():
                hidden = (self.small(occ)[box] & ~m).astype(np.uint8)
            self.crop[i] = Crop(views.w2c[i][2, :3].copy(), float(views.w2c[i][2, 3]), np.array([x0, y0], float),
                                4 * max(m.shape), m.astype(np.uint8), int(m.sum()), hidden)

    def small(self, m: np.ndarray) -> np.ndarray:
        """A full-size mask at the silhouettes' size."""
        if self.scale >= 1:
            return m.astype(bool)
        return cv2.resize(m.astype(np.uint8), None, fx=self.scale, fy=self.scale, interpolation=cv2.INTER_AREA) > 0

    def iou(self, pts: np.ndarray, i: int) -> float:
        """Overlap of the convex silhouette of world points `pts` (N, 3) with frame i's mask (the motion routes'
        inner loop, a few hundred thousand calls a part: what is fixed per frame is made once, OpenCV counts)."""
        c = self.crop[i]
        if ((pts @ c.depth + c.depth_at) <= 1e-6).any():  # behind the camera
            return 0.0
        uv, _ = cv2.projectPoints(pts, *self.pose[i], self.k, self.dist)  # the lens's bend at the vertices
        return overlap(uv.reshape(-1, 2), c)

    def ious(self, shapes: np.ndarray, i: int) -> np.ndarray:
        """(A,) `iou` of each of shapes (A, N, 3) on frame i, projected in one call (a grid of angles or pulls)."""
        c = self.crop[i]
        pts = shapes.reshape(-1, 3)
        seen = ((pts @ c.depth + c.depth_at) > 1e-6).reshape(shapes.shape[:2]).all(1)
        out = np.zeros(len(shapes))
        if seen.any():
            uv, _ = cv2.projectPoints(pts, *self.pose[i], self.k, self.dist)
            uv = uv.reshape(len(shapes), -1, 2)
            for j in np.flatnonzero(seen):
                out[j] = overlap(uv[j], c)
        return out


def overlap(uv: np.ndarray, c: Crop) -> float:
    """IoU of the convex hull of image points uv (N, 2) with the mask of the crop `c`."""
    uv = (uv - c.corner).clip(-c.big, c.big)  # a far-off or huge projection would take a rasteriser long to clip
    pred = np.zeros(c.mask.shape, np.uint8)
    cv2.fillConvexPoly(pred, cv2.convexHull((uv * 16).round().astype(np.int32)), 1, shift=4)
    inter, shown = cv2.countNonZero(cv2.bitwise_and(pred, c.mask)), cv2.countNonZero(pred)
    if c.hidden is not None:  # an arm in front of the part is no evidence against it there
        shown -= cv2.countNonZero(cv2.bitwise_and(pred, c.hidden))
    union = shown + c.area - inter
    return inter / union if union else 0.0


def best_displacement(sil: Silhouettes, cand: Candidate, face: np.ndarray, i: int, grid: np.ndarray
                      ) -> tuple[float, float]:
    """(displacement, IoU) of frame i: the best grid point, refined by a parabola through it and its neighbours."""
    vals = sil.ious(np.stack([cand.moved(face, x) for x in grid]), i)
    j = int(np.argmax(vals))
    x = float(grid[j])
    if 0 < j < len(grid) - 1:
        a, b, c = vals[j - 1], vals[j], vals[j + 1]
        den = a - 2 * b + c
        if den < 0:
            x += 0.5 * (a - c) / den * float(grid[1] - grid[0])
    return x, float(vals[j])


def silhouette_motion(views: Views, states: np.ndarray, known: np.ndarray, frames: list[int]
                      ) -> tuple[Fit | None, dict[str, Any]]:
    """The best candidate as a `Fit` over `frames` (positions into views: its per-frame displacement, the frames
    it measured, the search step as its position noise), or None and why; figures (per candidate mean IoU)."""
    face, fig = find_front(views, states, known)
    if face is None:
        return None, fig
    sil = Silhouettes(views, frames)
    shown = [i for i in frames if i in sil.crop]
    diag = float(np.linalg.norm(face[2] - face[0]))
    # a front found at state 0 is where a drawer rests closed: it cannot slide behind it (a mask that spills onto
    # the cabinet above would otherwise read as the drawer pushed in, and stretch the range)
    low = 0.0 if fig["front_state"] == 0 else -SLIDE_REACH
    grids = {"slide": np.linspace(low, SLIDE_REACH, STEPS) * diag,
             "hinge": np.radians(np.linspace(-HINGE_SPAN_DEG, HINGE_SPAN_DEG, STEPS))}
    results = []
    for cand in candidates(face, views.w2c[shown]):
        found = [best_displacement(sil, cand, face, i, grids[cand.kind]) for i in shown]
        results.append((float(np.mean([v for _, v in found])), cand, np.array([x for x, _ in found]),
                        np.array([v for _, v in found])))
    fig["silhouette_iou"] = {f"{c.kind}{'' if c.kind == 'slide' else k}": round(v, 3)
                             for k, (v, c, _, _) in enumerate(results)}
    score, cand, d, ious = max(results, key=lambda r: r[0])
    fig["silhouette_mean_iou"] = round(score, 3)
    if score < MIN_IOU:
        fig["silhouette_reason"] = f"no motion's silhouettes overlap the masks well (best {score:.2f}, need {MIN_IOU})"
        return None, fig
    measured = {i: x for i, x, v in zip(shown, d, ious) if v >= MIN_FRAME_IOU}
    fig["silhouette_unfit_frames"] = len(shown) - len(measured)
    step = float(grids[cand.kind][1] - grids[cand.kind][0])
    return Fit(cand.kind, cand.axis, cand.point, np.array([measured.get(i, 0.0) for i in frames]),
               np.array([i in measured for i in frames]), np.full(len(frames), step), 1.0, {}), fig


def views_of(ds, obj: int) -> Views:
    """Object `obj`'s masks over the dataset's frames with its known cameras (the routes that need no pose), and
    the transient layer (hands, arms, people: painted or found) as what stands in front of it."""
    w2c = np.stack([np.linalg.inv(opengl_to_opencv(f.c2w)) for f in ds.frames])
    masks = [ds.load_mask(f)[..., obj] for f in ds.frames]
    occluders = ([read_transient(ds.root, f.fid, m.shape) for f, m in zip(ds.frames, masks)]
                 if has_transients(ds.root) else None)
    images = (lambda i: ds.load_image(ds.frames[i])) if hasattr(ds, "load_image") else None
    return Views(masks, w2c, ds.intrinsics.K(), ds.intrinsics.dist(), occluders, images)


def measure_silhouettes(ds, obj: int, states: np.ndarray, known: np.ndarray, labelled: np.ndarray,
                        min_pixels: int = 400, trust_labels: bool = False, views: Views | None = None
                        ) -> tuple[Articulation | None, dict[str, Any]]:
    """Object `obj`'s motion from its masks over the dataset `ds` and its known cameras; states, known, labelled
    (N,) over the dataset's frames; `views`: `views_of(ds, obj)` when the caller has it. (None, figures with
    `silhouette_reason`) when the route cannot measure it."""
    views = views_of(ds, obj) if views is None else views
    frames = [i for i, m in enumerate(views.masks) if int(m.sum()) >= min_pixels]
    fit, fig = silhouette_motion(views, states, known, frames)
    fig["route"] = "silhouette"
    if fit is None:
        return None, dict(fig, registered=0)
    fig.update(registered=int(fit.ok.sum()), kind_from="silhouettes")
    at = np.array(frames)
    return articulate(fit, at, states[at], known[at], labelled[at], fig, trust_labels)
