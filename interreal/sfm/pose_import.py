"""`interreal poses DS --poses FILE`: poses imported from a nerfstudio / Polycam transforms.json (kept as given) or
a COLMAP model (oriented as SfM's are) instead of running SfM. A pose file names images by file name, stem, or the
source file a frame was extracted from (reports/frames.json)."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from .. import provenance
from ..conventions import opencv_to_opengl
from ..dataset import (Frame, Intrinsics, camera_angle_intrinsics, image_hw, parse_transforms, read_transforms_file,
                       write_transforms)
from ..errors import InputError
from ..layout import IMAGES_DIR
from ..report import StageReport, report_path
from .colmap import load_pycolmap
from .config import SfMConfig
from .geometry import apply_similarity, camera_intrinsics, orientation_transform, rec_poses


def _name_lookup(ds: Path, images: list[Path]) -> dict[str, Path]:
    """Keys under which a pose file may name a dataset image: its name, its stem, and the source file it came from
    (reports/frames.json keeps frame name -> original file name for image folders)."""
    look: dict[str, Path] = {}
    for p in images:
        look.setdefault(p.name, p)
        look.setdefault(p.stem, p)
    frames_rep = report_path(ds, "frames")
    try:
        src_names = json.loads(frames_rep.read_text()).get("figures", {}).get("source_names", {})
    except (OSError, ValueError):
        src_names = {}
    by_stem = {p.stem: p for p in images}
    for stem, original in src_names.items():
        if stem in by_stem:
            look.setdefault(original, by_stem[stem])
            look.setdefault(Path(original).stem, by_stem[stem])
    return look


def _match_name(look: dict[str, Path], name: str) -> Path | None:
    base = Path(name).name
    return look.get(base) or look.get(Path(base).stem)


def import_poses(ds: Path, file: Path, images: list[Path], cfg: SfMConfig) -> dict[str, Any]:
    """Poses from a nerfstudio/Polycam transforms.json (kept as given) or a COLMAP model (oriented as SfM is)."""
    if not file.exists():
        raise InputError(f"--poses {file} does not exist")
    h, w = image_hw(images[0])
    look = _name_lookup(ds, images)
    with StageReport(ds, "poses", inputs={"images": len(images), "poses_file": str(file),
                                          "fingerprints": provenance.fingerprints(ds, ["images"])},
                     settings={"import": True, **asdict(cfg)}) as rep:
        if file.is_dir():
            frames, intr, T = _import_colmap(file, look, cfg)
            meta = {"applied_transform": T[:3, :].tolist(), "orientation_method": cfg.orientation}
        else:
            frames, intr = _import_transforms(file, look)
            T = np.eye(4)
            meta = {}
        if len(frames) < 3:
            raise InputError(f"--poses {file}: only {len(frames)} of its frames match images in {ds / IMAGES_DIR} "
                             "(matched by file name, stem, or the source file names in reports/frames.json)")
        intr = intr.scaled(w, h) if (intr.w, intr.h) != (w, h) else intr
        frames.sort(key=lambda f: f.file_path)
        write_transforms(ds, intr, frames, extra={**meta, "poses_imported_from": str(file)})
        matched = {Path(f.file_path).name for f in frames}
        missing = [p.name for p in images if p.name not in matched]
        if missing:
            rep.warn(f"{len(missing)} images have no pose in {file} and are left out of transforms.json "
                     f"(e.g. {missing[:3]})", cause="import")
        rep.figures.update({"registered": len(frames), "total": len(images),
                            "registered_frac": round(len(frames) / len(images), 4), "intrinsics": intr.to_json(),
                            "applied_transform": T.tolist(), "imported": str(file)})
        figures = dict(rep.figures)
    figures["wall_s"] = rep.data.get("wall_s")
    return figures


def _import_transforms(file: Path, look: dict[str, Path]) -> tuple[list[Frame], Intrinsics]:
    """Frames of a transforms.json whose images are in the dataset (by `look`), and its camera: the shared one,
    else the first frame's own (Polycam writes per-frame intrinsics of one camera), else `camera_angle_x`'s."""
    meta = read_transforms_file(file, f"--poses {file}", InputError,
                                frames_hint=" (expected a nerfstudio/Polycam transforms.json)")
    try:
        shared, parsed, _, _ = parse_transforms(meta)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"--poses {file}: a frame entry is unreadable ({exc})") from exc
    frames: list[Frame] = []
    per_frame: list[Intrinsics] = []
    for fr in parsed:
        p = _match_name(look, fr.file_path)
        if p is None or fr.c2w is None:
            continue
        if fr.intrinsics is not None:
            per_frame.append(fr.intrinsics)
        frames.append(Frame(file_path=f"{IMAGES_DIR}/{p.name}", c2w=fr.c2w))
    if shared is not None:
        intr = shared
    elif per_frame:
        intr = per_frame[0]
    elif "camera_angle_x" in meta and frames:
        hh, ww = image_hw(look[Path(frames[0].file_path).name])
        intr = camera_angle_intrinsics(meta["camera_angle_x"], ww, hh, camera_model="OPENCV")
    else:
        raise InputError(f"--poses {file} has no intrinsics (fl_x/fl_y/cx/cy/w/h or camera_angle_x)")
    return frames, intr


def _import_colmap(folder: Path, look: dict[str, Path], cfg: SfMConfig) -> tuple[list[Frame], Intrinsics, np.ndarray]:
    pycolmap = load_pycolmap(False)
    cands = [folder, folder / "0", folder / "sparse" / "0", folder / "sparse"]
    model = next((c for c in cands if (c / "images.bin").exists() or (c / "images.txt").exists()), None)
    if model is None:
        raise InputError(f"--poses {folder} holds no COLMAP model (images.bin / images.txt)")
    rec = pycolmap.Reconstruction(str(model))
    names, c2w_cv, ids = rec_poses(rec)
    keep = [(k, _match_name(look, n)) for k, n in enumerate(names)]
    keep = [(k, p) for k, p in keep if p is not None]
    if not keep:
        raise InputError(f"--poses {folder}: no image of the model matches {IMAGES_DIR}/")
    c2w_cv = c2w_cv[[k for k, _ in keep]]
    T = orientation_transform(c2w_cv, cfg.orientation, cfg.center_scale)
    c2w_gl = opencv_to_opengl(apply_similarity(T, c2w_cv))
    intr = camera_intrinsics(rec.cameras[rec.images[ids[keep[0][0]]].camera_id])
    frames = [Frame(file_path=f"{IMAGES_DIR}/{p.name}", c2w=m) for (_, p), m in zip(keep, c2w_gl)]
    return frames, intr, T
