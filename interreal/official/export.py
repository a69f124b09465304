"""`interreal export-official DS OUT`: a copy the official trainer reads with no NaN and no rescaled label.

The fraction split is kept when each object has a 1.0 and a 0 (a 0.0 label or an unlabelled frame) on both sides;
else frames move between the sides and transforms.json lists the split; what no split can keep is refused by name.
Also the `--scene-scale` that holds the scene after nerfstudio's own pose normalisation.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from .. import atomic
from ..conventions import LABELS_FILE, MAPPING_FILE, MASKS_DIR, TRANSFORMS_FILE, frame_id
from ..dataset import format_problems, load_dataset, read_labels, read_point_cloud, validate
from ..dataset.official import is_blender, label_columns
from ..errors import InputError
from .rules import SPLIT_KEYS, TOL, _norm_path, check_official, fraction_split, official_frames, read_meta


def _changed(rows: list[int], values: np.ndarray) -> set[int]:
    """Columns whose labels the official normalisation over `rows` would change (every column when empty): a column
    survives exactly when its zero-filled values reach 0 and 1 (labels lie in [0, 1])."""
    if not rows:
        return set(range(values.shape[1]))
    sub = values[rows]
    return {j for j in range(values.shape[1])
            if not (np.isclose(sub[:, j].max(), 1.0) and np.isclose(sub[:, j].min(), 0.0))}


def _labels_unsafe(names: list[str], values: np.ndarray, given: np.ndarray, fids: list[str]) -> list[str]:
    """Reasons no split can keep these labels unchanged (named per object)."""
    out = []
    for j, name in enumerate(names):
        if not given[:, j].any():
            out.append(f"'{name}' has no state label at all: every split would give NaN; label at least one frame "
                       f"where it is fully open (1.0) in each split")
            continue
        top = values[given[:, j], j].max()
        ones = [fids[i] for i in np.flatnonzero(given[:, j] & np.isclose(values[:, j], 1.0))]
        zeros = int((~given[:, j] | np.isclose(values[:, j], 0.0)).sum())
        if top < 1.0 - TOL:
            out.append(f"'{name}': its largest label is {top:g}, and the official reader rescales each object's "
                       f"labels so the largest reads 1.0; label a frame where it is fully open (1.0)")
        elif len(ones) < 2:
            out.append(f"'{name}': only {'frame ' + ones[0] if ones else 'no frame'} is labelled 1.0, and train "
                       f"and eval each need a frame at 1.0 (else the split's labels are rescaled or NaN); label "
                       f"another frame where it is fully open")
        elif zeros < 2:
            out.append(f"'{name}': fewer than two frames are labelled 0.0 or left unlabelled, and train and eval "
                       f"each need one (else the split's labels are rescaled)")
    return out


def _fill(dst: set[int], src: set[int], values: np.ndarray) -> tuple[set[int], set[int]]:
    """Move frames from `src` to `dst` until every column of `dst` holds a 0 and a 1, taking only frames whose
    loss leaves `src` no worse off; per column and target, the candidate in the middle of its run (a typical frame
    of that state)."""
    for j in range(values.shape[1]):
        for target in (1.0, 0.0):
            if any(np.isclose(values[i, j], target) for i in dst):
                continue
            cands = [i for i in sorted(src) if np.isclose(values[i, j], target)]
            mid = cands[len(cands) // 2] if cands else 0
            for i in sorted(cands, key=lambda i: abs(i - mid)):
                if _changed(sorted(src - {i}), values) <= _changed(sorted(src), values):
                    src, dst = src - {i}, dst | {i}
                    break
    return dst, src


def choose_split(fids: list[str], values: np.ndarray, names: list[str]) -> tuple[list[int], list[int], bool]:
    """(train, eval, explicit): the official fraction split when it keeps every label unchanged (explicit False);
    else that split with, per object, a frame at 1.0 / at 0 moved to the side that lacks one (only while the other
    side keeps its own), to be written as explicit file lists. InputError naming the objects when none exists."""
    train, ev = fraction_split(len(fids))
    if not _changed(train, values) and not _changed(ev, values):
        return train, ev, False
    ev_set, tr_set = _fill(set(ev), set(train), values)
    tr_set, ev_set = _fill(tr_set, ev_set, values)
    train, ev = sorted(tr_set), sorted(ev_set)
    bad = sorted(_changed(train, values) | _changed(ev, values))
    if bad:
        raise InputError("no train / eval split keeps the labels of " + ", ".join(repr(names[j]) for j in bad)
                         + " unchanged under the official normalisation: each split needs a frame where the object "
                         "is labelled 1.0 and one where it is labelled 0.0 or unlabelled")
    return train, ev, True


# ----------------------------------------------------------------------------------------------------------------
# Scene box: what nerfstudio's parser does to the poses, and the box that then holds the scene
# ----------------------------------------------------------------------------------------------------------------
def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation taking unit vector a to unit vector b (nerfstudio's rotation_matrix_between)."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v = np.cross(a, b)
    if np.linalg.norm(v) < 1e-8:
        if a @ b > 0:
            return np.eye(3)
        perp = np.eye(3)[int(np.argmin(np.abs(a)))]
        v = np.cross(a, perp)
        v /= np.linalg.norm(v)
        return 2 * np.outer(v, v) - np.eye(3)
    c = float(a @ b)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k * ((1 - c) / (np.linalg.norm(v) ** 2))


def nerfstudio_transform(c2w_gl: np.ndarray) -> tuple[np.ndarray, float]:
    """(3x4 transform, scale) of nerfstudio's real-data parser: orientation 'up', centre 'poses', auto scale
    (largest |camera coordinate| = 1)."""
    t = c2w_gl[:, :3, 3]
    centre = t.mean(axis=0)
    up = c2w_gl[:, :3, 1].mean(axis=0)
    rot = _rotation_between(up, np.array([0.0, 0.0, 1.0]))
    tf = np.concatenate([rot, (rot @ -centre)[:, None]], axis=1)
    moved = t @ rot.T + tf[:, 3]
    return tf, 1.0 / max(float(np.abs(moved).max()), 1e-9)


def scene_scale(root: Path, meta: dict[str, Any]) -> tuple[float, str]:
    """The `--scene-scale` that makes nerfstudio's box (+-scale, after its own pose normalisation) hold the scene:
    transforms.json's `aabb` when given, else the 1-99 % range of the SfM points (`ply_file_path`), and the
    cameras, plus 10 %."""

    c2w = np.array([np.asarray(f["transform_matrix"], np.float64)[:4, :4] for f in official_frames(meta)])
    tf, s = nerfstudio_transform(c2w)
    pts, src = c2w[:, :3, 3], "the cameras"
    box = None
    if "aabb" in meta:
        box, src = np.asarray(meta["aabb"], np.float64).reshape(2, 3), "transforms.json aabb and the cameras"
    else:
        cloud = read_point_cloud(root, meta)
        if cloud is not None and len(cloud) >= 10:
            box, src = np.percentile(cloud, [1, 99], axis=0), "the SfM points (1-99 %) and the cameras"
    if box is not None:
        lo, hi = box
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        pts = np.vstack([pts, corners])
    moved = (pts @ tf[:, :3].T + tf[:, 3]) * s
    return max(1.0, math.ceil(float(np.abs(moved).max()) * 1.1 * 10) / 10), src


def ns_train_command(out: Path, scale: float) -> str:
    """The official training command for an exported folder (method options before the dataparser subcommand)."""
    return (f"ns-train livescene --data {out} --pipeline.use-gt-val False livescene-real-data"
            + (f" --scene-scale {scale:g}" if scale != 1.0 else ""))


# ----------------------------------------------------------------------------------------------------------------
# Export
# ----------------------------------------------------------------------------------------------------------------
def export_official(ds: Path, out: Path) -> dict[str, Any]:
    """Write OUT (module doc): images, masks, mapping and labels as they are, transforms.json with explicit split
    lists when the fraction split would change a label; then check OUT with the official rules. Returns the log."""

    ds, out = Path(ds), Path(out)
    result = validate(ds)
    if not result.ok:
        raise InputError(f"{ds} is not a valid dataset, so it cannot be exported (check with `interreal validate "
                         f"{ds}`):\n{format_problems(result, per_kind=3)}")
    if out.exists() and any(out.iterdir()):
        raise InputError(f"{out} exists and is not empty: choose a new folder")
    if out.resolve() == ds.resolve() or ds.resolve() in out.resolve().parents:
        raise InputError(f"{out} is inside the dataset {ds}: choose a folder outside it")
    meta = read_meta(ds)
    if is_blender(meta):
        raise InputError(f"{ds} is already in the official OmniSim (Blender) layout: train it as it is with "
                         f"`livescene-sim-data`, or check it with `interreal export-official --check {ds}`")
    data = load_dataset(ds)
    frames = official_frames(meta)
    fids = [frame_id(str(f["file_path"])) for f in frames]
    names = data.object_names
    values, given = label_columns(fids, read_labels(ds), names)  # as stored: what the official reader will see
    outside = np.argwhere(given & ((values < 0) | (values > 1)))
    if len(outside):
        i, j = outside[0]
        raise InputError(f"{ds} stores raw values outside [0, 1] ('{names[j]}' = {values[i, j]:g} on frame {fids[i]}): "
                         f"it is official data already, which the official reader rescales as it was made to; train "
                         f"it as it is (check it with `interreal export-official --check {ds}`)")
    unsafe = _labels_unsafe(names, values, given, fids)
    if unsafe:
        raise InputError("the official reader would rescale these labels (or make them NaN), and no split avoids "
                         "it:\n  " + "\n  ".join(unsafe))
    train, ev, explicit = choose_split(fids, values, names)
    new_meta = {k: v for k, v in meta.items() if k not in SPLIT_KEYS}
    notes = [f"the official fraction split ({len(train)} train / {len(ev)} eval) keeps every label"]
    if explicit:
        notes = [f"the official fraction split would rescale labels (or give NaN), so transforms.json lists "
                 f"train_filenames / val_filenames / test_filenames: {len(train)} train / {len(ev)} eval frames (the "
                 f"fraction split, with frames at each object's 0 and 1 moved to the side that lacked one)"]
        paths = [str(f["file_path"]) for f in frames]
        new_meta["train_filenames"] = [paths[i] for i in train]
        new_meta["val_filenames"] = new_meta["test_filenames"] = [paths[i] for i in ev]
    tmp = out.with_name(f".{out.name}.partial")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    try:
        kept = _copy_files(ds, tmp, frames, fids, meta)
        atomic.write_json(tmp / TRANSFORMS_FILE, new_meta)
        scale, box_src = scene_scale(tmp, new_meta)
        check = check_official(tmp)
        if not check.ok:
            raise InputError("the exported folder still fails the official rules:\n  " + "\n  ".join(check.problems))
        log = {"source": str(ds), "frames": len(frames), "objects": names, "split": check.split,
               "notes": notes + [
                   "labels written as they are: each object's column holds a 1.0 and a 0 (a 0.0 label or an "
                   "unlabelled frame) in each split, so the official min-max normalisation (zeros included) leaves "
                   "every label unchanged and gives no NaN",
                   f"scene box: nerfstudio centres the cameras and scales them into +-1; the scene ({box_src}) then "
                   f"fits in +-{scale:g} (--scene-scale {scale:g}, offset 0 0 0)",
                   "not copied (the official code reads none of them): " + (", ".join(
                       sorted(p.name for p in ds.iterdir() if p.name not in kept)) or "nothing")] + check.notes,
               "scene_scale": scale, "command": ns_train_command(out, scale)}
        atomic.write_json(tmp / "export_official.json", log)
        if out.exists():
            out.rmdir()
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return log


def _copy_files(ds: Path, out: Path, frames: list[dict], fids: list[str], meta: dict) -> set[str]:
    """Copy what the official code reads (images, masks, mapping, labels, the point cloud); the top-level names
    written (transforms.json is written by the caller)."""
    kept = {TRANSFORMS_FILE, MAPPING_FILE, LABELS_FILE, MASKS_DIR}
    for name in (MAPPING_FILE, LABELS_FILE):
        shutil.copy2(ds / name, out / name)
    ply = _norm_path(str(meta.get("ply_file_path") or ""))
    if ply and (ds / ply).is_file():
        (out / ply).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ds / ply, out / ply)
        kept.add(Path(ply).parts[0])
    (out / MASKS_DIR).mkdir()
    for entry, fid in zip(frames, fids):
        rel = _norm_path(str(entry["file_path"]))
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ds / rel, out / rel)
        kept.add(Path(rel).parts[0])
        m = np.load(ds / MASKS_DIR / f"{fid}.npy", allow_pickle=False)
        atomic.write_npy(out / MASKS_DIR / f"{fid}.npy", m.astype(bool))
    return kept
