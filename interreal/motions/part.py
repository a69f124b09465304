"""One part's motion by every route in turn: its own SfM, known-camera PnP, its silhouettes, its static edge, its
front pulled out (`measure_part`), from the part's masks (`part_masks`); `measure_object` is one object's whole
measurement, run in a worker process of its own when a scene has several parts (`motions.stage`).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np
from tqdm import tqdm

from .. import atomic
from ..conventions import IMAGES_DIR, opengl_to_opencv
from ..dataset import Articulation, load_dataset
from ..errors import DatasetError
from ..layout import KEYFRAMES_DIR, MOTIONS_DIR  # DS/motions/<object>/: the part reconstructions
from ..options import option
from ..report import read_report
from ..sfm import colmap
from ..sfm.colmap import NativeLog
from ..transients import excluded
from .fit import PartViews, fit_motion, part_point
from .known import known_camera_motion
from .pnp import pnp_views, reference_frames
from .edge import measure_edge, trusted_frames
from .prism import contested_slide, measure_prism
from .reach import frames_to_draw, guessed_ends, reach_hinge, unmeasured
from .silhouette import Views, measure_silhouettes, views_of

# MotionConfig.route: the route tried first; the others follow, in this order, while no motion is accepted
ROUTES = ("sfm", "pnp", "silhouette", "edge", "prism")
# the routes that read the part's masks against the known cameras: (progress label, measure)
OUTLINE_ROUTES = {"edge": ("static edge", measure_edge), "prism": ("front pulled out", measure_prism)}
POSE_ROUTES = ("sfm", "pnp")  # the routes that measure the part's pose, only in the frames they register: a hinge
#                               they give is carried by the masks past its measured angles (`reached`)
PNP_LONG_SIDE = 800  # the PnP route reads the images at most this large
DRAW_WHY = {  # why a person is asked to draw a part's mask on some frames (`draw_frames`), in the warning's words
    "end": "no route followed it to this end of its motion, so only the labels' guess scales it there",
    "decide": "where it moves a slide of its front and a leaf turning on its edge explain its masks alike: a drawn "
              "mask there decides",
    "confirm": "where it moves a leaf turning on its edge explains its masks better than a slide of its front, but "
               "not on every count: a drawn mask there confirms it"}
RESULT_FILE = "measured.json"  # DS/motions/object_<k>/: the part's finished measurement (`save_result`)




@dataclass
class MotionConfig:
    """Settings of one `interreal motions` run (they enter the resume fingerprint)."""

    erode: int = option(2, "px taken off each mask's border (features there may belong to the background)")
    min_pixels: int = option(400, "frames showing fewer part pixels are skipped")
    max_features: int = 2048
    overlap: int = 10  # sequential pairs (i, i+1..overlap, then i+2^k), plus every `key_every`-th frame exhaustively
    key_every: int = 4
    min_registered: int = 8  # fewer registered frames than this: no motion for the part (the k-axis alone moves it)
    min_known: int = 3  # frames with a known state among the registered ones
    seed: int = 0  # mapper attempt k uses seed + k
    attempts: int = 3  # mapper runs per part at most (a bent or flipped model of a planar part gives bad states)
    max_frames: int = 100  # frames of a part matched at most (evenly spread, labelled frames kept): time is bounded
    budget_s: float = 110.0  # another mapper attempt starts only before half of this has passed
    route: str = option("sfm", "the route tried first (the others when it gives no accepted motion): sfm (the "
                               "part's own SfM), pnp (known-camera PnP: seconds, needs a stretch where the part "
                               "rests), silhouette (its masks against the known cameras: for a plain part with "
                               "a flat front whose corners show) or edge (a plain door or lid cut by the image "
                               "border: the static edge of its keyframes' outlines as the hinge) or prism (a plain "
                               "drawer: its front at rest pulled out along its normal)", choices=ROUTES)
    trust_labels: bool = option(False, "let the state labels calibrate each motion and refuse it when most of them "
                                       "disagree (default: the geometry measures every frame's state, the labels "
                                       "only say which end is closed, and a label that disagrees is reported)")
    num_threads: int = -1
    workers: int = option(0, "parts measured at once, each in a process of its own (0: one per CPU core; 1: one "
                             "after another); the same answers either way")
    verbose: bool = option(False, "COLMAP's own log on the terminal")


# ----------------------------------------------------------------------------------------------------------------
# The part's own reconstruction
# ----------------------------------------------------------------------------------------------------------------
def transient_pixels(ds, frame, hw: tuple[int, int], cfg: MotionConfig) -> np.ndarray | None:
    """(H, W) bool pixels of `frame` no part reconstruction may use (the transient layer: hands, people), grown by
    the erosion: a hand on a lid moves with it and would be taken for the lid's texture. None when none."""
    return excluded(ds.root, frame.fid, hw, dilate=cfg.erode)


def spread(shown: list[int], keep: set[int], most: int) -> list[int]:
    """At most `most` of the positions `shown` (sorted), evenly spread over them, every one in `keep` included."""
    if len(shown) <= most:
        return shown
    pick = {shown[i] for i in np.linspace(0, len(shown) - 1, max(2, most - len(keep))).round().astype(int)}
    return sorted(pick | (keep & set(shown)))


class PartMasks(NamedTuple):
    """The frames a part's own reconstruction is matched on, and how many frames show the part at all."""

    names: list[str]  # image names, at most `MotionConfig.max_frames`
    shown: int  # frames whose mask holds `min_pixels` of the part: what the pose-free routes count against


def part_masks(ds, obj: int, out: Path, cfg: MotionConfig, keep: set[int] = frozenset(),
               exclude=transient_pixels) -> PartMasks:
    """COLMAP masks (<image name>.png, 255 = use) of object `obj`'s eroded pixels less `exclude(ds, frame, hw,
    cfg)` (None: nothing excluded); the image names that show it, at most `cfg.max_frames` of them (dataset
    positions in `keep`, the labelled frames, always among them), and the count of frames that show it at all
    (a measured count is reported against it: the cap must not read as fewer frames than were measured)."""
    out.mkdir(parents=True, exist_ok=True)
    kernel = np.ones((2 * cfg.erode + 1,) * 2, np.uint8)
    shown: dict[int, np.ndarray] = {}
    seen = 0
    for i, f in enumerate(ds.frames):
        m = ds.load_mask(f)[..., obj].astype(np.uint8) * 255
        seen += int(np.count_nonzero(m)) >= cfg.min_pixels
        if cfg.erode:
            m = cv2.erode(m, kernel)
        gone = exclude(ds, f, m.shape, cfg) if exclude is not None else None
        if gone is not None:
            m[gone] = 0
        if int((m > 0).sum()) >= cfg.min_pixels:
            shown[i] = m
    names = []
    for i in spread(sorted(shown), set(keep), cfg.max_frames):
        name = Path(ds.frames[i].file_path).name
        atomic.write_image(out / f"{name}.png", shown[i])
        names.append(name)
    return PartMasks(names, seen)  # every frame kept shows the part: seen >= len(names)


def part_pairs(n: int, overlap: int, key_every: int) -> list[tuple[int, int]]:
    """Sequential pairs (quadratic beyond `overlap`) and every `key_every`-th frame against each other: the part is
    seen again after it moved away and back (a door closed, opened, closed) with frames in between."""
    pairs = set()
    for i in range(n):
        steps = list(range(1, overlap + 1)) + [2 ** k for k in range(4, 12) if 2 ** k > overlap]
        pairs |= {(i, i + d) for d in steps if i + d < n}
    keys = list(range(0, n, max(1, key_every)))
    pairs |= {(a, b) for ia, a in enumerate(keys) for b in keys[ia + 1:]}
    return sorted(pairs)


def match_part(pc, ds, names: list[str], mask_dir: Path, work: Path, cfg: MotionConfig) -> Path:
    """work/database.db with the masked part's features and verified matches (the dataset's intrinsics)."""
    intr = ds.intrinsics
    db = work / "database.db"
    db.unlink(missing_ok=True)
    params = ",".join(f"{v:.9g}" for v in (intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.k1, intr.k2, intr.p1, intr.p2))
    ex = colmap.Extraction("OPENCV", 4096, cfg.max_features, camera_params=params, num_threads=cfg.num_threads)
    # first octave -1: on small regions the upsampled octave finds several times the features
    colmap.extract_cropped(pc, db, (ds.root / IMAGES_DIR).resolve(), names, ex, mask_dir, first_octave=-1)
    colmap.match_pairs(pc, db, names, part_pairs(len(names), cfg.overlap, cfg.key_every), work / "pairs.txt",
                       cfg.seed, cfg.num_threads, chunk=None)
    return db


def map_part(pc, ds, db: Path, out: Path, cfg: MotionConfig, seed: int):
    """The largest pycolmap model of the matched part, the dataset's intrinsics held fixed (None when none).
    A part is often nearly planar (a drawer's front): which model the mapper settles on depends on its seed."""
    opt = colmap.incremental_options(pc, cfg.num_threads, seed, fixed_intrinsics=True)
    colmap.fresh_model_dir(pc, out, seed)
    models = colmap.incremental_map(pc, db, (ds.root / IMAGES_DIR).resolve(), out, opt)
    if not models:
        return None
    return max(models.values(), key=lambda r: r.num_reg_images())


def part_views(rec, ds) -> PartViews:
    """A part reconstruction's registered frames related to their world cameras (OpenCV axes inside). The point
    followed is the middle of the part's own points (`part_point`), not the reconstruction's origin."""
    by_name = {Path(f.file_path).name: i for i, f in enumerate(ds.frames)}
    point = part_point(np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3))
    frames, rot, u, centre, cam_rot = [], [], [], [], []
    for im in rec.images.values():
        if not im.has_pose or im.name not in by_name:
            continue
        i = by_name[im.name]
        w2c_part = np.asarray(im.cam_from_world().matrix())  # 3x4, reconstruction units
        c2w = opengl_to_opencv(ds.frames[i].c2w)
        frames.append(i)
        rot.append(c2w[:3, :3] @ w2c_part[:, :3])
        u.append(c2w[:3, :3] @ (w2c_part[:, :3] @ point + w2c_part[:, 3]))
        centre.append(c2w[:3, 3])
        cam_rot.append(c2w[:3, :3])
    order = np.argsort(frames)
    return PartViews(np.asarray(frames)[order], np.asarray(rot)[order], np.asarray(u)[order],
                     np.asarray(centre)[order], np.asarray(cam_rot)[order])


# ----------------------------------------------------------------------------------------------------------------
# Measuring a part
# ----------------------------------------------------------------------------------------------------------------
def _better(fig: dict[str, Any], best: dict[str, Any]) -> bool:
    """An accepted fit beats a refused one; then the one whose labels agree best."""
    def key(f: dict[str, Any]) -> tuple[bool, float]:
        return bool(f.get("accepted")), -float(f.get("label_median_error", float("inf")))

    return key(fig) > key(best)


def measure_part(pc, ds, names: list[str], part: Path, states: np.ndarray, known: np.ndarray,
                 cfg: MotionConfig, step: Any = None, labelled: np.ndarray | None = None, obj: int | None = None,
                 routes: tuple[str, ...] | None = None) -> tuple[Articulation | None, dict[str, Any]]:
    """The part's motion; states, known (N,) over the dataset's frames, `labelled` (N,) the frames a person
    labelled (default `known`). Two routes to the part's per-frame poses, the same geometric fit after either
    (`fit.fit_motion`: the geometry decides and measures, the labels orient):
    - pnp (`measure_part_pnp`): the part triangulated at rest with the known cameras, located by PnP in every frame
      (seconds; needs some texture and a stretch where the part rests);
    - sfm: the part's own reconstruction, mapped with up to `cfg.attempts` seeds on the same matches until a motion
      is accepted (a nearly planar part sometimes comes out bent or with a flipped view); another attempt starts
      only before half of `cfg.budget_s` has passed; its tracks posed by the known cameras (`posed_fit`);
    - silhouette (`motions.silhouette`, needs `obj`, the object's index): its masks against the known
      cameras, for a part too plain for either (seconds);
    - edge (`motions.edge`, needs `obj`): a plain door or lid whose corners no view shows: the static edge of its
      keyframes' outlines as the hinge, the leaf fitted to every mask (tens of seconds);
    - prism (`motions.prism`, needs `obj`): a plain drawer: its front at rest on such an edge pulled out along its
      normal, refused where a leaf turning on the edge explains the masks as well (up to a minute).
    `cfg.route` is tried first, the others in `ROUTES` order while none gives an accepted motion (`routes`: only
    these, in this order; a benchmark measures each alone). The best fit is returned (None when no
    route registered enough frames with a known state).
    step(text): called as each phase starts (a progress bar)."""
    step = step or (lambda text: None)
    labelled = known if labelled is None else labelled
    start = time.monotonic()
    best: tuple[Articulation | None, dict[str, Any]] = (None, {"registered": 0})
    order = list(routes) if routes else [cfg.route] + [r for r in ROUTES if r != cfg.route]
    tried: dict[str, dict[str, Any]] = {}
    attempts = 0
    views: Views | None = None  # the part's masks, cameras and occluders, read once for the pose-free routes
    edge_fig: dict[str, Any] = {}  # the edge route's figures: its leaf against a slide (the prism route heeds it),
    #                                and the frames a drawn mask would decide between them on (`edge_decide`),
    #                                or confirm its leaf on (`edge_confirm`)
    for route in order:
        if best[0] is not None and best[1]["accepted"]:
            break
        t0 = time.monotonic()
        if route == "pnp":
            step("known-camera PnP")
            motion, fig = measure_part_pnp(ds, names, part / "masks", states, known, labelled, cfg)
        elif route == "silhouette":
            if obj is None:
                continue
            step("silhouettes")
            views = views_of(ds, obj) if views is None else views
            motion, fig = measure_silhouettes(ds, obj, states, known, labelled, cfg.min_pixels, cfg.trust_labels,
                                              views)
        elif route in OUTLINE_ROUTES:
            if obj is None:
                continue
            label, measure = OUTLINE_ROUTES[route]
            step(label)
            views = views_of(ds, obj) if views is None else views
            motion, fig = measure(ds, obj, states, known, labelled, keyframe_positions(ds), cfg.min_pixels,
                                  cfg.trust_labels, mask_confidence(ds, obj), views)
        else:
            motion, fig = _measure_part_sfm(pc, ds, names, part, states, known, labelled, cfg, step, start)
        fig.setdefault("route", route)
        edge_fig = fig if route == "edge" else edge_fig
        if route == "prism" and fig.get("accepted") and (why := contested_slide(edge_fig)):
            fig.update(accepted=False, reason=why)
        tried[route] = {"registered": fig.get("registered", 0), "kind": None if motion is None else motion.kind,
                        "accepted": bool(fig.get("accepted")),
                        "reason": fig.get("reason") or fig.get(f"{route}_reason")
                        or ("" if fig.get("accepted") else "gave no motion (no reason recorded)"),
                        "seconds": round(time.monotonic() - t0, 1)}
        if route == "sfm":
            attempts = fig.get("attempts", 0)
        if motion is not None and (best[0] is None or _better(fig, best[1])):
            best = (motion, fig)
        elif best[0] is None:
            best[1]["registered"] = max(best[1]["registered"], fig.get("registered", 0))
    if obj is not None and best[0] is not None and best[1]["accepted"] and best[0].kind == "hinge" \
            and best[1]["route"] in POSE_ROUTES and unmeasured(best[1]):  # the masks are read only then
        step("the masks past its measured angles")
        views = views_of(ds, obj) if views is None else views
        best = reached(views, best, ds, obj, states, known, labelled, cfg)
    # where an end is the labels' guess, the frames a person is asked to draw (the reports are read only then)
    if obj is not None and best[0] is not None and guessed_ends(best[1]):
        best[1]["draw_frames"] = frames_to_draw(best[1], len(ds.frames), keyframe_positions(ds),
                                                suggested_positions(ds))
        best[1]["draw_why"] = DRAW_WHY["end"]
    elif edge_fig.get("edge_decide") and not (best[0] is not None and best[1]["accepted"]):
        best[1].update(draw_frames=edge_fig["edge_decide"], draw_why=DRAW_WHY["decide"])
    elif edge_fig.get("edge_confirm") and best[1] is edge_fig and best[1]["accepted"]:
        best[1].update(draw_frames=edge_fig["edge_confirm"], draw_why=DRAW_WHY["confirm"])
    best[1]["attempts"] = attempts  # the reconstructions tried, whichever route's figures these are
    best[1]["routes"] = tried
    best[1].update({f"{r}_registered": v["registered"] for r, v in tried.items()})
    best[1]["seconds"] = round(time.monotonic() - start, 1)
    return best


def reached(views: Views, best: tuple[Articulation, dict[str, Any]], ds, obj: int, states: np.ndarray,
            known: np.ndarray, labelled: np.ndarray, cfg: MotionConfig) -> tuple[Articulation, dict[str, Any]]:
    """A hinge measured from poses carried by the part's masks into the frames past its measured angles
    (`reach.reach_hinge`) where an end of it is not one the route measured and a label confirms (`reach.unmeasured`;
    `measure_part` reads the masks only then), and that is accepted; else as it was, with why not. Why only there:
    where the route measured both ends, its poses read them better than a rectangle fitted to masks."""
    if not unmeasured(best[1]):
        return best
    keys = keyframe_positions(ds)
    frames = trusted_frames(views, keys, cfg.min_pixels, mask_confidence(ds, obj))
    motion, fig = reach_hinge(views, best[0], best[1], frames, keys, states, known, labelled, cfg.trust_labels)
    if motion is not None and fig.get("accepted"):
        return motion, fig
    why = fig.get("reach_reason") or f"refused: {fig.get('reason')}"
    return best[0], {**best[1], **{k: v for k, v in fig.items() if k.startswith("reach_")}, "reach_reason": why}


def keyframe_positions(ds) -> list[int]:
    """Dataset positions of the frames whose masks a person drew (the masks stage's keyframes; the annotate app's
    `keyframes/` when that report is absent): the exact outlines the edge route lifts its hinge from."""
    fids = [f.fid for f in ds.frames]
    listed = ((read_report(ds.root, "masks") or {}).get("inputs") or {}).get("keyframes") or {}
    if not listed and (ds.root / KEYFRAMES_DIR).is_dir():
        listed = {p.stem: p.name for p in (ds.root / KEYFRAMES_DIR).iterdir() if p.suffix in (".png", ".json")}
    at = {fid: i for i, fid in enumerate(fids)}
    return sorted(at[k] for k in listed if k in at)


def suggested_positions(ds) -> list[int]:
    """Dataset positions of the frames the masks stage asks a person to draw next (its report), its order kept."""
    fids = ((read_report(ds.root, "masks") or {}).get("figures") or {}).get("suggested_frames") or []
    at = {f.fid: i for i, f in enumerate(ds.frames)}
    return [at[f] for f in fids if isinstance(f, str) and f in at]


def mask_confidence(ds, obj: int) -> np.ndarray | None:
    """(N,) the masks stage's confidence in object `obj`'s mask on each frame (its report), None without one."""
    conf = (((read_report(ds.root, "masks") or {}).get("figures") or {}).get("confidence") or {})
    per = conf.get(ds.object_names[obj]) if isinstance(conf, dict) else None
    if not isinstance(per, dict):
        return None
    return np.array([float(per.get(f.fid, 1.0)) for f in ds.frames])


def _measure_part_sfm(pc, ds, names: list[str], part: Path, states: np.ndarray, known: np.ndarray,
                      labelled: np.ndarray, cfg: MotionConfig, step: Any, start: float
                      ) -> tuple[Articulation | None, dict[str, Any]]:
    """The part's own reconstruction, up to `cfg.attempts` mapper seeds while the budget allows."""
    best: tuple[Articulation | None, dict[str, Any]] = (None, {"registered": 0})
    if cfg.attempts < 1:
        return None, {"registered": 0, "attempts": 0, "reason": "no reconstruction attempted (attempts 0)"}
    step("matching")
    db = match_part(pc, ds, names, part / "masks", part, cfg)
    a, most_known = 0, 0
    for a in range(cfg.attempts):
        if a and time.monotonic() - start > cfg.budget_s / 2:
            best[1]["stopped"] = f"time: {time.monotonic() - start:.0f} s of a {cfg.budget_s:.0f} s budget"
            a -= 1
            break
        step(f"reconstruction {a + 1}/{cfg.attempts}")
        rec = map_part(pc, ds, db, part / "sparse" / str(a), cfg, cfg.seed + a)
        pv = part_views(rec, ds) if rec is not None else None
        if pv is None or len(pv.frames) < cfg.min_registered or int(known[pv.frames].sum()) < cfg.min_known:
            if best[0] is None and pv is not None:  # what the warning reports: the most any attempt registered
                best[1]["registered"] = max(len(pv.frames), best[1]["registered"])
                most_known = max(most_known, int(known[pv.frames].sum()))
            continue
        motion, fig = posed_fit(rec, ds, pv, states, known, labelled, cfg)
        fig["attempt"], fig["route"] = a, "sfm"
        if best[0] is None or _better(fig, best[1]):
            best = (motion, fig)
        if fig["accepted"]:
            break
    best[1]["attempts"] = a + 1
    if best[0] is None:
        best[1]["reason"] = (f"its own reconstruction registered at most {best[1]['registered']} of the {len(names)} "
                             f"frames matched, {most_known} of them at a known state (need {cfg.min_registered} "
                             f"and {cfg.min_known}), over {a + 1} attempt(s)"
                             + (f"; stopped by {best[1]['stopped']}" if best[1].get("stopped") else ""))
    return best


def posed_fit(rec, ds, pv: PartViews, states: np.ndarray, known: np.ndarray, labelled: np.ndarray,
              cfg: MotionConfig) -> tuple[Articulation, dict[str, Any]]:
    """The motion of one reconstruction from its own poses; where those are refused (a small flat part's
    reconstruction turning with the camera, a bent one), or give a slide, its tracks posed by the known cameras
    (`known.known_camera_motion`) when that locates enough frames and is accepted (a slide only as a slide). Why a
    slide: its length is in the scene's units, which its own reconstruction reaches only through the scale that fits
    its positions to the cameras', while the known cameras triangulate its points in those units. A hinge's angle
    needs no scale, and on the real laptop video the lid's own motion is the nearer to the careful reference."""
    own = fit_motion(pv, states[pv.frames], known[pv.frames], labelled[pv.frames], cfg.trust_labels)
    if own[1]["accepted"] and own[0].kind != "slide":
        return own[0], dict(own[1], poses_from="its own reconstruction")
    motion, fig = known_camera_motion(rec, ds, states, known, labelled, cfg.trust_labels)
    enough = (motion is not None and fig["registered"] >= cfg.min_registered
              and fig["at_known_state"] >= cfg.min_known)
    if enough and fig["accepted"] and (not own[1]["accepted"] or motion.kind == own[0].kind):
        return motion, fig
    why = (fig.get("known_reason") or f"located {fig.get('known_located', 0)} frames" if not enough
           else f"a {motion.kind}, not the slide its own poses give" if fig["accepted"]
           else f"refused: {fig['reason']}")
    return own[0], dict(own[1], poses_from="its own reconstruction", known_cameras=why)


def measure_part_pnp(ds, names: list[str], mask_dir: Path, states: np.ndarray, known: np.ndarray,
                     labelled: np.ndarray, cfg: MotionConfig) -> tuple[Articulation | None, dict[str, Any]]:
    """The other route (`motions.pnp`): the part triangulated at rest with the known cameras, then
    located in every frame by PnP; the same geometric fit. (None, figures) when it cannot locate enough frames."""
    by_name = {Path(f.file_path).name: i for i, f in enumerate(ds.frames)}
    positions = sorted(by_name[n] for n in names)
    intr = ds.intrinsics
    f = min(1.0, PNP_LONG_SIDE / max(intr.w, intr.h))  # SIFT at <= this size: seconds, not minutes
    size = (int(round(intr.w * f)), int(round(intr.h * f)))
    k = intr.scaled(*size).K()
    grays, masks, c2w = {}, {}, {}
    for i in positions:
        name = Path(ds.frames[i].file_path).name
        grays[i] = cv2.resize(cv2.imread(str(ds.root / IMAGES_DIR / name), cv2.IMREAD_GRAYSCALE), size,
                              interpolation=cv2.INTER_AREA)
        masks[i] = cv2.resize(cv2.imread(str(mask_dir / f"{name}.png"), cv2.IMREAD_GRAYSCALE), size,
                              interpolation=cv2.INTER_NEAREST) > 0
        c2w[i] = opengl_to_opencv(ds.frames[i].c2w)
    refs = reference_frames(positions, states, known, labelled)
    pv, fig = pnp_views(grays, masks, c2w, k, intr.dist(), refs, most=min(cfg.max_features, 1500))
    if pv is None or len(pv.frames) < cfg.min_registered or int(known[pv.frames].sum()) < cfg.min_known:
        n, n_known = (0, 0) if pv is None else (len(pv.frames), int(known[pv.frames].sum()))
        reason = (f"located {n} of the {len(names)} frames matched, {n_known} at a known state (need "
                  f"{cfg.min_registered} and {cfg.min_known}), from {fig.get('points', 0)} points triangulated where "
                  f"it rests")
        return None, dict(fig, registered=n, reason=reason)
    motion, out = fit_motion(pv, states[pv.frames], known[pv.frames], labelled[pv.frames], cfg.trust_labels)
    out.update({k: v for k, v in fig.items() if k not in out})
    return motion, out


class ObjectResult(NamedTuple):
    """One object's measurement, as the stage reports it."""

    matched: int  # frames its own reconstruction was matched on (fewer than `min_registered`: nothing measured)
    shown: int  # frames that show it
    motion: Articulation | None
    fig: dict[str, Any] | None  # `measure_part`'s figures; None when too few frames show it to try
    reused: bool = False  # read back from an interrupted run with the same inputs and settings (`saved_result`)


def part_dir(root: Path, o: int) -> Path:
    """DS/motions/object_<o>/: object `o`'s masks, reconstructions, log and finished measurement."""
    return Path(root) / MOTIONS_DIR / f"object_{o}"


def save_result(part: Path, key: str, name: str, result: ObjectResult) -> None:
    """The part's finished measurement beside its work (atomic), for a run the stage did not finish: a Ctrl-C
    or a failure in another part costs only the parts not yet measured."""
    motion = None if result.motion is None else result.motion.to_json()
    atomic.write_json(part / RESULT_FILE, {"key": key, "object": name, "matched": result.matched,
                                           "shown": result.shown, "motion": motion, "fig": result.fig})


def saved_result(part: Path, key: str, name: str) -> ObjectResult | None:
    """`save_result`'s measurement when it was made with the resume key `key` for this object, else None (an
    unreadable file is measured again)."""
    try:
        saved = json.loads((part / RESULT_FILE).read_text())
        if saved.get("key") != key or saved.get("object") != name:
            return None
        motion = None if saved["motion"] is None else Articulation.from_json(saved["motion"], str(part / RESULT_FILE))
        return ObjectResult(int(saved["matched"]), int(saved["shown"]), motion, saved["fig"], reused=True)
    except (OSError, ValueError, KeyError, TypeError, DatasetError):
        return None


def measure_object(ds, o: int, cfg: MotionConfig, states: np.ndarray, known: np.ndarray, labelled: np.ndarray,
                   position: int = 0, key: str | None = None) -> ObjectResult:
    """Object `o`'s masks and motion; states, known, labelled (N,) its column of the dataset's. Its progress bar
    is on the terminal's row `position` (parts measured at once each keep a row of their own). With the stage's
    resume `key` the result is saved (`save_result`) as soon as the part is done."""
    part = part_dir(ds.root, o)
    result = _measured(ds, o, part, cfg, states, known, labelled, position)
    if key is not None:
        save_result(part, key, ds.object_names[o], result)
    return result


def _measured(ds, o: int, part: Path, cfg: MotionConfig, states: np.ndarray, known: np.ndarray,
              labelled: np.ndarray, position: int) -> ObjectResult:
    names, shown = part_masks(ds, o, part / "masks", cfg, keep=set(np.flatnonzero(labelled).tolist()))
    if len(names) < cfg.min_registered:
        return ObjectResult(len(names), shown, None, None)
    with NativeLog(part / "colmap.log", cfg.verbose) as log:
        # on the terminal even while COLMAP's log (fd 2) goes to the file: a part takes minutes
        with tqdm(total=4 + cfg.attempts, desc=f"motions '{ds.object_names[o]}'", file=log.term, leave=False,
                  unit="phase", position=position) as bar:
            def step(text: str) -> None:
                if text != "matching":
                    bar.update(1)
                bar.set_postfix_str(text)

            motion, fig = measure_part(colmap.load_pycolmap(cfg.verbose), ds, names, part, states, known, cfg, step,
                                       labelled=labelled, obj=o)
    return ObjectResult(len(names), shown, motion, fig)


def measure_object_at(ds_path: Path, o: int, cfg: MotionConfig, states: np.ndarray, known: np.ndarray,
                      labelled: np.ndarray, position: int, key: str | None = None) -> ObjectResult:
    """`measure_object` in a worker process: the dataset is read there (and the result saved there, whichever
    part the stage is waiting for)."""
    return measure_object(load_dataset(ds_path), o, cfg, states, known, labelled, position, key)
