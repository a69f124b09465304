"""The pose stage: `estimate_poses(DS)` runs (or resumes) SfM on DS/images and writes transforms.json,
colmap/sparse/0, sparse_pc.ply and reports/poses.json, or imports a pose file instead (`pose_import`)."""

from __future__ import annotations

import json
import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .. import atomic, provenance
from ..conventions import frame_id
from ..dataset import image_hw, list_images
from ..errors import InputError, LowParallaxError, StageError
from ..layout import IMAGES_DIR, MASKS_DIR, SFM_MASKS_DIR, TRANSFORMS_FILE, UNDISTORTED_DIR
from ..options import config_from
from ..report import StageReport, files_fingerprint, fingerprint
from ..transients import read_transient, transient_file
from . import colmap, parallax
from .config import (BA_LOSSES, SfMConfig, fine_frames, ladder, resolve_octave, use_track_extension,
                     use_track_refinement)
from .export import export
from .intrinsics import read_intrinsics, scaled_to
from .ladder import Workspace, diagnose, extract, keep_models, polish, run_ladder
from .pose_import import import_poses


NOT_IN_MODEL = ("verbose", "undistort", "allow_low_parallax", "intrinsics")  # settings left out of the final model's
# fingerprint: no effect on it, or (the intrinsics) already in the features' fingerprint by value


def estimate_poses(ds: str | Path, **opts: Any) -> dict[str, Any]:
    """Run (or resume) SfM on DS/images and write transforms.json, colmap/sparse/0, sparse_pc.ply, reports/poses.json.

    Options are `SfMConfig` fields, plus `poses=FILE` to import a transforms.json / COLMAP model instead.
    Returns the report's figures.
    """
    ds = Path(ds)
    poses_file = opts.pop("poses", None)
    cfg = make_config(**opts)
    images = list_images(ds / IMAGES_DIR)
    if len(images) < 3:
        raise InputError(f"{ds / IMAGES_DIR} has {len(images)} images; run `interreal frames INPUT {ds}` first "
                         "(at least 3 frames are needed)")
    _check_sizes(images)
    if poses_file is not None:
        if cfg.intrinsics:
            raise InputError("give --poses or --intrinsics, not both: an imported pose file carries its own camera")
        return import_poses(ds, Path(poses_file), images, cfg)
    h0, w0 = image_hw(images[0])
    known, known_note = scaled_to(read_intrinsics(cfg.intrinsics), ds, (w0, h0)) if cfg.intrinsics else (None, "")
    settings = asdict(cfg)
    fps = provenance.fingerprints(ds, ["images"])  # what validate compares later (stale poses)
    with StageReport(ds, "poses", inputs={"images": len(images), "fingerprints": fps}, settings=settings) as rep:
        ws = Workspace(colmap.load_pycolmap(cfg.verbose), ds, cfg, rep, [p.name for p in images])
        ws.work.mkdir(parents=True, exist_ok=True)
        ws.state = _load_state(ws.state_path)
        ws.known = known
        if known is not None:
            rep.figures["intrinsics_given"] = {**known.to_json(), "note": known_note,
                                               "held": not cfg.intrinsics_refine}
        ws.mask_dir, mask_src, mask_files = prepare_masks(ds, images, ws.work) if cfg.use_masks else (None, "off", [])
        if mask_src in ("sfm_masks", "masks.npy"):
            kinds = ["sfm_masks"] if mask_src == "sfm_masks" else ["masks", "transients"]
            fps.update(provenance.fingerprints(ds, kinds))
        rep.data["inputs"]["masks"] = {"source": mask_src, "files": len(mask_files)}
        if cfg.use_masks and mask_src == "none":
            rep.warn("no object masks (DS/masks or DS/sfm_masks): moving parts may corrupt poses; run "
                     "`interreal masks DS --keyframes DIR` first", cause="no-masks")
        octave, side = resolve_octave(cfg, images[0]), max(h0, w0)
        fine = fine_frames(cfg, len(images), octave, side)
        fp_feat = fingerprint("features", files_fingerprint(images), files_fingerprint(mask_files) if mask_files else None,
                              cfg.sfm_long_side, cfg.max_features, octave, cfg.camera_model, fine,
                              *([known.colmap_params()] if known is not None else []))  # refining them: mapping only
        with rep.step("features") as st:
            if ws.state.get("features") == fp_feat and ws.db.exists():
                st["reused"] = True
            else:
                ws.state = {"features": fp_feat}
                with ws.log() as log:
                    extract(ws, octave, set(fine), log)
                ws.save_state()
                st["reused"] = False
            with ws.pc.Database.open(str(ws.db)) as d:
                st["keypoints_mean"] = round(d.num_keypoints() / max(1, d.num_images()), 1)
        extend = use_track_extension(cfg, len(images), side)
        rungs = ladder(cfg, len(images), mixed_octaves=len(fine) < len(images), extended=extend)
        fp_final = fingerprint(fp_feat, {k: v for k, v in settings.items() if k not in NOT_IN_MODEL},
                               [asdict(r) for r in rungs])
        final = ws.sparse / "0"
        if ws.state.get("final") == fp_final and (ds / TRANSFORMS_FILE).exists() and final.exists():
            rep.steps["reuse"] = {"wall_s": 0.0, "reused": True}
            rec = ws.pc.Reconstruction(str(final))
        else:
            check_parallax(ws, (w0, h0))
            attempt, tried = run_ladder(ws, rungs, fp_feat)
            rec = polish(ws, attempt.rec, use_track_refinement(cfg, len(images), side), extend)
            keep_models(ws, attempt, rec, tried)
        _report_registration(ws, rec)
        if cfg.undistort:
            with rep.step("undistort"), ws.log():
                und = ds / UNDISTORTED_DIR
                shutil.rmtree(und, ignore_errors=True)
                ws.pc.undistort_images(str(und), str(final), str(ws.images), num_threads=colmap.threads(cfg.num_threads))
        with rep.step("export") as st:
            out = export(ds, rec, cfg)
            st.update(frames=out["frames"])
        rep.figures["intrinsics"] = out["intrinsics"]
        rep.figures["applied_transform"] = out["applied_transform_4x4"]
        ws.state["final"] = fp_final
        ws.save_state()
        figures = dict(rep.figures)
    figures["wall_s"] = rep.data.get("wall_s")
    figures["steps"] = {k: v.get("wall_s") for k, v in rep.steps.items()}
    return figures


def check_parallax(ws: Workspace, size: tuple[int, int]) -> None:
    """Refuse in seconds, before any mapping, a capture whose camera only turned or stood still
    (`parallax.measure`: no sampled frame pair shows the parallax a triangulation needs); with
    --allow-low-parallax only warn. Figures and time go to the report's step "parallax". size: the frames' (w, h)."""
    rep, cfg = ws.rep, ws.cfg
    with rep.step("parallax") as st:
        noise = max(1.0, max(size) / cfg.sfm_long_side)  # keypoints come back in full-size pixels
        res = parallax.measure(ws.pc, ws.db, ws.names, size, noise, None if ws.known is None else ws.known.K)
        st.update(res.figures())
    rep.figures["parallax"] = res.figures()
    if not res.low():
        return
    if not cfg.allow_low_parallax:
        raise LowParallaxError(res.message(ws.names))
    rep.warn(f"the camera barely moved ({res.finding(ws.names)}); mapping anyway (--allow-low-parallax)",
             cause="low-parallax")


def make_config(**opts: Any) -> SfMConfig:
    """`SfMConfig` from keyword options (None = the default); InputError naming an unknown or bad option."""
    cfg = config_from(SfMConfig, opts, "pose")
    if cfg.ba_loss not in BA_LOSSES:
        raise InputError(f"ba_loss must be one of {', '.join(BA_LOSSES)}, not {cfg.ba_loss!r}")
    return cfg


def _report_registration(ws: Workspace, rec) -> None:
    """Figures of the kept model, a warning per group of frames that did not register (with its likely cause);
    StageError when too few registered to train on."""
    rep, cfg = ws.rep, ws.cfg
    total = len(ws.names)
    stats = colmap.model_stats(rec)
    frac = stats["registered"] / total
    reg_names = {rec.images[i].name for i in rec.reg_image_ids()}
    dropped = diagnose(ws.pc, ws.db, ws.names, reg_names)
    for g in dropped:
        rep.warn(f"frames {g['frames']} did not register: {g['cause']}", cause=g["cause"], frames=g["frames"])
    rep.figures.update({"registered": stats["registered"], "total": total, "registered_frac": round(frac, 4),
                        **{k: v for k, v in stats.items() if k != "registered"}, "unregistered": dropped})
    if frac < cfg.fail_below:
        raise StageError(f"SfM registered only {stats['registered']}/{total} frames ({frac:.0%} < "
                         f"{cfg.fail_below:.0%}); causes: {'; '.join(g['cause'] for g in dropped) or '?'}. "
                         "Film slower with more overlap and texture, or give masks of moving objects")
    if frac < 0.8:
        rep.warn(f"only {frac:.0%} of frames registered; training will see fewer views", cause="low-registration")


def prepare_masks(ds: Path, images: list[Path], work: Path) -> tuple[Path | None, str, list[Path]]:
    """Folder of COLMAP masks (<image name>.png, 255 = use) or None; also a label of the source and its files.

    DS/sfm_masks/ (written by `interreal masks`) wins; else masks are derived from DS/masks/<fid>.npy, where the
    background channel (last) less the transient layer (DS/transients/, people and hands) is what SfM may use.
    """
    given = ds / SFM_MASKS_DIR
    if given.is_dir() and any(given.glob("*.png")):
        files = [given / f"{p.name}.png" for p in images if (given / f"{p.name}.png").exists()]
        return given, "sfm_masks", files
    npy_dir = ds / MASKS_DIR
    if not npy_dir.is_dir():
        return None, "none", []
    out = work / "masks"
    out.mkdir(parents=True, exist_ok=True)
    used = []
    for p in images:
        src = npy_dir / f"{frame_id(p)}.npy"
        if not src.exists():
            continue
        used.append(src)
        dst = out / f"{p.name}.png"
        tr_file = transient_file(ds, frame_id(p))
        newest = max(src.stat().st_mtime_ns, tr_file.stat().st_mtime_ns if tr_file.exists() else 0)
        if dst.exists() and dst.stat().st_mtime_ns >= newest:
            continue
        m = np.load(src, allow_pickle=False)
        use = m[..., -1].astype(bool) if m.ndim == 3 else m.astype(bool)
        tr = read_transient(ds, frame_id(p), use.shape)
        use = (use & ~tr if tr is not None else use).astype(np.uint8) * 255
        h, w = image_hw(p)
        if use.shape != (h, w):
            use = cv2.resize(use, (w, h), interpolation=cv2.INTER_NEAREST)
        atomic.write_image(dst, use)
    return (out if used else None), ("masks.npy" if used else "none"), used


def _load_state(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _check_sizes(images: list[Path]) -> None:
    sizes: dict[tuple[int, int], str] = {}
    for p in images:
        try:
            h, w = image_hw(p)
        except Exception as exc:  # noqa: BLE001 - any decode failure is bad input
            raise InputError(f"{p} is not a readable image ({exc}); re-run `interreal frames`") from exc
        sizes.setdefault((w, h), p.name)
    if len(sizes) > 1:
        raise InputError(f"images in one dataset must share one size, found {sorted(sizes)} "
                         f"(e.g. {list(sizes.values())[:2]}); re-run `interreal frames`")
