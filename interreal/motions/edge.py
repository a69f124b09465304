"""A plain door or lid: its hinge as the edge of its outline that stays put, its leaf fitted to every frame's mask.

The corners route (`silhouette`) needs the front's four corners in some views; a tall door filmed from close by is
cut by the image border in every frame, and a plain one gives SfM and PnP nothing to match. What its masks do show
is its outline, and one straight stretch of it stays in one place in the world whatever the state: the hinge edge.
1. `hinge_lines`: each pair of straight stretches of two keyframes' outlines (keyframe masks are the person's,
   not propagated) is triangulated to a 3D line, costed by its distance to every keyframe's outline; the hinge is
   the one all keyframes agree on (along the hinge side, where a plain door meets its plain body, propagated
   outlines stray 2-5 px, and a line lifted with them is tens of degrees off); with one keyframe, its stretches
   are lifted to the line most frames' outlines agree with (`static_line`);
2. `leaf.fit_leaf`: the door is a rectangle hinged on that line, `width` wide and spanning [h0, h1] along it,
   turned by its own angle in each frame: the three sizes are those whose best silhouettes overlap the masks most
   on average (Nelder-Mead from a grid; frames labelled at one end share one angle) on each of the best lines;
   `leaf.refine_leaf` then moves the two ends of each line that fits nearly as well as the best with the size and
   a thickness (a slab) until every frame's best silhouette fits (a line a few px off turns the angles by 10-17 deg
   seen from close by, and can trail a wrong line before it is refined);
3. every frame's angle by dynamic programming over the frames in time order (a door turns smoothly: a frame whose
   mask lost the door follows its neighbours, not a guess from that mask); the frames the masks stage lost are read
   by their colours (`colour`) and steer the path without measuring a state: the door closed seen from the side
   pins the closed angle that a frontal view cut by the border leaves free over tens of degrees; `judge`: bounds
   on the keyframes, a slide as the rival elsewhere;
4. the angles are the displacement `fit.articulate` reads: the geometry measures, the labels only orient.
Its limits: a drawer (nothing of it stays put) is left to the other routes; propagated masks that lose the open
door leave its angles to the path's smoothness, and a slide explains them as well on some simulated captures
(refused); a thick door filmed from the side its hinge edge faces hides that edge behind its own (no line stays
within 3 px of the keyframes' outlines) (docs/measurements.md, 2026-12-06).
"""

from __future__ import annotations

from itertools import permutations, product
from typing import Any

import cv2
import numpy as np
from scipy.optimize import minimize

from ..dataset import SAME_STATE, Articulation
from .colour import SWEEP, ColourSilhouettes
from .fit import Fit, articulate
from .leaf import KEEP, Leaf, Line, fit_leaf, iou_curves, refine_leaf
from .path import anchored_path, refine
from .silhouette import Silhouettes, Views, views_of

SIDE = 480            # outlines and final silhouettes are compared at most this large (long side) ...
SEARCH_SIDE = 240     # ... the leaf's size is searched on silhouettes this large
TRUNC_PX = 12.0       # an outline further than this (work-size px) from a projected point counts as this far
ALONG = np.linspace(0.15, 0.85, 12)[:, None]  # where a candidate line is sampled: its ends may be corners shared
#                                                with edges that move
SEGMENT_SHARE = 0.1   # straight stretches of an outline at least this share of the image diagonal
MAX_LINE_PX = 3.0     # a hinge line further than this (work size, mean over the frames kept) from the outlines: none
ANGLES = 144          # angle grid of a frame's search (2.5 deg), refined by a parabola
MIN_FRAME_IOU = 0.7   # a frame whose best silhouette overlaps its mask less than this is not measured
MAX_OUTLINE_PX = 3.0  # the turning leaf's outline within this of the keyframes' (median, work-size px) ...
MOVED = 0.25          # ... and, over the frames turned at least this share of the widest turn from rest, ...
OUTLINE_RATIO = 0.8   # ... within this share of the distance a slide of its front keeps from the masks' outlines ...
SLIDE_MARGIN = 0.05   # ... or overlapping those masks this much more than the slide (`leaf_beats_slide`), which
#                       takes its best reach in each frame, unsmoothed: a drawer's outline has static edges too (the
#                       cabinet's opening).
#                       Simulated plain captures (--hard seeds 1-10), moved frames, propagated masks: doors' leaves
#                       0.44-0.70 of the slide's outline distance (one 0.89), -0.01 to +0.14 in overlap; drawers
#                       0.73-1.8; with the simulator's masks one drawer as a flap 0.69 and +0.03. Chosen on those seeds.
REFINE_MARGIN = 0.05  # the lines whose thin leaf fits within this of the best one's are refined (at most
REFINED = 2           # this many), the best refined kept: refining gains 0.03-0.05 in overlap, so a line a few cm
#                       off the hinge can trail a wrong one (the door's free edge) until both are refined
LINES = 4             # the cheapest static lines a leaf is fitted on, and at most OTHER_DIRECTIONS more: the
OTHER_DIRECTIONS = 2  # cheapest of each direction they leave out (APART_DEG or more from each): between two closed
APART_DEG = 30.0      # keyframes every edge of a closed door stays put, and its top and bottom edges, seen from each,
#                       can take every slot (simulated plain seed 1: the hinge 5th, 1.16 px against 0.5-1.1)
ASK = 3               # frames a person is asked to draw at most (here where a slide and a leaf tie; `reach`)
KEY_WEIGHT = 5.0      # a keyframe's overlap counts this many frames' in the dynamic programming
MIN_CONFIDENCE = 0.5  # frames whose mask the masks stage trusts less than this are left out (a plain door's mask
#                       leaves it within a few frames of a keyframe, and the stage knows: 0.07-0.3 there)
MIN_KEY_IOU = 0.8     # the keyframes' masks (exact) must be explained this well on average (a door's edge seen side
#                       on widens its mask beyond its front's: 0.76 on one simulated keyframe with its true masks)


class Outlines:
    """Per frame: the distance (work-size px, at most `TRUNC_PX`) to its mask's outline away from the image border
    (a mask cut by the border shows no edge of the part there), stacked to project points into every frame at once."""

    def __init__(self, views: Views, frames: list[int]):
        h, w = views.masks[frames[0]].shape
        scale = min(1.0, SIDE / max(h, w))
        self.k = views.K.copy()
        self.k[:2] *= scale
        self.dist = np.zeros(5) if views.dist is None else np.asarray(views.dist, float)
        self.size = (int(round(w * scale)), int(round(h * scale)))
        maps, kept = [], []
        hidden: dict[int, np.ndarray] = {}  # per frame, where an occluder (dilated) covers the image
        for i in frames:
            m = cv2.resize(views.masks[i].astype(np.uint8), self.size, interpolation=cv2.INTER_AREA)
            edge = cv2.morphologyEx(m, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
            edge[:2], edge[-2:], edge[:, :2], edge[:, -2:] = False, False, False, False
            occ = views.occluder(i)
            if occ is not None and occ.any():  # where an arm cuts the mask, its outline is the arm's, not the part's
                occ = cv2.dilate(cv2.resize(occ.astype(np.uint8), self.size, interpolation=cv2.INTER_NEAREST),
                                 np.ones((5, 5), np.uint8)) > 0
                edge &= ~occ
                hidden[i] = occ
            if edge.sum() >= 10:
                maps.append(np.minimum(cv2.distanceTransform((~edge).astype(np.uint8), cv2.DIST_L2, 3), TRUNC_PX))
                kept.append(i)
        self.frames = kept
        self.at = {i: n for n, i in enumerate(kept)}
        self.dt = np.stack(maps) if maps else np.zeros((0, self.size[1], self.size[0]), np.float32)
        self.w2c = views.w2c[kept] if kept else np.zeros((0, 4, 4))
        self.occluded = (np.stack([hidden.get(i, np.zeros(self.dt.shape[1:], bool)) for i in kept])
                         if hidden and kept else None)  # (F, h, w) or None: no occluder in any frame kept

    def distances(self, pts: np.ndarray) -> np.ndarray:
        """(F,) mean outline distance of the points' (P, 3) projections in each frame; NaN where fewer than half
        land inside the image or any lies behind the camera."""
        cam = np.einsum("fij,pj->fpi", self.w2c[:, :3, :3], pts) + self.w2c[:, None, :3, 3]
        z = cam[..., 2]
        uv, _ = cv2.projectPoints(cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.k, self.dist)
        uv = np.nan_to_num(uv, nan=-1e6, posinf=1e6, neginf=-1e6)  # a point in the camera's plane: outside
        u, v = uv.reshape(*z.shape, 2).transpose(2, 0, 1)
        w, h = self.size
        inside = (u >= 2) & (u < w - 2) & (v >= 2) & (v < h - 2) & (z > 1e-6)
        f = np.broadcast_to(np.arange(len(self.frames))[:, None], u.shape)
        at = (f, np.clip(v, 0, h - 1).astype(int), np.clip(u, 0, w - 1).astype(int))
        if self.occluded is not None:  # behind an occluder: not seen, neither near nor far from the outline
            inside &= ~self.occluded[at]
        vals = np.where(inside, self.dt[at], 0.0)
        n = inside.sum(1)
        good = (n >= 0.5 * pts.shape[0]) & (z > 1e-6).all(1)
        return np.where(good, vals.sum(1) / np.maximum(n, 1), np.nan)

    def hull_distance(self, pts: np.ndarray, i: int) -> float | None:
        """Mean distance (work-size px) from the outline of the points' projected hull in frame i to its mask's
        outline, over the hull's samples inside the image; None when fewer than 10 are."""
        n = self.at.get(i)
        if n is None or ((pts @ self.w2c[n][2, :3] + self.w2c[n][2, 3]) <= 1e-6).any():
            return None
        uv, _ = cv2.projectPoints(pts, cv2.Rodrigues(self.w2c[n][:3, :3])[0], self.w2c[n][:3, 3], self.k, self.dist)
        hull = cv2.convexHull(uv.reshape(-1, 2).astype(np.float32)).reshape(-1, 2)
        along = np.linspace(0.0, 1.0, 20, endpoint=False)[:, None]
        samples = np.concatenate([a + along * (b - a) for a, b in zip(hull, np.roll(hull, -1, 0))])
        w, h = self.size
        inside = (samples[:, 0] >= 3) & (samples[:, 0] < w - 3) & (samples[:, 1] >= 3) & (samples[:, 1] < h - 3)
        if inside.sum() < 10:
            return None
        s = samples[inside].astype(int)
        if self.occluded is not None:  # samples behind an occluder say nothing of the part's outline
            s = s[~self.occluded[n][s[:, 1], s[:, 0]]]
            if len(s) < 10:
                return None
        return float(self.dt[n][s[:, 1], s[:, 0]].mean())


def segments(mask: np.ndarray, min_len: float) -> list[np.ndarray]:
    """Straight stretches (2, 2) of the mask's outline at least `min_len` px long, none along the image border."""
    m = mask.astype(np.uint8)
    h, w = m.shape
    contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)

    def on_border(z: np.ndarray) -> bool:
        return min(z[0], z[1], w - 1 - z[0], h - 1 - z[1]) < 3

    out = []
    for c in contours:
        if cv2.contourArea(c) < 0.01 * h * w:
            continue
        poly = cv2.approxPolyDP(c, 0.01 * cv2.arcLength(c, True), True).reshape(-1, 2).astype(float)
        for k in range(len(poly)):
            p, q = poly[k], poly[(k + 1) % len(poly)]
            if np.linalg.norm(q - p) >= min_len and not (on_border(p) and on_border(q) and on_border((p + q) / 2)):
                out.append(np.array([p, q]))
    return out


def static_line(out: Outlines, views: Views, key: int, seg: np.ndarray, keys: list[int], scale: float) -> Line:
    """The 3D line through keyframe `key`'s outline stretch `seg` that lies on the outlines of the other keyframes
    and of the best `KEEP` of the frames: its two end depths searched on a grid, then refined. Used where a single
    keyframe shows the part (`keyframe_lines` needs two)."""
    centre, rays = _rays(views, out, key, seg)
    on_key = np.array([i in keys and i != key for i in out.frames])

    def cost(x: np.ndarray) -> float:
        p, q = centre + np.exp(x[0]) * rays[0], centre + np.exp(x[1]) * rays[1]
        d = out.distances(p + ALONG * (q - p))
        vals = d[np.isfinite(d)]
        if len(vals) < 3:
            return TRUNC_PX
        kept = float(np.mean(np.sort(vals)[:max(3, int(KEEP * len(vals)))]))
        keyed = d[on_key & np.isfinite(d)]
        return 0.5 * (kept + float(keyed.mean())) if len(keyed) else kept

    grid = np.log(np.geomspace(0.05, 5.0, 40) * scale)
    start = min(((cost(np.array([a, b])), (a, b)) for a in grid for b in grid), key=lambda r: r[0])[1]
    res = minimize(cost, np.array(start), method="Nelder-Mead", options={"xatol": 1e-3, "fatol": 1e-3, "maxiter": 200})
    p, q = centre + np.exp(res.x[0]) * rays[0], centre + np.exp(res.x[1]) * rays[1]
    return Line.seen_from(p, q, float(res.fun), key, centre)


def _rays(views: Views, out: Outlines, key: int, seg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keyframe `key`'s camera centre (3,) and the unit rays (2, 3) through the ends of its outline stretch `seg`."""
    c2w = np.linalg.inv(views.w2c[key])
    und = cv2.undistortPoints(seg.reshape(-1, 1, 2).astype(float), views.K, out.dist).reshape(-1, 2)
    rays = (c2w[:3, :3] @ np.c_[und, np.ones(2)].T).T
    return c2w[:3, 3], rays / np.linalg.norm(rays, axis=1, keepdims=True)


def triangulate(views: Views, out: Outlines, a: int, seg_a: np.ndarray, b: int, seg_b: np.ndarray) -> Line | None:
    """The 3D line two keyframes' outline stretches are views of (the planes through each camera and its stretch
    meet there), spanning stretch `seg_a`'s ends; None when the planes are within 5 deg of one another."""
    (ca, ra), (cb, rb) = _rays(views, out, a, seg_a), _rays(views, out, b, seg_b)
    na, nb = np.cross(ra[0], ra[1]), np.cross(rb[0], rb[1])
    na, nb = na / np.linalg.norm(na), nb / np.linalg.norm(nb)
    u = np.cross(na, nb)
    if np.linalg.norm(u) < np.sin(np.radians(5.0)):
        return None
    u /= np.linalg.norm(u)
    p0 = np.linalg.solve(np.array([na, nb, u]), [na @ ca, nb @ cb, 0.0])
    ends = []
    for r in ra:  # the line's point nearest each end ray of stretch a
        m = np.array([[1.0, -(u @ r)], [u @ r, -1.0]])
        s, _ = np.linalg.solve(m, [(ca - p0) @ u, (ca - p0) @ r])
        ends.append(p0 + s * u)
    if np.linalg.norm(ends[1] - ends[0]) < 1e-9:
        return None
    return Line.seen_from(ends[0], ends[1], 0.0, a, ca)


def key_cost(on_keys: np.ndarray, pair: list[int]) -> float:
    """A line's mean distance (NaN: not seen) to the keyframes' outlines, the two it was triangulated from (`pair`,
    positions into `on_keys`) counted as they are and of the others the best `KEEP` share (at least one): with more
    keyframes come more where an arm or the door's own thickness hides the hinge's edge (a door open past 90 deg
    shows its back face's edge there)."""
    others = np.sort([d for n, d in enumerate(on_keys) if n not in pair and np.isfinite(d)])
    kept = np.r_[on_keys[[n for n in pair if np.isfinite(on_keys[n])]], others[:int(np.ceil(KEEP * len(others)))]]
    return float(kept.mean())


def keyframe_lines(views: Views, out: Outlines, keys: list[int], kout: Outlines) -> list[Line]:
    """Every pair of straight stretches of two keyframes' outlines triangulated to a 3D line, costed by its mean
    distance to the outlines of the keyframes it shows in (a person drew those; two keyframes agree with any line
    they triangulate, so with two the best `KEEP` of the frames' outlines count as much). Why keyframes: along the
    hinge side, where a plain door meets its plain body, propagated outlines stray, and lines lifted with them do."""
    h, w = views.masks[keys[0]].shape
    segs = {k: segments(views.masks[k], SEGMENT_SHARE * float(np.hypot(h, w))) for k in keys}
    lines = []
    for a, b in permutations(keys, 2):
        for sa, sb in product(segs[a], segs[b]):
            ln = triangulate(views, out, a, sa, b, sb)
            if ln is None:
                continue
            pts = ln.p + ALONG * (ln.q - ln.p)
            on_keys = kout.distances(pts)
            if np.isfinite(on_keys).sum() < min(3, len(kout.frames)):  # seen in every keyframe (or three)
                continue
            ln.cost = key_cost(on_keys, [n for n, k in enumerate(kout.frames) if k in (a, b)])
            if len(kout.frames) < 3:
                d = out.distances(pts)
                vals = np.sort(d[np.isfinite(d)])
                ln.cost = 0.5 * (ln.cost + (float(vals[:max(3, int(KEEP * len(vals)))].mean())
                                            if len(vals) >= 3 else TRUNC_PX))
            lines.append(ln)
    return lines


def hinge_lines(views: Views, frames: list[int], keys: list[int]) -> tuple[list[Line], Outlines]:
    """Hinge candidates, best first, one per line in the world: triangulated from pairs of keyframes
    (`keyframe_lines`), or with one keyframe its outline stretches lifted to the line most frames agree with."""
    out = Outlines(views, frames)
    centres = np.array([np.linalg.inv(views.w2c[i])[:3, 3] for i in frames])
    scale = float(np.linalg.norm(centres - centres.mean(0), axis=1).mean()) or 1.0
    h, w = views.masks[keys[0]].shape
    kout = Outlines(views, keys)
    if len(kout.frames) >= 2:
        lines = keyframe_lines(views, out, kout.frames, kout)
    else:
        lines = [static_line(out, views, k, seg, keys, scale)
                 for k in keys for seg in segments(views.masks[k], SEGMENT_SHARE * float(np.hypot(h, w)))]
    distinct: list[Line] = []
    for ln in sorted(lines, key=lambda ln: ln.cost):  # one line seen in several keyframes is one candidate
        mid = 0.5 * (ln.p + ln.q)
        if not any(abs(float(ln.axis @ o.axis)) > np.cos(np.radians(3.0))
                   and np.linalg.norm(np.cross(mid - o.p, o.axis)) < 0.02 * scale for o in distinct):
            distinct.append(ln)
    return distinct, out


def slide_rival(sil: Silhouettes, out: Outlines, leaf: Leaf, size: np.ndarray, frames: list[int], rest: float
                ) -> tuple[float, float, list[int]]:
    """The median outline distance (px), the mean overlap and the frames judged of the best slide of the leaf's
    front as it rests (at angle `rest`, give or take 10 deg, and up to a third of its width in front of or behind
    the line): pulled along its normal by each frame's best amount (the prism between its rest and its moved
    place). A drawer's outline has static edges too (the cabinet's opening), and a turning leaf covers much of a
    drawer's silhouette; the slide explains a drawer's masks better."""
    some = frames[::max(1, len(frames) // 24)]
    width = size[0] * leaf.length
    reach = np.linspace(0.0, 1.5, 31) * width
    best: tuple[float, list[np.ndarray]] = (-1.0, [])
    for phi in rest + np.radians([-10.0, 0.0, 10.0]):
        base = leaf.corners(*size, phi)
        normal = np.cross(base[1] - base[0], base[3] - base[0])
        normal /= np.linalg.norm(normal)
        for sign in (1.0, -1.0):  # the drawer comes out on one side of its front
            for shift in np.linspace(-1 / 3, 1 / 3, 5) * width:
                front = base + shift * normal
                prisms = np.stack([np.concatenate([front, front + sign * x * normal]) for x in reach])
                shapes, total = [], 0.0
                for i in some:
                    v = sil.ious(prisms, i)
                    total += float(v.max())
                    shapes.append(prisms[int(np.argmax(v))])
                if total > best[0]:
                    best = (total, shapes)
    dist = [d for i, q in zip(some, best[1]) if (d := out.hull_distance(q, i)) is not None]
    return (float(np.median(dist)) if dist else TRUNC_PX), best[0] / len(some), some


def judge(fig: dict[str, Any], sil: Silhouettes, out: Outlines, leaf: Leaf, size: np.ndarray, shown: list[int],
          phi: np.ndarray, rest: float, keys: list[int]) -> str | None:
    """Why the leaf at angles `phi` (unwrapped, over `shown`) is no flat door or lid, or None; its figures into
    `fig`. Absolute bounds are put on the keyframes' outlines (a person drew them; a propagated outline strays 2-5 px
    from a plain door's own); propagated frames only compare the leaf with its rival, a slide of its front, on the
    same masks, and only where the two differ: the frames turned at least `MOVED` of the way from rest
    (`leaf_beats_slide`). A leaf kept on one count only must be kept on the keyframes among them too (exact masks:
    a drawer's leaf traced its propagated outlines 1.7 px against the slide's 3.7 and lost its drawn ones), and the
    frames that would confirm it are named (`edge_confirm`)."""
    key_px = [d for i, a in zip(shown, phi) if i in keys and (d := out.hull_distance(leaf.corners(*size, a), i))
              is not None]
    key_px = float(np.median(key_px)) if key_px else TRUNC_PX
    away = np.abs(phi - rest)
    moved = [i for i, a in zip(shown, away) if a >= MOVED * away.max()]
    hinge_px, slide_px, hinge_iou, slide_iou, some = rival_figures(sil, out, leaf, size, shown, phi, rest,
                                                                   moved if len(moved) >= 3 else shown)
    fig.update(edge_key_outline_px=round(key_px, 2), edge_outline_px=round(hinge_px, 2),
               edge_slide_outline_px=round(slide_px, 2), edge_hinge_iou=round(hinge_iou, 3),
               edge_slide_iou=round(slide_iou, 3), edge_judged_frames=len(some))
    if key_px > MAX_OUTLINE_PX:
        return (f"a leaf turning on its static edge does not trace the keyframes' outlines (median {key_px:.1f} px "
                f"from them, need {MAX_OUTLINE_PX:g}): no flat door or lid")
    if hinge_iou < MIN_FRAME_IOU:
        return (f"a leaf turning on its static edge overlaps the masks of the frames it turned in by {hinge_iou:.2f} "
                f"(need {MIN_FRAME_IOU}): no flat door or lid")
    kept, on_both = leaf_beats_slide(hinge_px, slide_px, hinge_iou, slide_iou)
    drawn, where = [i for i in moved if i in keys], "the frames it moved in"
    if kept and not on_both and drawn:  # kept on one count: the masks a person drew where it moved must keep it too
        hinge_px, slide_px, hinge_iou, slide_iou, _ = rival_figures(sil, out, leaf, size, shown, phi, rest, drawn)
        kept, where = leaf_beats_slide(hinge_px, slide_px, hinge_iou, slide_iou)[0], "the keyframes it moved in"
    if not kept:
        fig["edge_decide"] = deciding_frames(moved, keys)
        fig["edge_contested"] = bool(hinge_px < slide_px and hinge_iou > slide_iou)  # better, not by the margins
        return (f"a slide of its front explains the masks of {where} as well as a leaf turning on its "
                f"static edge (outline {slide_px:.1f} px against {hinge_px:.1f}, need {OUTLINE_RATIO:g} of it or "
                f"less; overlap {slide_iou:.2f} against {hinge_iou:.2f}, need {SLIDE_MARGIN:g} less, the other not "
                f"lost by as much): a drawer, not a flat door or lid")
    if not on_both:  # kept on one count: a drawn mask where it moved confirms it
        fig["edge_confirm"] = deciding_frames(moved, keys)
    return None


def rival_figures(sil: Silhouettes, out: Outlines, leaf: Leaf, size: np.ndarray, shown: list[int], phi: np.ndarray,
                  rest: float, frames: list[int]) -> tuple[float, float, float, float, list[int]]:
    """(leaf's outline px, slide's, leaf's overlap, slide's, frames judged) over `frames` (a subset of `shown`), the
    leaf at its angles `phi` and the slide of its front at its best pull in each (`slide_rival`)."""
    slide_px, slide_iou, some = slide_rival(sil, out, leaf, size, frames, rest)
    at = [leaf.corners(*size, phi[shown.index(i)]) for i in some]
    hinge_iou = float(np.mean([sil.iou(c, i) for c, i in zip(at, some)]))
    hinge_px = [d for c, i in zip(at, some) if (d := out.hull_distance(c, i)) is not None]
    return (float(np.median(hinge_px)) if hinge_px else TRUNC_PX), slide_px, hinge_iou, slide_iou, some


def rival_words(fig: dict[str, Any]) -> str:
    """The edge route's leaf against the slide of its front, from its figures (`judge`), in a warning's words."""
    return (f"the leaf's outline {fig.get('edge_outline_px')} px from theirs against the slide's "
            f"{fig.get('edge_slide_outline_px')}, its overlap {fig.get('edge_hinge_iou')} against "
            f"{fig.get('edge_slide_iou')}")


def leaf_beats_slide(hinge_px: float, slide_px: float, hinge_iou: float, slide_iou: float) -> tuple[bool, bool]:
    """(kept, on both counts): the leaf against a slide of its front, on the median outline distance (px) and the
    mean overlap of the frames it turned in, each won or lost by its margin (`OUTLINE_RATIO`, `SLIDE_MARGIN`). It
    is kept where it wins one count and does not lose the other: propagated masks of a plain door stray 2-5 px, so
    either count alone can tie (simulated plain doors: overlap 0.94 against 0.78 at 2.7 px against 2.6; 1.4 px
    against 4.7 at 0.93 against 0.90)."""
    won = (hinge_px <= OUTLINE_RATIO * slide_px, hinge_iou >= slide_iou + SLIDE_MARGIN)
    lost = (OUTLINE_RATIO * hinge_px > slide_px, hinge_iou < slide_iou - SLIDE_MARGIN)
    return (won[0] and not lost[1]) or (won[1] and not lost[0]), all(won)


def deciding_frames(moved: list[int], keys: list[int]) -> list[int]:
    """At most `ASK` of the frames the leaf turned in (`moved`, in time order) that no person drew, spread over them:
    where a drawn mask decides between a leaf and a slide of its front. Why: propagated masks of a plain door stray
    where it turns, and both models explain them alike; a drawn mask there is exact, and the keyframes pin the
    path (`KEY_WEIGHT`) and bound the outline (simulated plain doors refused so: 2 of 4 measured right once three
    were drawn)."""
    free = [i for i in moved if i not in keys]
    if not free:
        return []
    return sorted({free[int(q * (len(free) - 1))] for q in np.linspace(1 / 6, 5 / 6, ASK)})


def label_ends(shown: list[int], states: np.ndarray | None, known: np.ndarray | None
               ) -> tuple[np.ndarray, list[np.ndarray]]:
    """(still (F,), [closed (F,), opened (F,)]) over `shown` from the labels: the frames resting at one labelled
    state with the frame before, those labelled at the lowest state (where it rests closed) and at the highest."""
    n = len(shown)
    still, closed, opened = np.zeros(n, bool), np.zeros(n, bool), np.zeros(n, bool)
    if states is not None and known is not None and n:
        at = np.array(shown)
        still[1:] = known[at[1:]] & known[at[:-1]] & (np.abs(states[at[1:]] - states[at[:-1]]) <= SAME_STATE)
        if known[at].any():
            closed = known[at] & (states[at] <= states[at][known[at]].min() + SAME_STATE)
            opened = known[at] & (states[at] >= states[at][known[at]].max() - SAME_STATE) & ~closed
    return still, [closed, opened]


def end_samples(shown: list[int], ends: list[np.ndarray]) -> list[list[int]]:
    """Of each of `ends` (bool over `shown`), at most about 8 of its frames, spread: what `fit_leaf` pins a size on."""
    return [[shown[f] for f in np.flatnonzero(e)[::max(1, int(e.sum()) // 8)]] for e in ends]


def trusted_frames(views: Views, keys: list[int], min_pixels: int, confidence: np.ndarray | None) -> list[int]:
    """The frames whose mask shows the part (`min_pixels`) and that the masks stage trusts (`MIN_CONFIDENCE`;
    the keyframes always)."""
    n = len(views.masks)
    trusted = np.ones(n, bool) if confidence is None else np.asarray(confidence) >= MIN_CONFIDENCE
    trusted[[k for k in keys if k < n]] = True
    return [i for i, m in enumerate(views.masks) if trusted[i] and int(m.sum()) >= min_pixels]


def candidate_lines(lines: list[Line]) -> list[Line]:
    """The `LINES` cheapest of `lines` (cheapest first) and, after them, the cheapest line of each direction they
    leave out (at most `OTHER_DIRECTIONS`): a cost that every edge of a closed door shares says nothing of which edge
    turns, the leaf fitted on each does."""
    picked = list(lines[:LINES])
    for ln in lines[LINES:]:
        if len(picked) >= LINES + OTHER_DIRECTIONS:
            break
        if all(_angle_deg(ln, other) >= APART_DEG for other in picked):
            picked.append(ln)
    return picked


def _angle_deg(a: Line, b: Line) -> float:
    """The angle between two lines' directions, 0-90 deg."""
    u, v = a.q - a.p, b.q - b.p
    return float(np.degrees(np.arccos(min(1.0, abs(u @ v) / (np.linalg.norm(u) * np.linalg.norm(v) + 1e-12)))))


def edge_motion(views: Views, frames: list[int], keys: list[int], states: np.ndarray | None = None,
                known: np.ndarray | None = None) -> tuple[Fit | None, dict[str, Any]]:
    """The hinge about the best static outline line, as a `Fit` over `frames` (the angle per frame), or None and
    why; `keys`: the keyframes (positions into views) among `frames`; states, known (over views): where the labels
    say the part rests (`smooth_path`)."""
    keys = [k for k in keys if k in frames]
    if not keys:
        return None, {"edge_reason": "no keyframe mask shows the part (its outline's straight edges come from "
                                     "keyframes)"}
    lines, out = hinge_lines(views, frames, keys)
    fig: dict[str, Any] = {"edge_lines": [round(ln.cost, 2) for ln in lines[:4]]}
    lines = [ln for ln in lines if ln.cost <= MAX_LINE_PX]
    if not lines:
        fig["edge_reason"] = (f"no straight edge of its keyframe outlines stays put across the frames (best "
                              f"{min(fig['edge_lines'], default=float('nan'))} px from the outlines, need "
                              f"{MAX_LINE_PX})")
        return None, fig
    coarse, sil = Silhouettes(views, frames, SEARCH_SIDE), Silhouettes(views, frames)
    shown = [i for i in frames if i in sil.crop]
    still, (closed, opened) = label_ends(shown, states, known)
    ends = end_samples(shown, [closed, opened])
    fits = sorted(((ln, *fit_leaf(coarse, ln, shown, keys, ends)) for ln in candidate_lines(lines)),
                  key=lambda r: -r[2])
    line, size, thickness, _ = max((refine_leaf(coarse, ln, sz, shown, keys) for ln, sz, fit in fits[:REFINED]
                                    if fit >= fits[0][2] - REFINE_MARGIN), key=lambda r: r[3])
    leaf = Leaf(line, thickness)
    angles = np.linspace(-np.pi, np.pi, ANGLES, endpoint=False)
    lost = [i for i in range(len(views.masks)) if i not in sil.crop] if views.images is not None else []
    every = sorted(shown + lost)
    colour = ColourSilhouettes(views, sil, keys, [leaf.corners(*size, a) for a in SWEEP]) if lost else None
    curves = np.zeros((len(every), len(angles)))
    read = np.isin(every, shown)
    curves[read] = iou_curves(sil, leaf, size, shown, angles)
    if colour is not None:
        curves[~read] = iou_curves(colour, leaf, size, lost, angles)
        fig["edge_read_by_colour"] = len(lost)
    still, (closed, opened) = label_ends(every, states, known)
    weight = np.array([KEY_WEIGHT if i in keys else 1.0 for i in every])[:, None]  # a person drew those masks
    path = anchored_path(curves * weight, angles, still, [closed, opened])
    phi = np.array([refine(curves[f], j, angles) for f, j in enumerate(path)])
    iou = curves[np.arange(len(every)), path]
    unwrapped = np.unwrap(phi)
    rest = float(np.median(unwrapped[closed if closed.any() else still if still.any() else slice(0, 1)]))
    reason = judge(fig, coarse, out, leaf, size, shown, unwrapped[read], rest, keys)
    if reason:
        fig["edge_reason"] = reason
        return None, fig
    key_iou = [float(v) for i, v in zip(every, iou) if i in keys]
    fig.update(edge_line_px=round(line.cost, 2), edge_leaf=[round(float(v), 3) for v in size],
               edge_mean_iou=round(float(iou[read].mean()), 3), edge_key_iou=[round(v, 3) for v in key_iou])
    if not key_iou or float(np.mean(key_iou)) < MIN_KEY_IOU:
        fig["edge_reason"] = (f"a leaf hinged on its static edge does not explain the keyframes' masks (overlap "
                              f"{np.mean(key_iou) if key_iou else 0.0:.2f}, need {MIN_KEY_IOU}): no flat door or lid")
        return None, fig
    measured = read & (iou >= MIN_FRAME_IOU)  # a frame read by colour steers the path, never measures: an open door
    #                                          shows colours no keyframe taught, and its plain body reads as it closed
    d = unwrapped - unwrapped[int(np.argmax(measured))]
    span = float(np.ptp(d[measured])) if measured.any() else 0.0
    if span > np.pi:  # no door or lid turns further; the path went over to the leaf's mirror image somewhere
        fig["edge_reason"] = (f"its leaf turns {np.degrees(span):.0f} deg over the video, more than a door or lid can: "
                              f"its mirror image was followed (label a frame in each stretch where it rests)")
        return None, fig
    pos = {i: n for n, i in enumerate(every)}
    at = [pos.get(i) for i in frames]
    step = float(angles[1] - angles[0])
    ok = np.array([n is not None and bool(measured[n]) for n in at])
    return Fit("hinge", line.axis, line.p.copy(), np.array([d[n] if n is not None else 0.0 for n in at]), ok,
               np.full(len(frames), step), 1.0, {}), fig


def measure_outlines(route: str, motion: Any, kind_from: str, ds, obj: int, states: np.ndarray, known: np.ndarray,
                     labelled: np.ndarray, keys: list[int], min_pixels: int, trust_labels: bool,
                     confidence: np.ndarray | None, views: Views | None) -> tuple[Articulation | None, dict[str, Any]]:
    """A route that reads a part's masks against the known cameras (`motion(views, frames, keys, states, known)`
    -> (Fit or None, figures with `<route>_reason`)) over the frames the masks stage trusts, its fit oriented by
    the labels (`articulate`)."""
    views = views_of(ds, obj) if views is None else views
    frames = trusted_frames(views, keys, min_pixels, confidence)
    if not frames:
        return None, {f"{route}_reason": "the part shows in no frame", "route": route, "registered": 0}
    fit, fig = motion(views, frames, keys, states, known)
    fig["route"] = route
    if fit is None:
        return None, dict(fig, registered=0)
    fig.update(registered=int(fit.ok.sum()), kind_from=kind_from)
    at = np.array(frames)
    return articulate(fit, at, states[at], known[at], labelled[at], fig, trust_labels)


def measure_edge(ds, obj: int, states: np.ndarray, known: np.ndarray, labelled: np.ndarray, keys: list[int],
                 min_pixels: int = 400, trust_labels: bool = False, confidence: np.ndarray | None = None,
                 views: Views | None = None) -> tuple[Articulation | None, dict[str, Any]]:
    """Object `obj`'s hinge from its outlines and masks over the dataset `ds` (keys: dataset positions of the
    keyframes; confidence (N,): the masks stage's per-frame confidence, frames under `MIN_CONFIDENCE` left out but
    the keyframes; `views`: `views_of(ds, obj)` when the caller has it); (None, figures with `edge_reason`) when the
    route cannot measure it."""
    motion, fig = measure_outlines("edge", edge_motion, "the static edge of its outline", ds, obj, states, known,
                                   labelled, keys, min_pixels, trust_labels, confidence, views)
    if fig.get("accepted") and motion.range > np.pi:  # the labels scaled what it measured past what a door can turn
        fig.update(accepted=False, reason=f"its range comes to {np.degrees(motion.range):.0f} deg, more than a door or "
                                          f"lid turns: the measured angles or the labels that scale them are wrong")
    return motion, fig
