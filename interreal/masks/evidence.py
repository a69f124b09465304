"""What moves with each object between two frames, on the chains: its plane's homography (`_fit_plane`, RANSAC),
the motion evidence that takes out mask pixels that follow the background rather than their object
(`_motion_evidence`), the growth onto pixels that move with it and have its colours (`_grow`), the per-object rigid
warp (`_rigid`) and a GrabCut of each frame gated by the keyframe's colours (`_cut`).

`StepEvidence` is a part of `track.Propagator` (it reads the tracker's config, frame cache and Steps); kept here so
the chains and their fusion read apart from the evidence each step weighs.
"""

from __future__ import annotations

import cv2
import numpy as np

from .appearance import ColourModel, LocalColour, grabcut, lab_of
from .flow import Step
from .soft import chsum, disk

# A plane fit (RANSAC homography) whose inlier ratio is under MIN_INLIERS gets no weight (`_rigid`,
# `_motion_evidence`), so the motion evidence's fits need only find a model with that many inliers: 4-point
# samples, 99.5 % sure (OpenCV's default of 2000 iterations made its fits a fifth of the propagation time).
# `_rigid` keeps OpenCV's default: capping it too moved drift-straight's first-frame J by -0.015 (RANSAC luck).
MIN_INLIERS = 0.4
GROW_BAND = 0.01     # `_grow`'s band around an object per step, as a share of the work image's long side
GROW_COLOUR = 2.0    # ... and how much likelier a joining pixel's colour must be under the object than the background
# `_cut`'s trimap around each object, as shares of the work image's long side: a core eroded by CUT_CORE stays the
# object, a band dilated by CUT_BAND is what the cut may give or take; beyond it is background. A pixel changes
# label only where the keyframe's colours favour the new label by CUT_COLOUR (the same test as GROW_COLOUR).
CUT_CORE = 0.02
CUT_BAND = 0.05
CUT_COLOUR = 2.0
CUT_SIDE = 160       # ... and the cut runs on the window shrunk to this long side (px): 0.6 of its time at full size
RANSAC_ITERS = int(np.ceil(np.log(1 - 0.995) / np.log(1 - MIN_INLIERS ** 4)))


class StepEvidence:
    """The per-step evidence of `track.Propagator` (a mixin: `cfg`, `k`, `cache`, `step`, `_labels_of` are the
    tracker's)."""

    def _fit_plane(self, mask: np.ndarray, st: Step, rng: np.random.Generator, iters: int = RANSAC_ITERS
                   ) -> tuple[np.ndarray, float] | None:
        """Homography fit (RANSAC, 1 px, `iters` iterations) to the flow of an eroded region; with its inlier
        ratio, or None."""
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
        ys, xs = np.nonzero(cv2.erode(mask.astype(np.uint8), kernel))
        if len(xs) < 40:
            return None
        sel = rng.choice(len(xs), size=min(len(xs), 600), replace=False)
        src = np.stack([xs[sel], ys[sel]], 1).astype(np.float32)
        H, inl = cv2.findHomography(src, src + st.push[ys[sel], xs[sel]], cv2.RANSAC, 1.0, maxIters=iters)
        if H is None or not np.all(np.isfinite(H)):
            return None
        return H, float(inl.mean())

    def _plane_fits(self, soft: np.ndarray, st: Step) -> tuple[np.ndarray | None, list]:
        """The background's homography and each object's (None where a fit failed), with inlier ratios."""
        rng = np.random.default_rng(1)
        bg = self._fit_plane(soft[..., -1] > 0.5, st, rng)
        if bg is None:
            return None, []
        return bg, [self._fit_plane(soft[..., k] > 0.5, st, rng) for k in range(self.k)]

    def _moves_apart(self, t: int, prev: int, region: np.ndarray, remnant: np.ndarray) -> bool:
        """False when the flow of frame t shows `region` (work-size mask) moving with the background where the
        `remnant` of its object moves otherwise; True when it moves with the remnant, or nothing tells (the two
        motions agree there, or either fit is untrusted).

        Each motion is one homography fit to the flow from t back to prev (as `_plane_fits`, on this frame's
        pixels); a pixel of the region's new part counts for the one that predicts its flow better, where the two
        predict displacements more than one flow tolerance apart (`_residual2`'s units)."""
        st = self.step(t, prev)  # flow t -> prev, per pixel of frame t
        rng = np.random.default_rng(2)
        bg = self._fit_plane(~(region | remnant), st, rng)
        obj = self._fit_plane(remnant, st, rng)
        if bg is None or obj is None or _plane_weight(bg[1]) <= 0 or _plane_weight(obj[1]) <= 0:
            return True
        ys, xs = np.nonzero(region & ~remnant)
        if not len(xs):
            return True
        u, v = st.push[ys, xs, 0], st.push[ys, xs, 1]
        to_bg, to_obj = _project(bg[0], xs, ys), _project(obj[0], xs, ys)
        apart = ((to_bg - to_obj) ** 2).sum(-1) > self._tolerance2(u, v)
        if apart.mean() < 0.5:
            return True
        seen = np.stack([xs + u, ys + v], -1)  # where the flow takes each pixel
        with_bg = ((to_bg - seen) ** 2).sum(-1) < ((to_obj - seen) ** 2).sum(-1)
        return bool(with_bg[apart].mean() <= 0.5)

    def _tolerance2(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Squared consistency tolerance of displacements (u, v): FlowConfig abs_tol + rel_tol |flow|^2."""
        fc = self.cfg.flow
        return fc.abs_tol ** 2 + fc.rel_tol * (u * u + v * v)

    def _residual2(self, st: Step, H: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
        """Squared residual of the measured flow at pixels (ys, xs) of src under the homography H, in units of
        the flow's own consistency tolerance (FlowConfig: abs_tol + rel_tol |flow|^2)."""
        pu, pv = st.push[ys, xs, 0], st.push[ys, xs, 1]
        pred = _project(H, xs, ys)
        e2 = (pred[..., 0] - xs - pu) ** 2 + (pred[..., 1] - ys - pv) ** 2
        return e2 / self._tolerance2(pu, pv)

    def _motion_evidence(self, soft: np.ndarray, st: Step, fits, motion: float) -> np.ndarray:
        """Take out of each object the pixels whose own flow moves with the background rather than the object.

        Flow smears a moving object onto the background next to it, and a part of the mask that slid onto the
        background then travels with it for good (the parked scooters behind a passing one, the trees behind a
        jumping horse). The background's motion (one homography: the camera over the far scene) and each
        object's (one homography) predict every pixel's displacement; the residual of the measured flow under
        each (`_residual2`) gives a Gaussian likelihood, floored at three tolerances (beyond that neither model
        explains the pixel: a deforming limb stays neutral). Where the two motions agree the ratio is one: no
        evidence. The evidence only removes here; `_grow` adds, where colour agrees too. Each fit counts by its
        inlier ratio, as in `_rigid`.
        """
        bg, objects = fits
        floor = np.float32(np.exp(-0.5 * 9.0))
        out = soft.copy()
        for k, fit in enumerate(objects):
            if fit is None:
                continue
            a = motion * float(_plane_weight(fit[1]) * _plane_weight(bg[1]))
            ys, xs = np.nonzero(soft[..., k] > 1e-3)  # below that the object has nothing to lose
            if a <= 0 or not len(xs):
                continue
            y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
            by, bx = np.mgrid[y0:y1, x0:x1]
            ratio = np.minimum((np.exp(-0.5 * self._residual2(st, fit[0], by, bx)) + floor)
                               / (np.exp(-0.5 * self._residual2(st, bg[0], by, bx)) + floor), 1.0)
            out[y0:y1, x0:x1, k] *= ratio ** a if a != 1.0 else ratio
        out /= np.maximum(chsum(out), 1e-6)
        return out.astype(np.float32, copy=False)

    def _grow(self, soft: np.ndarray, st: Step, fits, model: ColourModel, bins: np.ndarray, grow: float,
              local: LocalColour | None = None, image: np.ndarray | None = None,
              known: np.ndarray | None = None) -> np.ndarray:
        """Add to each object the pixels next to it that move with it and have its colours.

        A part that turns into view (a car's rear as it rounds a bend, a drawer's side as it slides out) or an
        object that comes closer is new to every chain: flow carries only what the mask already holds, so
        without a second keyframe the mask keeps the object's first outline and shrinks against it (measured:
        0.7 of the true area after 40-75 frames on three DAVIS cars). A pixel in a thin band around the object
        joins it when its flow fits the object's homography clearly better than the background's (a quarter of
        the residual, and beyond three tolerances from the background's) and its colour is at least
        `GROW_COLOUR` times likelier under the object's keyframe histogram than the background's: motion alone
        would take a wake or a shadow, colour alone the background of the same colour. With `local` (the
        chain's `LocalColour`, at this frame) the colour test is the keyframe's colours near the pixel where both
        labels were there (`image`: this frame's work image), the histograms elsewhere. With `known` (between
        keyframes: the chain's trust times 'seen', per pixel) a pixel's share is scaled by what its keyframe did
        not tell: a pixel the keyframe labelled background keeps that label.
        """
        bg, objects = fits
        out = soft.copy()
        h, w = soft.shape[:2]
        r = max(1, round(GROW_BAND * max(h, w)))
        ring = disk(r)
        for k, fit in enumerate(objects):
            if fit is None or _plane_weight(fit[1]) * _plane_weight(bg[1]) <= 0:
                continue
            obj = (soft[..., k] > 0.5).astype(np.uint8)
            ys, xs = np.nonzero(cv2.dilate(obj, ring) > obj)
            if not len(xs):
                continue
            e_obj, e_bg = self._residual2(st, fit[0], ys, xs), self._residual2(st, bg[0], ys, xs)
            q = bins[ys, xs]
            colour = np.log(model.hist[k, q] / model.hist[-1, q])
            if local is not None:
                near = local.log_ratio(k, lab_of(image[ys, xs][:, None]).reshape(-1, 3), ys, xs)
                colour = np.where(np.isnan(near), colour, near)
            add = (e_bg > 9.0) & (e_obj < 0.25 * e_bg) & (colour > np.log(GROW_COLOUR))
            if add.any():
                ya, xa = ys[add], xs[add]
                share = np.full(len(ya), grow, np.float32) if known is None else \
                    (grow * (1.0 - known[ya, xa])).astype(np.float32)
                out[ya, xa] *= (1.0 - share)[:, None]
                out[ya, xa, k] += share
        return out

    def _rigid(self, soft: np.ndarray, st: Step, warped: np.ndarray, trust: np.ndarray):
        """Move each object as one plane (homography fit to its interior flow) where that explains the flow.

        Dense flow is smooth across boundaries, so per-pixel warping drags background along with a moving
        object and loses its leading edge; a rigid or planar part (a door, a drawer, a car side) is moved
        exactly by one homography, which keeps its outline. Blended by the fit's inlier ratio, so a
        deforming object falls back to per-pixel flow. Also returns each object's (K,) area scale under its
        homography (what of it stays in view, over what it was; 1 where no fit is trusted): `health` compares a
        mask's area with the area its object's own motion predicts.
        """
        h, w = trust.shape
        out = warped.copy()
        scale = np.ones(self.k)
        hs: list = [None] * self.k
        rng = np.random.default_rng(0)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
        for k in range(self.k):
            fit = self._fit_plane(soft[..., k] > 0.5, st, rng, iters=2000)  # OpenCV's default
            if fit is None:
                continue
            H, inlier_ratio = fit
            lam = self.cfg.rigid * _plane_weight(inlier_ratio)
            if lam <= 0:
                continue
            moved = cv2.warpPerspective(soft[..., k], H, (w, h), flags=cv2.INTER_LINEAR, borderValue=0)
            out[..., k] = lam * moved + (1 - lam) * warped[..., k]
            scale[k] = float(moved.sum()) / max(float(soft[..., k].sum()), 1e-6)
            hs[k] = H if lam >= 0.5 else None
            region = cv2.dilate(((moved > 0.05) | (warped[..., k] > 0.05)).astype(np.uint8), kernel, iterations=2) > 0
            trust = np.where(region, np.maximum(trust, lam), trust)
        objects = chsum(np.ascontiguousarray(out[..., :-1]))[..., 0]
        out[..., -1] = np.clip(1.0 - objects, 0.0, None)
        out /= np.maximum(chsum(out), 1e-6)
        return out, trust.astype(np.float32), scale, hs

    def _cut(self, soft: np.ndarray, image: np.ndarray, model: ColourModel, bins: np.ndarray) -> np.ndarray:
        """Let a GrabCut of this frame move each object's boundary where the keyframe's colours agree.

        Flow carries only what the mask already holds: a wheel or a rider's back that turns into view, or a
        limb that moves unlike the rest, stays outside it, and a sliver of background it took stays inside.
        GrabCut learns the object's and the background's colours on this very frame (lighting and pose as they
        are now) and finds the best boundary in a band around the mask. Its own colour models learn from the
        mask it is given and take a neighbour of the object's colours along, so what it changes is kept only
        where the keyframe's histograms (`model`, over this frame's colour `bins`) favour the new label by
        CUT_COLOUR (without that test, scooter-black's first-frame J fell from 0.79 to 0.62: the parked scooters
        beside the moving one are as black). The result is blended by `TrackConfig.cut`, so one bad cut is halved
        and the chain carries the rest. Runs on the chains before the first and after the last keyframe only:
        between keyframes fusion already corrects the boundary, and a cut there moved every-10 J by -0.05 to +0.05
        per sequence for nothing on the mean.
        """
        h, w = soft.shape[:2]
        band = max(2, round(CUT_BAND * max(h, w)))
        out = soft.copy()
        c = np.float32(self.cfg.cut)
        for k in range(self.k):
            obj = soft[..., k] > 0.5
            if obj.sum() < 30:  # nothing to cut around (a lost object is `redetect`'s)
                continue
            ys, xs = np.nonzero(obj)
            win = np.s_[max(ys.min() - 2 * band, 0):min(ys.max() + 2 * band + 1, h),
                        max(xs.min() - 2 * band, 0):min(xs.max() + 2 * band + 1, w)]
            others = np.delete(soft[win][..., :-1], k, axis=-1).max(-1) > 0.5 if self.k > 1 else None
            fg = _cut_window(image[win], obj[win], others, band, seed=k)
            q = bins[win]
            ratio = model.hist[k, q] / model.hist[-1, q]
            fg = np.where(obj[win], fg | (ratio >= 1 / CUT_COLOUR), fg & (ratio > CUT_COLOUR)).astype(np.float32)
            # the cut decides between this object and the background only: their joint share is redistributed,
            # other objects' probability is left as it is
            sub = out[win]
            pair = sub[..., k] + sub[..., -1]
            sub[..., k] = (1 - c) * sub[..., k] + c * fg * pair
            sub[..., -1] = pair - sub[..., k]
        out /= np.maximum(chsum(out), 1e-6)
        return out.astype(np.float32, copy=False)


def _cut_window(rgb: np.ndarray, obj: np.ndarray, others: np.ndarray | None, band: float, seed: int) -> np.ndarray:
    """(h, w) bool foreground of one GrabCut iteration around the mask `obj` in the window `rgb`.

    Its trimap: `obj` eroded by CUT_CORE / CUT_BAND of `band` is the object, `obj` is likely the object, `obj`
    dilated by `band` px likely background, the rest and `others` (other objects' pixels) background. All of it
    runs on the window shrunk to CUT_SIDE px (morphology and the cut), then the answer is scaled back; `seed`
    fixes GrabCut's k-means start (OpenCV's RNG), so a frame always cuts alike."""
    h, w = obj.shape
    f = min(1.0, CUT_SIDE / max(h, w))
    size = (max(1, round(w * f)), max(1, round(h * f)))
    small = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    m = cv2.resize(obj.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
    core, out = (max(1, round(r * f)) for r in (band * CUT_CORE / CUT_BAND, band))
    tri = np.full(m.shape, cv2.GC_BGD, np.uint8)
    tri[cv2.dilate(m, disk(out)) > 0] = cv2.GC_PR_BGD
    tri[m > 0] = cv2.GC_PR_FGD
    tri[cv2.erode(m, disk(core)) > 0] = cv2.GC_FGD
    if others is not None:
        tri[cv2.resize(others.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0] = cv2.GC_BGD
    fg = grabcut(small, tri, 1, seed) if (tri == cv2.GC_FGD).any() and (tri == cv2.GC_BGD).any() else None
    if fg is None:  # nothing sure on one side, or too few pixels to model its colours: the mask as it is
        return obj.copy()
    return cv2.resize(fg.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR) > 0.5


def _project(H: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """(..., 2) where the homography H takes the pixels (xs, ys) (arrays of one shape)."""
    pts = np.stack([xs, ys], -1).reshape(-1, 1, 2).astype(np.float32)
    return cv2.perspectiveTransform(pts, H).reshape(xs.shape + (2,))


def _plane_weight(inliers: float) -> float:
    """How far a plane fit is trusted: 0 at MIN_INLIERS of its points or fewer, 1 at twice that."""
    return float(np.clip((inliers - MIN_INLIERS) / MIN_INLIERS, 0.0, 1.0))
