"""The reconstruction of one pose stage: features, the retry ladder of match + map attempts, and the polishing of
the kept model (track refinement, the final BA that decides the principal point, track extension and its BA).

Each step is a function over a `Workspace` (the run's folders, settings, resume state and report) and reaches
pycolmap only through `interreal.sfm.colmap`.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import atomic
from ..conventions import frame_index
from ..errors import StageError
from ..keypoints import extend_tracks, refine_tracks
from ..layout import COLMAP_DIR, IMAGES_DIR
from ..report import StageReport, fingerprint
from . import colmap
from .colmap import NativeLog
from .config import Rung, SfMConfig, key_positions, loop_queries, rung_pairs
from .intrinsics import KnownIntrinsics

PP_MIN_GAIN = 0.003  # relative RMS reprojection gain that justifies freeing (cx, cy)
PP_MAX_SHIFT = 0.02  # ... and the largest plausible move of (cx, cy), as a fraction of the image diagonal
EXTENDED_BA_TOLERANCE = 1e-3  # the BA after `extend_tracks` starts at the optimum of the same points and cameras,
# so one LM step suffices (docs/sfm-measurements.md)


@dataclass
class Workspace:
    """One SfM run: the dataset, pycolmap, the settings, the image names (in order), the SfM masks, the resume
    state (DS/colmap/state.json) and the stage report. Paths under DS/colmap come from here only."""

    pc: Any
    ds: Path
    cfg: SfMConfig
    rep: StageReport
    names: list[str]
    state: dict[str, Any] = field(default_factory=dict)
    mask_dir: Path | None = None
    known: KnownIntrinsics | None = None  # --intrinsics, in pixels of the dataset's images
    work: Path = field(init=False)  # DS/colmap: database.db, vocab_tree.bin, state.json, sparse/<rank>, colmap.log
    images: Path = field(init=False)
    db: Path = field(init=False)
    tree: Path = field(init=False)
    state_path: Path = field(init=False)
    sparse: Path = field(init=False)

    def __post_init__(self) -> None:
        self.work, self.images = self.ds / COLMAP_DIR, self.ds / IMAGES_DIR
        self.db, self.tree = self.work / "database.db", self.work / "vocab_tree.bin"
        self.state_path, self.sparse = self.work / "state.json", self.work / "sparse"

    def log(self) -> NativeLog:
        """COLMAP's native log to DS/colmap/colmap.log (the terminal with --verbose)."""
        return NativeLog(self.work / "colmap.log", self.cfg.verbose)

    def save_state(self) -> None:
        atomic.write_json(self.state_path, self.state)

    @property
    def fixed_intrinsics(self) -> bool:
        """The camera is given and held: no step of the run may change it."""
        return self.known is not None and not self.cfg.intrinsics_refine


@dataclass
class Attempt:
    """One rung's models: model id -> reconstruction, and (registered images, model id) largest first."""

    rung: Rung
    models: dict[int, Any]
    sizes: list[tuple[int, int]]

    @property
    def rec(self):
        return self.models[self.sizes[0][1]]


# ----------------------------------------------------------------------------------------------------------------
# the three pycolmap steps with this stage's settings
# ----------------------------------------------------------------------------------------------------------------
def extract(ws: Workspace, octave: int, fine: set[int], log: NativeLog | None = None) -> None:
    """SIFT into a fresh database: frames at the positions `fine` (from `fine_frames`) get the first octave
    `octave`, the others octave 0."""
    cfg = ws.cfg
    groups = [(octave, [n for i, n in enumerate(ws.names) if i in fine]),
              (0, [n for i, n in enumerate(ws.names) if i not in fine])]
    model, params = ("OPENCV", ws.known.colmap_params()) if ws.known is not None else (cfg.camera_model, "")
    ex = colmap.Extraction(model, cfg.sfm_long_side, cfg.max_features, params, num_threads=cfg.num_threads)
    colmap.extract_features(ws.pc, ws.db, ws.images, groups, ex, ws.mask_dir, log)


def match(ws: Workspace, rung: Rung, log: NativeLog | None = None) -> None:
    """Match the rung's pairs, then (sequential rungs with loop detection) the vocabulary tree's loop queries."""
    n, cfg = len(ws.names), ws.cfg
    colmap.match_pairs(ws.pc, ws.db, ws.names, rung_pairs(rung, n, cfg.quadratic_overlap), ws.work / "pairs.txt",
                       cfg.seed, cfg.num_threads, log, desc=f"matching ({rung.name})")
    if rung.loop_detection and rung.matcher == "sequential":
        queries = [ws.names[i] for i in loop_queries(n, rung.stride)]
        colmap.match_loops(ws.pc, ws.db, ws.tree, queries, ws.work / "loop_queries.txt", cfg.seed, cfg.num_threads)


def reconstruct(ws: Workspace, rung: Rung, out: Path, log: NativeLog | None = None) -> dict[int, Any]:
    """Model id -> reconstruction of one rung. A strided rung maps its keyframes first (a third of the frames carry
    the geometry at a fraction of incremental BA's cost), then registers every other frame into that model."""
    pc, cfg, names = ws.pc, ws.cfg, ws.names
    colmap.fresh_model_dir(pc, out, cfg.seed)
    if rung.mapper == "global":
        return colmap.global_map(pc, ws.db, ws.images, out, cfg.num_threads, cfg.seed, ws.fixed_intrinsics)
    opt = colmap.incremental_options(pc, cfg.num_threads, cfg.seed, ws.fixed_intrinsics)
    # fewer, shorter global BAs while growing (same accuracy on fox, -30 % mapping time); refine_intrinsics polishes
    opt.ba_global_frames_ratio = opt.ba_global_points_ratio = 1.6
    opt.ba_global_max_num_iterations = 20
    opt.ba_local_max_num_iterations = 10
    opt.ba_global_max_refinements = 2
    opt.ba_global_function_tolerance = cfg.ba_tolerance
    opt.ba_local_max_refinements = 1
    if rung.relaxed:
        opt.min_num_matches = 8
        opt.mapper.init_min_num_inliers = 40
        opt.mapper.abs_pose_min_num_inliers = 15
        opt.mapper.abs_pose_min_inlier_ratio = 0.15
        opt.mapper.init_min_tri_angle = 8.0
        opt.mapper.max_reg_trials = 6
    bar = log.bar(len(names), "mapping (registered)") if log and names else None
    tick = (lambda: bar.update(1)) if bar is not None else None
    try:
        if rung.stride <= 1 or not names:
            return colmap.incremental_map(pc, ws.db, ws.images, out, opt, tick=tick)
        key_opt = pc.IncrementalPipelineOptions(opt.todict())
        key_opt.image_names = [names[i] for i in key_positions(len(names), rung.stride)]
        for sub in ("keys", "keys_best", "all"):
            (out / sub).mkdir()
        keys = colmap.incremental_map(pc, ws.db, ws.images, out / "keys", key_opt, tick=tick)
        if not keys:
            return {}
        best = max(keys, key=lambda k: keys[k].num_reg_images())
        keys[best].write(str(out / "keys_best"))
        fill = pc.IncrementalPipelineOptions(opt.todict())  # PnP + local BA, no global BA until the final one
        fill.ba_global_frames_ratio = fill.ba_global_points_ratio = 100.0
        return colmap.incremental_map(pc, ws.db, ws.images, out / "all", fill, input_path=out / "keys_best",
                                      tick=tick)
    finally:
        if bar is not None:
            bar.close()


# ----------------------------------------------------------------------------------------------------------------
# the retry ladder
# ----------------------------------------------------------------------------------------------------------------
def run_ladder(ws: Workspace, rungs: list[Rung], fp_feat: str) -> tuple[Attempt, list[dict[str, Any]]]:
    """Match + map rung after rung until >= retry_below of the frames register; (the best attempt, what each rung
    gave). Matches already in the database for the same features and pairs are kept."""
    n, cfg, rep = len(ws.names), ws.cfg, ws.rep
    best: tuple[tuple[int, float], Attempt] | None = None
    tried: list[dict[str, Any]] = []
    matched: list[str] = ws.state.get("matched", [])
    for k, rung in enumerate(rungs):
        t0 = time.perf_counter()
        info: dict[str, Any] = {"rung": rung.name, **asdict(rung)}
        fp_match = fingerprint(fp_feat, rung.matcher, rung.overlap, rung.loop_detection, cfg.quadratic_overlap,
                               rung.stride)
        if k == 0 and matched and matched[0] != fp_match:
            with ws.pc.Database.open(str(ws.db)) as d:
                d.clear_matches()
                d.clear_two_view_geometries()
            matched = []
        if fp_match not in matched:
            info["verified_pairs"] = _match_rung(ws, rung, fp_feat)
            matched.append(fp_match)
            ws.state["matched"] = matched
            ws.save_state()
        with rep.step(f"map:{rung.name}"), ws.log() as log:
            models = reconstruct(ws, rung, ws.work / "attempts" / rung.name, log)
        sizes = sorted(((int(r.num_reg_images()), i) for i, r in models.items()), reverse=True)
        info["models"] = [s for s, _ in sizes]
        info["wall_s"] = round(time.perf_counter() - t0, 3)
        if sizes:
            attempt = Attempt(rung, models, sizes)
            stats = colmap.model_stats(attempt.rec)
            info.update(stats)
            key = (stats["registered"], -stats["mean_reproj_error_px"])
            if best is None or key > best[0]:
                best = (key, attempt)
        else:
            info["registered"] = 0
        tried.append(info)
        rep.data["ladder"] = tried
        rep.write()
        if best is not None and best[0][0] >= cfg.retry_below * n:
            break
    if best is None:
        raise StageError(f"SfM found no model in {n} frames after {len(tried)} attempts "
                         f"({', '.join(t['rung'] for t in tried)}): the frames share too few features; film slower, "
                         "with more texture and overlap")
    return best[1], tried


def _match_rung(ws: Workspace, rung: Rung, fp_feat: str) -> int:
    """Match one rung (building the vocabulary tree first when its loop detection needs one); verified pairs."""
    with ws.rep.step(f"match:{rung.name}") as st:
        if rung.loop_detection and rung.matcher == "sequential" \
                and (ws.state.get("tree") != fp_feat or not ws.tree.exists()):
            with ws.rep.step("vocab_tree"), ws.log():
                colmap.build_vocab_tree(ws.pc, ws.db, ws.tree, seed=ws.cfg.seed)
            ws.state["tree"] = fp_feat
        with ws.log() as log:
            match(ws, rung, log)
        with ws.pc.Database.open(str(ws.db)) as d:
            st["verified_pairs"] = int(d.num_verified_image_pairs())
    return st["verified_pairs"]


def keep_models(ws: Workspace, attempt: Attempt, rec, tried: list[dict[str, Any]]) -> None:
    """Write the attempt's models to DS/colmap/sparse/<rank> (the polished `rec` as 0), report the ladder."""
    rep, sizes = ws.rep, attempt.sizes
    models = {**attempt.models, sizes[0][1]: rec}
    if len(tried) > 1:
        rep.figures["ladder_helped"] = attempt.rung.name if attempt.rung.name != "base" else None
    rep.figures["chosen_attempt"] = attempt.rung.name
    rep.figures["ladder"] = [{"rung": t["rung"], "registered": t.get("registered", 0)} for t in tried]
    rep.figures["models"] = [s for s, _ in sizes]
    if len(sizes) > 1 and sizes[0][0] < len(ws.names):  # a side model re-registering the main one's frames loses nothing
        rep.warn(f"SfM split into {len(sizes)} models of {[s for s, _ in sizes]} frames; the largest is kept "
                 f"(others in {COLMAP_DIR}/sparse/1..)", cause="split-model")
    shutil.rmtree(ws.sparse, ignore_errors=True)
    for rank, (_, mid) in enumerate(sizes):
        d = ws.sparse / str(rank)
        d.mkdir(parents=True)
        models[mid].write(str(d))
    shutil.rmtree(ws.work / "attempts", ignore_errors=True)


# ----------------------------------------------------------------------------------------------------------------
# polishing the kept model
# ----------------------------------------------------------------------------------------------------------------
def polish(ws: Workspace, rec, refine: bool, extend: bool):
    """Tracks aligned (when `refine`), the final BA deciding (cx, cy), then (when `extend`) tracks extended off the
    SfM masks from the adjusted poses and a last BA; returns the model (the final BA may swap in a refined copy)."""
    rep, cfg = ws.rep, ws.cfg
    rep.figures["track_refinement"] = refine
    if refine:
        with rep.step("refine_tracks") as st, ws.log() as log:
            bar = log.bar(rec.num_reg_images(), "track refinement")
            st.update(refine_tracks(rec, ws.images, bar=bar))
            bar.close()
    with rep.step("refine_intrinsics") as st:
        with ws.log():
            res = refine_intrinsics(ws.pc, rec, cfg, "given" if ws.fixed_intrinsics else cfg.principal_point)
        rec = res.pop("_rec", rec)
        st.update(res)
    rep.figures["principal_point"] = res["principal_point"]
    rep.figures["track_extension"] = extend
    if extend:  # (cx, cy) stays as decided on the matched tracks
        with rep.step("extend_tracks") as st, ws.log() as log:
            bar = log.bar(rec.num_reg_images(), "track extension")
            st.update(extend_tracks(rec, ws.images, ws.mask_dir, window=cfg.track_window, bar=bar))
            bar.close()
        with rep.step("final_ba") as st, ws.log():
            st["rms_px"] = round(_ba(ws.pc, rec, cfg, res["principal_point"] == "refined", EXTENDED_BA_TOLERANCE,
                                     intrinsics=not ws.fixed_intrinsics), 5)
    return rec


def _ba(pc, rec, cfg: SfMConfig, principal_point: bool, tolerance: float | None = None,
        intrinsics: bool = True) -> float:
    """One global BA with the stage's loss, to cfg.ba_tolerance unless told (`intrinsics` False: the camera is
    held); the RMS reprojection error."""
    return colmap.bundle_adjust(pc, rec, principal_point, cfg.ba_loss, cfg.ba_loss_scale,
                                cfg.ba_tolerance if tolerance is None else tolerance, cfg.num_threads, intrinsics)


def refine_intrinsics(pc, rec, cfg: SfMConfig, mode: str | bool = "auto") -> dict[str, Any]:
    """Final global BA; with mode "auto" the principal point is freed only when the data asks for it.

    ns-process-data always frees (cx, cy); on a short arc that lets it drift (5x the rotation error on the
    simulator at an unchanged reprojection error), while a real phone's off-centre point needs it. So "auto" keeps
    the free solution only when it lowers the RMS error by more than PP_MIN_GAIN (two extra parameters on tens of
    thousands of observations explain ~0.003 %) and moves (cx, cy) by less than PP_MAX_SHIFT
    (docs/sfm-measurements.md has the figures). Mode "given": the camera came with --intrinsics and is held.
    """
    if mode == "given":  # --intrinsics, held: only poses and points move
        return {"principal_point": "given", "rms_px": _ba(pc, rec, cfg, False, intrinsics=False)}
    if mode is False or mode == "fixed":
        return {"principal_point": "fixed", "rms_px": _ba(pc, rec, cfg, False)}
    if mode is True or mode == "refine":
        return {"principal_point": "refined", "rms_px": _ba(pc, rec, cfg, True)}
    fixed_rms = _ba(pc, rec, cfg, False)
    trial = pc.Reconstruction(rec)
    free_rms = _ba(pc, trial, cfg, True)
    gain = (fixed_rms - free_rms) / max(fixed_rms, 1e-12)
    cam_a, cam_b = next(iter(rec.cameras.values())), next(iter(trial.cameras.values()))
    shift = float(np.hypot(cam_b.principal_point_x - cam_a.principal_point_x,
                           cam_b.principal_point_y - cam_a.principal_point_y))
    shift_rel = shift / float(np.hypot(cam_a.width, cam_a.height))
    info = {"rms_fixed_px": round(fixed_rms, 5), "rms_free_px": round(free_rms, 5), "gain": round(gain, 5),
            "shift_px": round(shift, 3)}
    # phones put the principal point within ~1 % of the centre; a larger move is the free point absorbing outliers
    if gain > PP_MIN_GAIN and shift_rel < PP_MAX_SHIFT:
        return {"principal_point": "refined", **info, "_rec": trial}  # the caller swaps in the refined model
    return {"principal_point": "fixed", **info}


# ----------------------------------------------------------------------------------------------------------------
# frames that did not register
# ----------------------------------------------------------------------------------------------------------------
def diagnose(pc, db: Path, names_all: list[str], registered: set[str]) -> list[dict]:
    """Group unregistered frames into index ranges with a likely cause (texture / overlap / placement)."""
    missing = [n for n in names_all if n not in registered]
    if not missing:
        return []
    causes: dict[str, str] = {}
    with pc.Database.open(str(db)) as d:
        by_name = {im.name: im.image_id for im in d.read_all_images()}
        best: dict[int, int] = {}
        pair_ids, geoms = d.read_two_view_geometries()
        for pid, g in zip(pair_ids, geoms):
            a, b = pc.pair_id_to_image_pair(pid)
            k = len(g.inlier_matches)
            best[a] = max(best.get(a, 0), k)
            best[b] = max(best.get(b, 0), k)
        for n in missing:
            iid = by_name.get(n)
            kp = d.num_keypoints_for_image(iid) if iid is not None else 0
            if kp < 300:
                causes[n] = "too little texture (few features)"
            elif best.get(iid, 0) < 30:
                causes[n] = "too little overlap with other frames (fast motion or motion blur)"
            else:
                causes[n] = "matched but could not be placed (moving objects, repeated texture or weak geometry)"
    groups: dict[str, list[int]] = {}
    for n in missing:
        try:
            idx = frame_index(n.rsplit(".", 1)[0])
        except ValueError:
            idx = names_all.index(n)
        groups.setdefault(causes[n], []).append(idx)
    return [{"frames": _ranges(v), "count": len(v), "cause": c} for c, v in groups.items()]


def _ranges(ids: list[int]) -> str:
    """"0-4, 7, 9-12" of sorted frame indices."""
    if not ids:
        return ""
    ids = sorted(ids)
    out, start, prev = [], ids[0], ids[0]
    for v in ids[1:] + [None]:
        if v is not None and v == prev + 1:
            prev = v
            continue
        out.append(f"{start}-{prev}" if prev != start else str(start))
        if v is not None:
            start = prev = v
    return ", ".join(out)
