"""`interreal motions DS`: how each object moves with its state, measured from the video -> DS/articulation.json.

A rigid part's pose in the world at every frame, whether it was still or moving, comes from its own pixels (its
masks, eroded, with the transient layer's hands and people taken out) by one of two routes (a third, for a part too
plain for both, needs no pose: see the end):
- its own SfM (default first): the part's pixels alone reconstructed with pycolmap, as if it were a scene of its
  own; every frame that reconstruction registers gives the camera relative to the part, and with the camera's pose
  in the world (transforms.json), the part's pose;
- known-camera PnP (`motions.pnp`, the fallback, or first with `--route pnp`): the part triangulated once
  where it rests, with the known cameras, and located in every frame by PnP (seconds, but it needs a stretch where
  the part rests while the camera moves; its reference is the window that triangulates most points, which can be
  one where the part moved slowly).
When neither gives an accepted motion, the part's silhouettes against the known cameras (`motions.silhouette`:
its flat front triangulated from its masks' corners, then the hinge or slide whose predicted silhouettes fit the
masks) measure every frame's displacement directly, and for a plain door cut by the image border, the one straight
edge of its outline that stays put is its hinge (`motions.edge`); for a plain drawer, its front at rest on one
of those edges, pulled out along its normal, each frame's pull from its mask (`motions.prism`).
`motions.fit` turns those poses into a hinge or a slide decided by the geometry (does the part turn about
one axis, or translate along one line?), measures every registered frame's state from its displacement, and uses
the labels only to fix the ends and the direction; labels that disagree with the geometry are named as likely
mistakes. Time is bounded: at most `max_frames` frames of a part are used, and another mapper seed is tried only
when the first model is refused and time is left (`budget_s`).
The trainer (`livescene`, `model.motion`) then reads each part's samples in its rest frame (its pose at state 0).
Conventions of the file: `interreal.conventions` / `interreal.dataset.Articulation`.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np
from tqdm import tqdm

from .. import atomic, provenance
from ..conventions import ARTICULATION_FILE, IMAGES_DIR, opengl_to_opencv
from ..dataset import Articulation, known_states, load_dataset, write_articulation
from ..errors import InputError
from ..layout import KEYFRAMES_DIR, MOTIONS_DIR  # DS/motions/<object>/: the part reconstructions
from ..options import add_flags, config_from, option, values_from_args
from ..report import StageReport, finished_with, fingerprint, read_report, warning_lines
from ..sfm import colmap
from ..sfm.colmap import NativeLog
from ..transients import excluded
from .fit import FLAG_TOL, LABELS_LINE, UNLABELLED_END, PartViews, fit_motion, part_point
from .pnp import pnp_views, reference_frames
from .edge import measure_edge
from .prism import measure_prism
from .silhouette import Views, measure_silhouettes, views_of

# MotionConfig.route: the route tried first; the others follow, in this order, while no motion is accepted
ROUTES = ("sfm", "pnp", "silhouette", "edge", "prism")
# the routes that read the part's masks against the known cameras: (progress label, measure)
OUTLINE_ROUTES = {"edge": ("static edge", measure_edge), "prism": ("front pulled out", measure_prism)}
PNP_LONG_SIDE = 800  # the PnP route reads the images at most this large
MAX_STATE_RMSE = 0.1  # an accepted motion's labels within this RMSE: no retry with another mapper seed
__all__ = ["PartViews", "fit_motion", "estimate_motions", "measure_part", "MotionConfig"]


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
    return PartMasks(names, max(seen, len(names)))


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
    colmap.extract_features(pc, db, (ds.root / IMAGES_DIR).resolve(), [(-1, names)], ex, mask_dir, chunk=None)
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
def disagreement_text(check: list[list], fids: list[str], most: int = 5) -> str:
    """'measured states -0.05..1.12; labels that disagree most: 00042 (label 1.00, measured 0.62), ...'"""
    if not check:
        return "no labelled frame was measured"
    measured = [m for _, _, m in check]
    worst = sorted(check, key=lambda r: -abs(r[2] - r[1]))
    off = [r for r in worst if abs(r[2] - r[1]) > FLAG_TOL][:most]
    return (f"measured states {min(measured):.2f} to {max(measured):.2f} on {len(check)} labelled frames; "
            + ("labels off by more than " + f"{FLAG_TOL} (likely mistakes): " + ", ".join(
                f"{fids[f]} (label {lab:.2f}, measured {m:.2f})" for f, lab, m in off) if off
               else "no single label is off by more than " + f"{FLAG_TOL}"))


def routes_text(fig: dict[str, Any]) -> str:
    """'; the other routes: pnp: <why not>; ...' for the routes tried besides the one whose motion is reported."""
    used = fig.get("route")
    said = [f"{r}: {v.get('reason') or ('refused' if v.get('kind') else 'no motion')}"
            for r, v in fig.get("routes", {}).items() if r != used]
    return f"; the other routes: {'; '.join(said)}" if said else ""


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
      only before half of `cfg.budget_s` has passed;
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
    best[1]["attempts"] = attempts  # the reconstructions tried, whichever route's figures these are
    best[1]["routes"] = tried
    best[1].update({f"{r}_registered": v["registered"] for r, v in tried.items()})
    best[1]["seconds"] = round(time.monotonic() - start, 1)
    return best


def ends_warnings(name: str, fig: dict[str, Any]) -> list[tuple[str, str]]:
    """(text, cause) for each end of a used motion whose state the geometry alone did not give: an end with no
    label near it (taken as 0 or 1), and an end the labels' line placed short of it, where no route measured the
    part further: its range is then the labels' guess, so the person hears which labels to check."""
    ends = fig.get("ends_from", "")
    out = []
    if UNLABELLED_END in ends:
        out.append((f"'{name}': {ends}: label a frame at each end to be sure", "ends-from-geometry"))
    if LABELS_LINE in ends:
        out.append((f"'{name}': no route measured it further than the frames labelled there, so its range comes from "
                    f"the labels ({ends}): check the labels near that end, or film the part at its ends where it can "
                    f"be seen", "ends-from-labels"))
    return out


def keyframe_positions(ds) -> list[int]:
    """Dataset positions of the frames whose masks a person drew (the masks stage's keyframes; the annotate app's
    `keyframes/` when that report is absent): the exact outlines the edge route lifts its hinge from."""
    fids = [f.fid for f in ds.frames]
    listed = ((read_report(ds.root, "masks") or {}).get("inputs") or {}).get("keyframes") or {}
    if not listed and (ds.root / KEYFRAMES_DIR).is_dir():
        listed = {p.stem: p.name for p in (ds.root / KEYFRAMES_DIR).iterdir() if p.suffix in (".png", ".json")}
    at = {fid: i for i, fid in enumerate(fids)}
    return sorted(at[k] for k in listed if k in at)


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
        motion, fig = fit_motion(pv, states[pv.frames], known[pv.frames], labelled[pv.frames], cfg.trust_labels)
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


def frame_state_rows(fig: dict[str, Any], fids: list[str], labels: np.ndarray, given: np.ndarray) -> list[list]:
    """[[frame id, measured state, label or None, likely mistake], ...] over the registered frames: each frame's
    measured state next to its label, for the report and the annotate app."""
    flagged = {f for f, _, _ in fig.get("flagged_labels", [])}
    return [[fids[f], m, round(float(labels[f]), 3) if given[f] else None, f in flagged]
            for f, m in fig.get("frame_states", [])]


def _flag_rows(fig: dict[str, Any], fids: list[str]) -> list[list]:
    """[[frame id, label, measured state], ...] of the labels the fit named as likely mistakes."""
    return [[fids[f], lab, m] for f, lab, m in fig.get("flagged_labels", [])]


def flagged_labels(root: str | Path) -> list[dict[str, Any]]:
    """The labels the last `interreal motions` run named as likely mistakes: [{fid, object, label, measured}]
    (what the annotate app lists next to its suggested frames; [] without a report)."""
    out = []
    for w in (read_report(root, "motions") or {}).get("warnings", []):
        if isinstance(w, dict) and isinstance(w.get("flagged"), list):
            for row in w["flagged"]:
                if isinstance(row, list) and len(row) == 3:
                    out.append({"fid": str(row[0]), "object": str(w.get("object", "")), "label": row[1],
                                "measured": row[2]})
    return out


# ----------------------------------------------------------------------------------------------------------------
# The stage
# ----------------------------------------------------------------------------------------------------------------
def estimate_motions(ds_path: str | Path, force: bool = False, **opts: Any) -> dict[str, Any]:
    """Measure every object's motion and write DS/articulation.json and reports/motions.json; returns the figures.
    A finished run from the same masks, poses, labels and settings is reused unless `force`.

    An object the reconstruction cannot follow (too few registered frames, or too few of them with a known state)
    gets no motion and a warning: the trainer then moves it with the k-axis alone, as the paper does."""
    ds_path = Path(ds_path)
    cfg = config_from(MotionConfig, opts, "motion")
    if cfg.route not in ROUTES:
        raise InputError(f"--route {cfg.route!r} is not one of {', '.join(ROUTES)}")
    fps = provenance.fingerprints(ds_path, provenance.MOTION_INPUTS)  # before anything is read
    ds = load_dataset(ds_path)
    if not ds.n_objects:
        raise InputError(f"{ds_path} has no objects (mapping.yaml): nothing moves")
    if not ds.has_masks():
        raise InputError(f"{ds_path} has no masks for every frame: run `interreal masks {ds_path} --keyframes DIR`")
    if ds.intrinsics is None:
        raise InputError(f"{ds_path}: transforms.json has no shared intrinsics (per-frame cameras are not supported)")
    labels, given = ds.label_matrix()
    if not given.any():
        raise InputError(f"{ds_path} has no state labels: label a few frames first (`interreal label`)")
    times = np.array([f.index for f in ds.frames], float)
    states, known = known_states(times, labels, given)
    pc = colmap.load_pycolmap(cfg.verbose)
    work = ds_path / MOTIONS_DIR
    inputs = {"frames": len(ds.frames), "objects": ds.object_names, "fingerprints": fps}
    # by content: a re-run of an earlier stage that rewrote the same bytes does not measure everything again
    key = fingerprint(asdict(cfg), {k: v["content"] for k, v in sorted(fps.items())})
    done = finished_with(ds_path, "motions", key)
    if done is not None and (ds_path / ARTICULATION_FILE).exists() and not force:
        return dict(done["figures"], reused=True)
    motions: dict[str, Articulation] = {}
    parts: dict[str, dict[str, Any]] = {}
    with StageReport(ds_path, "motions", inputs=inputs, settings=asdict(cfg), resume_key=key) as rep:
        for o, name in enumerate(ds.object_names):
            part = work / f"object_{o}"
            with rep.step(f"object {o}") as st:
                names, shown = part_masks(ds, o, part / "masks", cfg, keep=set(np.flatnonzero(given[:, o]).tolist()))
                st["frames_shown"], st["frames_matched"] = shown, len(names)
                if len(names) < cfg.min_registered:
                    rep.warn(f"'{name}' shows in only {len(names)} frames: no motion measured (the k-axis alone "
                             f"will move it)", cause="motion-unseen", object=name)
                    continue
                with NativeLog(part / "colmap.log", cfg.verbose) as log:
                    # on the terminal even while COLMAP's log (fd 2) goes to the file: a part takes minutes
                    with tqdm(total=4 + cfg.attempts, desc=f"motions '{name}'", file=log.term, leave=False,
                              unit="phase") as bar:
                        def step(text: str) -> None:
                            if text != "matching":
                                bar.update(1)
                            bar.set_postfix_str(text)

                        motion, fig = measure_part(pc, ds, names, part, states[:, o], known[:, o], cfg, step,
                                                   labelled=given[:, o], obj=o)
                fids = [f.fid for f in ds.frames]
                st.update({k: v if not isinstance(v, float) or np.isfinite(v) else None for k, v in fig.items()})
                if motion is None:
                    rep.warn(f"'{name}': no route measured a motion in the {shown} frames it shows in: "
                             + "; ".join(f"{r}: {v['reason']}" for r, v in fig.get("routes", {}).items())
                             + "; label more frames where it moves, or film it with more texture in view",
                             cause="motion-unregistered", object=name)
                    continue
                st["kind"] = motion.kind
                st["frame_states"] = frame_state_rows(fig, fids, labels[:, o], given[:, o])
                motion.extra = {k: v for k, v in fig.items() if k != "frame_states"}
                # every registered frame's measured state, by frame id: what training fits the states to
                # (`Articulation.measured_states`), eyeballed labels being coarser than the geometry
                motion.extra["frame_states"] = {fids[f]: m for f, m in fig.get("frame_states", [])}
                measured_by = f"{fig.get('route', '?')} ({fig['registered']} of the {shown} frames it shows in)"
                if not fig["accepted"]:
                    rep.warn(f"'{name}': the {motion.kind} measured by {measured_by} is not used: {fig['reason']}; "
                             f"{disagreement_text(fig.get('label_check', []), fids)}{routes_text(fig)}; check "
                             + ("those labels and " if cfg.trust_labels else "") + "the part's masks",
                             cause="motion-inconsistent", object=name, flagged=_flag_rows(fig, fids))
                    continue
                for text, cause in ends_warnings(name, fig):
                    rep.warn(text, cause=cause, object=name)
                if fig["flagged_labels"]:
                    rep.warn(f"'{name}': {len(fig['flagged_labels'])} of {len(fig['label_check'])} labels disagree "
                             f"with the {motion.kind} measured by {measured_by}, which is used"
                             + ("" if cfg.trust_labels else " (the labels only orient it; --trust-labels lets them "
                                "decide)") + f": {disagreement_text(fig['label_check'], fids)}; the annotate app "
                             f"offers the measured states as the fix", cause="label-disagrees", object=name,
                             flagged=_flag_rows(fig, fids))
                motions[name] = motion
                parts[name] = part_summary(motion, fig, shown)
        write_articulation(ds_path, motions, {"source": "interreal motions"})
        rep.figures.update(objects={n: m.kind for n, m in motions.items()}, measured=len(motions),
                           total=ds.n_objects, parts=parts)
        figures = dict(rep.figures)
    return figures


def part_summary(motion: Articulation, fig: dict[str, Any], shown: int) -> dict[str, Any]:
    """What a user needs to trust a used motion, in one record: kind, size, route, frames, the states' span, the
    labels flagged (the report's step holds every frame's state and why the other routes gave nothing)."""
    states = [m for _, m in fig.get("frame_states", [])]
    size = round(float(np.degrees(motion.range)), 1) if motion.kind == "hinge" else round(float(motion.range), 4)
    return {"kind": motion.kind, "range": size, "unit": "deg" if motion.kind == "hinge" else "world units",
            "route": fig.get("route"), "measured_frames": len(states), "shown_frames": shown,
            "states": [round(min(states), 2), round(max(states), 2)] if states else None,
            "flagged_labels": len(fig.get("flagged_labels", [])), "ends_from": fig.get("ends_from", "")}


def part_line(name: str, p: dict[str, Any]) -> str:
    """One line per used motion, e.g. 'door': hinge of 53.6 deg by sfm, 64 of 64 frames, states -0.01 to 1.02."""
    return (f"'{name}': {p['kind']} of {p['range']:g} {p['unit']} by {p['route']}, {p['measured_frames']} of "
            f"{p['shown_frames']} frames" + (f", states {p['states'][0]:g} to {p['states'][1]:g}" if p["states"] else "")
            + (f"; {p['flagged_labels']} label(s) flagged" if p["flagged_labels"] else ""))


def add_arguments(p) -> None:
    p.add_argument("dataset", type=Path, help="dataset folder with images, masks, transforms.json and labels")
    add_flags(p, MotionConfig)  # one flag per `option` field
    p.add_argument("--force", action="store_true", help="measure again even when a finished run matches")
    p.epilog = ("examples:\n  interreal motions out/ds\n  interreal motions out/ds --erode 4\n"
                "  interreal motions out/ds --route edge      # a plain door filmed from close by, tried first\n"
                "  interreal motions out/ds --route prism     # a plain drawer, tried first\n"
                f"writes DS/{ARTICULATION_FILE} (read by `livescene train`) and DS/reports/motions.json")


def main(args) -> int:
    fig = estimate_motions(args.dataset, force=args.force, **values_from_args(MotionConfig, args))
    for line in warning_lines(args.dataset, ["motions"]):
        print(line)
    print(f"motions: {fig['measured']} of {fig['total']} objects measured"
          + (" (reused: same inputs and settings)" if fig.get("reused") else "") + ": "
          + ", ".join(f"{n} ({k})" for n, k in fig["objects"].items()))
    for name, part in (fig.get("parts") or {}).items():
        print("  " + part_line(name, part))
    return 0
