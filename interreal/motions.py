"""`interreal motions DS`: how each object moves with its state, measured from the video -> DS/articulation.json.

A rigid part filmed by a moving camera is, to SfM, a static scene of its own. So each object's pixels alone (its
masks, eroded) are reconstructed with pycolmap, and every frame the part's reconstruction registers gives the camera
relative to the part; with the camera's pose in the world (transforms.json) that is the part's pose in the world at
that frame, whether the part was still or moving. Those poses fix the motion:
- the relative rotations of a hinge share one axis: the axis is their principal direction, and the angle about it
  is linear in the state (`angle = range * state + c`, fitted on the frames whose state the labels give);
- the translations are then linear in the part's unknowns (the reconstruction's scale, the rest pose, a point on
  the axis), solved by robust least squares over every registered frame;
- a part that turns less than `SLIDE_MAX_DEG` over its whole range is a slide: its centre moves linearly with the
  state.
The trainer (`livescene`, `model.motion`) then reads each part's samples in its rest frame (its pose at state 0).
Conventions of the file: `interreal.conventions` / `interreal.dataset.Articulation`.
"""

from __future__ import annotations

import shutil
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import atomic, provenance
from .conventions import ARTICULATION_FILE, IMAGES_DIR, opengl_to_opencv
from .dataset import Articulation, known_states, load_dataset, write_articulation
from .errors import InputError
from .report import StageReport, finished_with, fingerprint, warning_lines

MOTIONS_DIR = "motions"  # DS/motions/<object>/: the part reconstructions (database, masks, model)
SLIDE_MAX_DEG = 3.0  # a part that turns less than this between states 0 and 1 (or at all) slides
MAX_STATE_RMSE = 0.1  # a motion that gives the labelled states from the part's poses worse than this is not used
OFF_AXIS_DEG = 3.0  # a frame whose turn leaves the hinge axis by more than this is misregistered


@dataclass
class MotionConfig:
    """Settings of one `interreal motions` run (they enter the resume fingerprint)."""

    erode: int = 2  # px taken off each mask's border: features there may belong to the background
    min_pixels: int = 400  # frames showing fewer of the part's pixels are not used
    max_features: int = 2048
    overlap: int = 10  # sequential pairs (i, i+1..overlap, then i+2^k), plus every `key_every`-th frame exhaustively
    key_every: int = 4
    min_registered: int = 8  # fewer registered frames than this: no motion for the part (the k-axis alone moves it)
    min_known: int = 3  # frames with a known state among the registered ones
    seed: int = 0  # mapper attempt k uses seed + k
    attempts: int = 3  # mapper runs per part at most (a bent or flipped model of a planar part gives bad states)
    num_threads: int = -1
    verbose: bool = False


# ----------------------------------------------------------------------------------------------------------------
# The part's own reconstruction
# ----------------------------------------------------------------------------------------------------------------
def part_masks(ds, obj: int, out: Path, cfg: MotionConfig) -> list[str]:
    """COLMAP masks (<image name>.png, 255 = use) of object `obj`'s eroded pixels; the image names that show it."""
    import cv2

    out.mkdir(parents=True, exist_ok=True)
    kernel = np.ones((2 * cfg.erode + 1,) * 2, np.uint8)
    names = []
    for f in ds.frames:
        m = ds.load_mask(f)[..., obj].astype(np.uint8) * 255
        if cfg.erode:
            m = cv2.erode(m, kernel)
        if int((m > 0).sum()) < cfg.min_pixels:
            continue
        name = Path(f.file_path).name
        atomic.write_image(out / f"{name}.png", m)
        names.append(name)
    return names


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
    ext = pc.FeatureExtractionOptions(num_threads=cfg.num_threads, use_gpu=False, max_image_size=4096)
    ext.sift.first_octave = -1  # small regions: the upsampled octave finds several times the features
    ext.sift.max_num_features = cfg.max_features
    params = ",".join(f"{v:.9g}" for v in (intr.fl_x, intr.fl_y, intr.cx, intr.cy, intr.k1, intr.k2, intr.p1, intr.p2))
    reader = pc.ImageReaderOptions(camera_model="OPENCV", camera_params=params)
    reader.mask_path = str(mask_dir)
    pc.extract_features(str(db), str((ds.root / IMAGES_DIR).resolve()), image_names=names,
                        camera_mode=pc.CameraMode.SINGLE, reader_options=reader, extraction_options=ext,
                        device=pc.Device.cpu)
    listing = work / "pairs.txt"
    listing.write_text("".join(f"{names[a]} {names[b]}\n" for a, b in part_pairs(len(names), cfg.overlap,
                                                                                  cfg.key_every)))
    verify = pc.TwoViewGeometryOptions()
    verify.ransac.random_seed = cfg.seed
    pc.match_image_pairs(str(db), matching_options=pc.FeatureMatchingOptions(num_threads=cfg.num_threads,
                                                                             use_gpu=False),
                         pairing_options=pc.ImportedPairingOptions(match_list_path=str(listing)),
                         verification_options=verify, device=pc.Device.cpu)
    return db


def map_part(pc, ds, db: Path, out: Path, cfg: MotionConfig, seed: int):
    """The largest pycolmap model of the matched part, the dataset's intrinsics held fixed (None when none).
    A part is often nearly planar (a drawer's front): which model the mapper settles on depends on its seed."""
    opt = pc.IncrementalPipelineOptions(num_threads=cfg.num_threads, random_seed=seed, min_model_size=3)
    opt.ba_refine_focal_length = opt.ba_refine_principal_point = opt.ba_refine_extra_params = False
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    pc.set_random_seed(seed)
    models = dict(pc.incremental_mapping(str(db), str((ds.root / IMAGES_DIR).resolve()), str(out), options=opt))
    if not models:
        return None
    return max(models.values(), key=lambda r: r.num_reg_images())


@dataclass
class PartViews:
    """Per registered frame (dataset positions `frames`): the part's reconstruction seen from the world.

    rot (F, 3, 3): reconstruction -> world rotation at that frame; u (F, 3): the camera-to-part offset rotated into
    the world (world units once multiplied by the reconstruction's unknown scale); centre (F, 3): camera centre."""

    frames: np.ndarray
    rot: np.ndarray
    u: np.ndarray
    centre: np.ndarray


def part_views(rec, ds) -> PartViews:
    """A part reconstruction's registered frames related to their world cameras (OpenCV axes inside)."""
    by_name = {Path(f.file_path).name: i for i, f in enumerate(ds.frames)}
    frames, rot, u, centre = [], [], [], []
    for im in rec.images.values():
        if not im.has_pose or im.name not in by_name:
            continue
        i = by_name[im.name]
        w2c_part = np.asarray(im.cam_from_world().matrix())  # 3x4, reconstruction units
        c2w = opengl_to_opencv(ds.frames[i].c2w)
        frames.append(i)
        rot.append(c2w[:3, :3] @ w2c_part[:, :3])
        u.append(c2w[:3, :3] @ w2c_part[:, 3])
        centre.append(c2w[:3, 3])
    order = np.argsort(frames)
    return PartViews(np.asarray(frames)[order], np.asarray(rot)[order], np.asarray(u)[order],
                     np.asarray(centre)[order])


# ----------------------------------------------------------------------------------------------------------------
# Fitting a hinge or a slide
# ----------------------------------------------------------------------------------------------------------------
def _rotvec(r: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(r).as_rotvec()


def _axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.outer(np.atleast_1d(angle), axis)).as_matrix()


def _robust_line(x: np.ndarray, y: np.ndarray, iters: int = 20) -> tuple[float, float]:
    """(slope, intercept) of y = slope * x + intercept, Huber-weighted (a few misregistered frames)."""
    w = np.ones_like(x)
    slope, icpt = 0.0, float(np.median(y))
    for _ in range(iters):
        a = np.stack([x, np.ones_like(x)], 1) * w[:, None]
        slope, icpt = np.linalg.lstsq(a, y * w, rcond=None)[0]
        r = np.abs(y - slope * x - icpt)
        k = 1.345 * max(float(np.median(r)) / 0.6745, 1e-9)
        w = np.sqrt(np.where(r <= k, 1.0, k / np.maximum(r, 1e-12)))
    return float(slope), float(icpt)


def _robust_lstsq(a: np.ndarray, b: np.ndarray, rows: int = 3, iters: int = 20) -> np.ndarray:
    """Huber IRLS of a x = b where each group of `rows` equations is one frame (weighted together)."""
    w = np.ones(len(b) // rows)
    x = np.zeros(a.shape[1])
    for _ in range(iters):
        ww = np.repeat(np.sqrt(w), rows)
        x = np.linalg.lstsq(a * ww[:, None], b * ww, rcond=None)[0]
        r = np.linalg.norm((a @ x - b).reshape(-1, rows), axis=1)
        k = 1.345 * max(float(np.median(r)) / 0.6745, 1e-12)
        w = np.where(r <= k, 1.0, k / np.maximum(r, 1e-12))
    return x


def _basis(axis: np.ndarray) -> np.ndarray:
    """(3, 2): two unit vectors perpendicular to `axis` and to each other."""
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(axis, e1)], 1)


def _consensus(rot: np.ndarray, known: np.ndarray, tries: int = 12) -> tuple[int, np.ndarray, np.ndarray]:
    """(reference frame, hinge axis, inliers (F,) bool): the relative rotations of a rigid part's frames share one
    axis; a misregistered frame does not. Each of up to `tries` frames with a known state is tried as the reference
    (it may be misregistered itself); the axis is the one most frames agree with (within `OFF_AXIS_DEG`), drawn
    from the frames' own turn directions (one wild frame must not set it), then refitted on those that agree."""
    best: tuple[int, int, np.ndarray, np.ndarray] | None = None
    cands = np.flatnonzero(known)
    cands = cands[np.linspace(0, len(cands) - 1, min(tries, len(cands))).round().astype(int)]
    for ref in cands:
        vecs = np.stack([_rotvec(r) for r in np.einsum("fij,kj->fik", rot, rot[ref])])
        axis = _vote_axis(vecs)
        inl = np.ones(len(vecs), bool)
        for _ in range(3):  # refit on the frames that agree
            inl = _off_axis_deg(vecs, axis) < OFF_AXIS_DEG
            axis = _principal(vecs[inl]) if inl.sum() >= 2 else axis
        if best is None or inl.sum() > best[1]:
            best = (int(ref), int(inl.sum()), axis, inl)
    assert best is not None
    return best[0], best[2], best[3]


def _off_axis_deg(vecs: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(F,) how far each rotation vector (F, 3) turns about anything but `axis`, in degrees."""
    return np.degrees(np.linalg.norm(vecs - np.outer(vecs @ axis, axis), axis=1))


def _vote_axis(vecs: np.ndarray, candidates: int = 64) -> np.ndarray:
    """The turn direction of one of the frames that turn clearly, the one the most frames agree with."""
    turn = np.degrees(np.linalg.norm(vecs, axis=1))
    big = np.flatnonzero(turn > 2 * OFF_AXIS_DEG)
    if not len(big):
        return _principal(vecs)  # nothing turns beyond the noise: any axis will do (a slide)
    big = big[np.linspace(0, len(big) - 1, min(candidates, len(big))).round().astype(int)]
    axes = vecs[big] / np.linalg.norm(vecs[big], axis=1, keepdims=True)
    votes = [int((_off_axis_deg(vecs, a) < OFF_AXIS_DEG).sum()) for a in axes]
    return axes[int(np.argmax(votes))]


def _principal(vecs: np.ndarray) -> np.ndarray:
    """The direction rotation vectors (F, 3) lie along, weighted by their size (small turns are mostly noise)."""
    turn = np.linalg.norm(vecs, axis=1)
    if turn.max() < 1e-9:
        return np.array([0.0, 0.0, 1.0])
    _, _, vt = np.linalg.svd(vecs * turn[:, None])
    return vt[0]


def fit_motion(pv: PartViews, states: np.ndarray, known: np.ndarray) -> tuple[Articulation, dict[str, Any]]:
    """A hinge or a slide from the part's per-frame poses; states, known (F,) of the registered frames.

    Returns the motion and what it measured (residuals in degrees and world units, frames used and rejected, the
    scale of the part reconstruction)."""
    ref, axis, inl = _consensus(pv.rot, known)
    pv = PartViews(pv.frames[inl], pv.rot[inl], pv.u[inl], pv.centre[inl])
    states, known = states[inl], known[inl]
    ref = int(np.searchsorted(np.flatnonzero(inl), ref))
    vecs = np.stack([_rotvec(r) for r in np.einsum("fij,kj->fik", pv.rot, pv.rot[ref])])
    turn = np.degrees(np.linalg.norm(vecs, axis=1))
    extra: dict[str, Any] = {"registered": int(len(inl)), "rejected": int((~inl).sum()), "known": int(known.sum()),
                             "max_turn_deg": round(float(turn.max()), 2)}
    slide = _fit_slide(pv, states, known, dict(extra))
    rate, _ = _robust_line(states[known], (vecs @ axis)[known])
    if np.percentile(turn, 95) < SLIDE_MAX_DEG or np.degrees(abs(rate)) < SLIDE_MAX_DEG:
        return slide  # it barely turns, or not with its state: noise
    hinge = _fit_hinge(pv, states, known, vecs, axis, ref, extra)
    # a small part's rotations are noisy: the motion that gives the labelled states better wins
    return hinge if hinge[1]["state_rmse_from_pose"] <= slide[1]["state_rmse_from_pose"] else slide


def _fit_hinge(pv: PartViews, states: np.ndarray, known: np.ndarray, vecs: np.ndarray, axis: np.ndarray, ref: int,
               extra: dict) -> tuple[Articulation, dict]:
    """The hinge about `axis` whose angle is linear in the state; vecs (F, 3) each frame's rotation vector relative
    to frame `ref`. The translations then give the reconstruction's scale, the rest pose and a point on the axis."""
    f = len(pv.frames)
    angle = vecs @ axis
    rate, c = _robust_line(states[known], angle[known])
    if rate < 0:
        axis, angle, rate, c = -axis, -angle, -rate, -c
    extra["off_axis_deg"] = round(float(np.median(_off_axis_deg(vecs, axis))), 3)
    # rotation at each frame relative to the rest pose (state 0), as measured
    moved = _axis_angle(axis, angle - c)
    rest_rot = _axis_angle(axis, np.array([c]))[0] @ pv.rot[ref]  # reconstruction -> world at state 0
    # sigma u_f + C_f = R_f b0 + (I - R_f) o,  o = B w (a point on the axis, the part along the axis dropped)
    basis = _basis(axis)
    eye = np.eye(3)[None]
    a = np.concatenate([pv.u[..., None], -moved, -((eye - moved) @ basis)], axis=2).reshape(3 * f, 6)
    sol = _robust_lstsq(a, -pv.centre.reshape(-1))
    sigma, b0, origin = sol[0], sol[1:4], basis @ sol[4:6]
    pred_rot = _axis_angle(axis, rate * states)
    resid_rot = np.degrees(np.linalg.norm(np.stack([_rotvec(r) for r in np.einsum(
        "fij,fjk->fik", np.einsum("fij,jk->fik", pred_rot, rest_rot), np.transpose(pv.rot, (0, 2, 1)))]), axis=1))
    pos = sigma * pv.u + pv.centre
    pred_pos = np.einsum("fij,j->fi", pred_rot, b0) + np.einsum("fij,j->fi", eye - pred_rot, origin)
    extra.update(scale=float(sigma), state_rmse_from_pose=_state_rmse(angle - c, rate, states, known),
                 label_check=_label_check(pv.frames, (angle - c) / rate, states, known),
                 rot_residual_deg=round(float(np.median(resid_rot[known])), 3),
                 pos_residual=float(np.median(np.linalg.norm(pos - pred_pos, axis=1)[known])))
    return Articulation("hinge", axis, origin, rate, extra), extra


def _state_rmse(motion: np.ndarray, rate: float, states: np.ndarray, known: np.ndarray) -> float:
    """How well the measured motion alone gives the known states (a check of the fit and of the labels); infinite
    when the fit found no motion (all known states alike, or the part did not move)."""
    if not abs(rate) > 1e-12 or not known.any():
        return float("inf")
    return round(float(np.sqrt(np.mean((motion[known] / rate - states[known]) ** 2))), 4)


def _label_check(frames: np.ndarray, measured: np.ndarray, states: np.ndarray, known: np.ndarray) -> list[list]:
    """[[dataset position, labelled state, measured state], ...] of the labelled frames the fit used: what the
    warnings name when the motion and the labels disagree."""
    return [[int(frames[i]), round(float(states[i]), 3), round(float(measured[i]), 3)] for i in np.flatnonzero(known)
            if np.isfinite(measured[i])]


def disagreement_text(check: list[list], fids: list[str], most: int = 5) -> str:
    """'measured states -0.05..1.12; labels that disagree most: 00042 (label 1.00, measured 0.62), ...'"""
    if not check:
        return "no labelled frame was measured"
    measured = [m for _, _, m in check]
    worst = sorted(check, key=lambda r: -abs(r[2] - r[1]))
    off = [r for r in worst if abs(r[2] - r[1]) > MAX_STATE_RMSE][:most]
    return (f"measured states {min(measured):.2f} to {max(measured):.2f} on {len(check)} labelled frames; "
            + ("labels off by more than " + f"{MAX_STATE_RMSE}: " + ", ".join(
                f"{fids[f]} (label {lab:.2f}, measured {m:.2f})" for f, lab, m in off) if off
               else "no single label is off by more than " + f"{MAX_STATE_RMSE}"))


def _still_frames(rot: np.ndarray) -> np.ndarray:
    """(F,) bool: the frames whose rotation (F, 3, 3) stays within max(SLIDE_MAX_DEG, 3 x the median) of the
    frames' mean orientation (recomputed on the kept frames, so a flipped frame does not pull it)."""
    from scipy.spatial.transform import Rotation

    rots = Rotation.from_matrix(rot)
    keep = np.ones(len(rot), bool)
    for _ in range(3):
        dev = np.degrees((rots * rots[keep].mean().inv()).magnitude())
        keep = dev <= max(SLIDE_MAX_DEG, 3 * float(np.median(dev)))
    return keep


def _fit_slide(pv: PartViews, states: np.ndarray, known: np.ndarray, extra: dict) -> tuple[Articulation, dict]:
    """sigma u_f + C_f = b0 + s_f v over the frames with a known state that keep the part's usual orientation (a
    slide does not turn: a frame that does is misregistered): scale, rest position, motion per state."""
    still = _still_frames(pv.rot)
    extra["slide_rejected"] = int((~still).sum())
    idx = np.flatnonzero(known & still)
    k = len(idx)
    eye = np.broadcast_to(np.eye(3), (k, 3, 3))
    a = np.concatenate([pv.u[idx, :, None], -eye, -states[idx, None, None] * eye], axis=2).reshape(3 * k, 7)
    sol = _robust_lstsq(a, -pv.centre[idx].reshape(-1))
    sigma, b0, v = sol[0], sol[1:4], sol[4:7]
    rate = float(np.linalg.norm(v))
    axis = v / max(rate, 1e-12)
    pos = sigma * pv.u + pv.centre
    along = (pos - b0) @ axis
    extra.update(scale=float(sigma), state_rmse_from_pose=_state_rmse(along, rate, states, known & still),
                 label_check=_label_check(pv.frames, along / max(rate, 1e-12), states, known & still),
                 pos_residual=float(np.median(np.linalg.norm(pos[idx] - b0 - np.outer(states[idx], v), axis=1))))
    return Articulation("slide", axis, b0, rate, extra), extra


def measure_part(pc, ds, names: list[str], part: Path, states: np.ndarray, known: np.ndarray,
                 cfg: MotionConfig, step: Any = None) -> tuple[Articulation | None, dict[str, Any]]:
    """The part's motion from its own reconstruction; states, known (N,) over the dataset's frames.

    The mapper is run with up to `cfg.attempts` seeds on the same matches, until a motion gives the labelled states
    within half of MAX_STATE_RMSE: a nearly planar part sometimes comes out bent or with a flipped view, which the
    labels tell. The best attempt is returned (None when none registered enough frames with a known state).
    step(text): called as each phase starts (a progress bar)."""
    step = step or (lambda text: None)
    step("matching")
    db = match_part(pc, ds, names, part / "masks", part, cfg)
    best: tuple[Articulation | None, dict[str, Any]] = (None, {"registered": 0})
    for a in range(cfg.attempts):
        step(f"reconstruction {a + 1}/{cfg.attempts}")
        rec = map_part(pc, ds, db, part / "sparse" / str(a), cfg, cfg.seed + a)
        pv = part_views(rec, ds) if rec is not None else None
        if pv is None or len(pv.frames) < cfg.min_registered or int(known[pv.frames].sum()) < cfg.min_known:
            if best[0] is None and pv is not None:  # what the warning reports: the most any attempt registered
                best[1]["registered"] = max(len(pv.frames), best[1]["registered"])
            continue
        motion, fig = fit_motion(pv, states[pv.frames], known[pv.frames])
        fig["attempt"] = a
        if best[0] is None or fig["state_rmse_from_pose"] < best[1]["state_rmse_from_pose"]:
            best = (motion, fig)
        if fig["state_rmse_from_pose"] <= MAX_STATE_RMSE / 2:
            break
    best[1]["attempts"] = a + 1
    return best


# ----------------------------------------------------------------------------------------------------------------
# The stage
# ----------------------------------------------------------------------------------------------------------------
def estimate_motions(ds_path: str | Path, force: bool = False, **opts: Any) -> dict[str, Any]:
    """Measure every object's motion and write DS/articulation.json and reports/motions.json; returns the figures.
    A finished run from the same masks, poses, labels and settings is reused unless `force`.

    An object the reconstruction cannot follow (too few registered frames, or too few of them with a known state)
    gets no motion and a warning: the trainer then moves it with the k-axis alone, as the paper does."""
    from .sfm import NativeLog, _pycolmap

    ds_path = Path(ds_path)
    unknown = set(opts) - set(MotionConfig.__dataclass_fields__)
    if unknown:
        raise InputError(f"unknown motion options {sorted(unknown)}")
    cfg = MotionConfig(**{k: v for k, v in opts.items() if v is not None})
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
    pc = _pycolmap(cfg.verbose)
    work = ds_path / MOTIONS_DIR
    inputs = {"frames": len(ds.frames), "objects": ds.object_names, "fingerprints": fps}
    # by content: a re-run of an earlier stage that rewrote the same bytes does not measure everything again
    key = fingerprint(asdict(cfg), {k: v["content"] for k, v in sorted(fps.items())})
    done = finished_with(ds_path, "motions", key)
    if done is not None and (ds_path / ARTICULATION_FILE).exists() and not force:
        return dict(done["figures"], reused=True)
    motions: dict[str, Articulation] = {}
    with StageReport(ds_path, "motions", inputs=inputs, settings=asdict(cfg), resume_key=key) as rep:
        for o, name in enumerate(ds.object_names):
            part = work / f"object_{o}"
            with rep.step(f"object {o}") as st:
                names = part_masks(ds, o, part / "masks", cfg)
                st["frames_shown"] = len(names)
                if len(names) < cfg.min_registered:
                    rep.warn(f"'{name}' shows in only {len(names)} frames: no motion measured (the k-axis alone "
                             f"will move it)", cause="motion-unseen", object=name)
                    continue
                with NativeLog(part / "colmap.log", cfg.verbose) as log:
                    from tqdm import tqdm

                    # on the terminal even while COLMAP's log (fd 2) goes to the file: a part takes minutes
                    with tqdm(total=1 + cfg.attempts, desc=f"motions '{name}'", file=log.term, leave=False,
                              unit="phase") as bar:
                        def step(text: str) -> None:
                            if text != "matching":
                                bar.update(1)
                            bar.set_postfix_str(text)

                        motion, fig = measure_part(pc, ds, names, part, states[:, o], known[:, o], cfg, step)
                st.update({k: v if not isinstance(v, float) or np.isfinite(v) else None for k, v in fig.items()})
                if motion is None:
                    rep.warn(f"'{name}': its own reconstruction registered only {st['registered']} of the "
                             f"{len(names)} frames it shows in (need {cfg.min_registered}, {cfg.min_known} with a "
                             f"known state), best of {fig['attempts']} reconstructions: no motion measured; "
                             f"label more frames where it moves, or film it with more texture in view",
                             cause="motion-unregistered", object=name)
                    continue
                st["kind"] = motion.kind
                rmse = fig["state_rmse_from_pose"]
                if not rmse <= MAX_STATE_RMSE:
                    how = (f"gives the labelled states only within {rmse:.2f} (RMSE > {MAX_STATE_RMSE})"
                           if np.isfinite(rmse) else "does not change with the labelled states")
                    fids = [f.fid for f in ds.frames]
                    rep.warn(f"'{name}': the measured {motion.kind} {how}, best of {fig['attempts']} "
                             f"reconstructions, which registered {fig['registered']} of the {len(names)} frames it "
                             f"shows in; {disagreement_text(fig.get('label_check', []), fids)}: not used; check "
                             f"those labels and the part's masks", cause="motion-inconsistent", object=name)
                    continue
                motions[name] = motion
        write_articulation(ds_path, motions, {"source": "interreal motions"})
        rep.figures.update(objects={n: m.kind for n, m in motions.items()}, measured=len(motions),
                           total=ds.n_objects)
        figures = dict(rep.figures)
    return figures


def add_arguments(p) -> None:
    p.add_argument("dataset", type=Path, help="dataset folder with images, masks, transforms.json and labels")
    p.add_argument("--erode", type=int, default=None, help="px taken off each mask's border (default 2)")
    p.add_argument("--min-pixels", type=int, default=None, help="frames showing fewer part pixels are skipped")
    p.add_argument("--force", action="store_true", help="measure again even when a finished run matches")
    p.add_argument("--verbose", action="store_true", help="COLMAP's own log on the terminal")
    p.epilog = ("examples:\n  interreal motions out/ds\n  interreal motions out/ds --erode 4\n"
                f"writes DS/{ARTICULATION_FILE} (read by `livescene train`) and DS/reports/motions.json")


def main(args) -> int:
    fig = estimate_motions(args.dataset, force=args.force, erode=args.erode, min_pixels=args.min_pixels,
                           verbose=args.verbose)
    for line in warning_lines(args.dataset, ["motions"]):
        print(line)
    print(f"motions: {fig['measured']} of {fig['total']} objects measured"
          + (" (reused: same inputs and settings)" if fig.get("reused") else "") + ": "
          + ", ".join(f"{n} ({k})" for n, k in fig["objects"].items()))
    return 0
