"""`validate`: every problem that stops the official reader or would make training wrong, listed (never raised),
and the `interreal validate` command."""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ..conventions import frame_id, frame_index, mask_file
from ..errors import DatasetError
from ..layout import (ARTICULATION_FILE, IMAGES_DIR, LABELS_FILE, MAPPING_FILE, PROMPTS_FILE, REPORTS_DIR,
                      TRANSFORMS_FILE)
from ..provenance import stale_stages
from ..transients import TRANSIENTS_DIR, problems as transient_problems
from ..images import image_size, list_images
from .official import is_official_data, raw_value_ok
from .io import (label_value_problem, npy_header, pose_matrix, read_articulation, read_prompts, read_yaml,
                 resolve_blender_path)
from .types import CAMERA_MODELS, DISTORTION_KEYS, INTRINSIC_KEYS


# ----------------------------------------------------------------------------------------------------------------
# Validation
# ----------------------------------------------------------------------------------------------------------------
@dataclass
class Problem:
    kind: str  # a stable class name, e.g. "mask-not-onehot"; tests and tools match on it
    where: str
    message: str

    def __str__(self) -> str:
        return f"[{self.kind}] {self.where}: {self.message}"


@dataclass
class ValidationResult:
    root: Path
    problems: list[Problem]
    summary: dict[str, Any]
    warnings: list[str] = field(default_factory=list)  # usable, but training will suffer (e.g. too few labels)

    @property
    def ok(self) -> bool:
        return not self.problems

    def kinds(self) -> set[str]:
        return {p.kind for p in self.problems}


def validate(root: str | Path, check_masks: bool = True) -> ValidationResult:
    """Every problem that stops the official reader (or would make training wrong); never raises on garbage.

    Also names stages whose inputs changed since they ran (`interreal.provenance`: stale poses, masks, labels,
    motions). `check_masks=False` is the quick mode for tools that validate before they start (`livescene`): image
    and mask headers, end markers and staleness only, no per-pixel decoding (about 0.5 s for 300 frames instead of
    10+ s); everything else is checked the same way, by the same code."""
    root = Path(root)
    problems: list[Problem] = []
    summary: dict[str, Any] = {"root": str(root)}

    def add(kind: str, where: str | Path, message: str) -> None:
        problems.append(Problem(kind, str(where), message))

    if not root.is_dir():
        add("no-dataset", root, "not a folder")
        return ValidationResult(root, problems, summary)

    meta = _validate_transforms_json(root, add)
    frames = _validate_frames(root, meta, add) if meta is not None else []
    summary["frames"] = len(frames)
    mapping = _validate_mapping(root, add)
    summary["objects"] = [mapping[i] for i in sorted(mapping)] if mapping else []
    labels, unposed = _validate_labels(root, mapping, frames, add)
    summary["labels_per_object"] = _labels_per_object(labels, mapping)
    warnings = [m for _, m in label_shortage(summary["labels_per_object"], len(frames))] if frames else []
    if unposed:
        warnings.append(f"{LABELS_FILE} labels frame(s) {', '.join(map(str, sorted(unposed)))} that have no camera "
                        f"pose (SfM did not register them): those labels are not used; label a registered frame instead")
    prompts = _read_prompts_or_none(root, add)
    undescribed = [n for n in summary["objects"] if not prompts.get(n)] if mapping and prompts is not None else []
    summary["described"] = len(summary["objects"]) - len(undescribed)
    if undescribed:
        warnings.append(f"{PROMPTS_FILE} has no description of {', '.join(repr(n) for n in undescribed)}: text "
                        f"grounding finds them by name alone (\"the fridge\", not \"what keeps food cold\"); add "
                        f"one with `interreal label DS --describe NAME TEXT`, in the annotate app, or "
                        f"`interreal process ... --prompts FILE`")
    sizes = _validate_images(root, frames, meta, add, decode=check_masks)
    summary["size"] = sorted({f"{w}x{h}" for (w, h) in sizes.values()})
    _validate_masks(root, frames, mapping, sizes, add, pixels=check_masks)
    for kind, where, message in transient_problems(root, [fid for fid, _ in frames], sizes, check_masks):
        add(kind, where, message)  # the transient layer (people, hands) beside the official files
    summary["transients"] = len(list((root / TRANSIENTS_DIR).glob("*.png"))) if (root / TRANSIENTS_DIR).is_dir() else 0
    summary["masks"] = bool(frames) and all(mask_file(root, fid).exists() for fid, _ in frames)
    summary["poses"] = sum(1 for _, e in frames if "transform_matrix" in e)
    summary["articulated"] = _validate_articulation(root, mapping, add)
    _validate_reports(root, add)
    _validate_provenance(root, add)
    return ValidationResult(root, problems, summary, warnings)


def _validate_transforms_json(root: Path, add) -> dict | None:
    path = root / TRANSFORMS_FILE
    if not path.exists():
        add("no-transforms", path, "missing: run `interreal poses DS` (or import poses with --poses FILE)")
        return None
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        add("bad-json", path, f"not valid JSON: {exc}")
        return None
    if not isinstance(meta, dict):
        add("bad-json", path, "top level is not an object")
        return None
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        add("no-frames", path, "'frames' is missing or empty")
        return None
    if "camera_angle_x" in meta and "fl_x" not in meta:
        angle = meta.get("camera_angle_x")
        if not isinstance(angle, (int, float)) or not (0 < float(angle) < math.pi):
            add("bad-intrinsics", path, f"camera_angle_x={angle!r} is not an angle in (0, pi) radians")
        return meta
    for i, entry in enumerate(frames):
        if not isinstance(entry, dict):
            continue
        merged = {**meta, **entry}
        where = f"{path.name} frames[{i}]" if any(k in entry for k in INTRINSIC_KEYS) else path.name
        missing = [k for k in INTRINSIC_KEYS if k not in merged]
        if missing:
            add("missing-intrinsics", where, f"missing keys {missing}")
            if where == path.name:
                break
            continue
        try:
            vals = {k: float(merged[k]) for k in INTRINSIC_KEYS + tuple(k for k in DISTORTION_KEYS if k in merged)}
        except (TypeError, ValueError):
            add("bad-intrinsics", where, "intrinsics must be numbers")
            continue
        if not all(math.isfinite(v) for v in vals.values()):
            add("bad-intrinsics", where, "intrinsics must be finite")
        elif vals["w"] <= 0 or vals["h"] <= 0 or vals["fl_x"] <= 0 or vals["fl_y"] <= 0:
            add("bad-intrinsics", where, "w, h, fl_x and fl_y must be positive")
        elif not (0 < vals["cx"] < vals["w"] and 0 < vals["cy"] < vals["h"]):
            add("bad-intrinsics", where, f"principal point ({vals['cx']}, {vals['cy']}) is outside the image")
        model = merged.get("camera_model", "OPENCV")
        if model not in CAMERA_MODELS:
            add("bad-intrinsics", where, f"camera_model {model!r} is not one of {CAMERA_MODELS}")
        if where == path.name:
            break
    return meta


def _validate_frames(root: Path, meta: dict, add) -> list[tuple[str, dict]]:
    """Checks each frame entry; returns (fid, entry) for entries whose image path and id are usable."""
    path = root / TRANSFORMS_FILE
    blender = "camera_angle_x" in meta and "fl_x" not in meta
    seen: dict[int, str] = {}
    out: list[tuple[str, dict]] = []
    for i, entry in enumerate(meta["frames"]):
        where = f"{path.name} frames[{i}]"
        if not isinstance(entry, dict) or "file_path" not in entry:
            add("bad-frame", where, "frame entry has no file_path")
            continue
        fp = str(entry["file_path"])
        fp = resolve_blender_path(root, fp) if blender else (fp[2:] if fp.startswith("./") else fp)
        entry = {**entry, "file_path": fp}
        norm = os.path.normpath(fp)
        if Path(fp).is_absolute() or os.path.isabs(norm) or norm == ".." or norm.startswith(".." + os.sep):
            add("bad-file-path", where, f"file_path {fp!r} leaves the dataset folder: paths must be relative to it "
                f"(e.g. images/frame_00042.png)")
            continue
        fid = frame_id(fp)
        if not fid.isdigit():
            add("bad-frame-id", where, f"frame id '{fid}' of {fp} is not a number (name frames like frame_00042.png)")
            continue
        if int(fid) in seen:
            add("duplicate-frame-id", where, f"frame id {fid} of {fp} is also used by {seen[int(fid)]}")
            continue
        seen[int(fid)] = fp
        if "transform_matrix" not in entry:
            add("bad-pose", where, "no transform_matrix")
            continue
        try:
            m = pose_matrix(entry["transform_matrix"])
        except (TypeError, ValueError) as exc:
            add("bad-pose", where, f"transform_matrix unreadable: {exc}")
            continue
        if not np.all(np.isfinite(m)):
            add("bad-pose", where, "transform_matrix has non-finite values")
            continue
        r = m[:3, :3]
        orth = float(np.abs(r.T @ r - np.eye(3)).max())
        det = float(np.linalg.det(r))
        if orth > 1e-3 or abs(det - 1) > 1e-3:
            add("bad-rotation", where, f"rotation is not orthonormal with det +1 (max |RtR-I|={orth:.2e}, det={det:.4f})")
            continue
        if not np.allclose(m[3], [0, 0, 0, 1]):
            add("bad-pose", where, f"last row is {m[3].tolist()}, expected [0, 0, 0, 1]")
            continue
        out.append((fid, entry))
    return out


def _read_checked_yaml(path: Path, add, missing_code: str, missing_hint: str) -> tuple[bool, Any]:
    """(readable, content) of a dataset YAML file; a missing or unparsable file is reported through `add`."""
    if not path.exists():
        add(missing_code, path, f"missing: {missing_hint}")
        return False, None
    try:
        return True, read_yaml(path)
    except (OSError, yaml.YAMLError, UnicodeDecodeError) as exc:
        add("bad-yaml", path, f"not valid YAML: {exc}")
        return False, None


def _validate_mapping(root: Path, add) -> dict[int, str]:
    path = root / MAPPING_FILE
    ok, raw = _read_checked_yaml(path, add, "no-mapping",
                                 "name the objects with `interreal label DS --add-object NAME` or `interreal masks`")
    if not ok:
        return {}
    if not isinstance(raw, dict) or not raw:
        add("bad-mapping", path, "expected a non-empty mapping {0: 'name', 1: 'name', ...}")
        return {}
    mapping: dict[int, str] = {}
    for k, v in raw.items():
        if not isinstance(k, int) or isinstance(k, bool):
            add("bad-mapping", path, f"object id {k!r} is not an integer")
            continue
        if not isinstance(v, str) or not v.strip():
            add("bad-mapping", path, f"object {k} has no name")
            continue
        mapping[k] = v
    if mapping and sorted(mapping) != list(range(len(mapping))):
        add("bad-mapping", path, f"object ids {sorted(mapping)} are not contiguous from 0")
    names = list(mapping.values())
    dups = sorted({n for n in names if names.count(n) > 1})
    if dups:
        add("bad-mapping", path, f"names used twice: {dups}")
    return mapping


def _validate_labels(root: Path, mapping: dict[int, str], frames: list[tuple[str, dict]], add
                     ) -> tuple[dict, list[int]]:
    """(the labels that training can use, the frames labelled that were extracted but have no pose). A label on an
    unposed frame (SfM did not register it) is a warning, not a problem: a re-run of `poses` may drop a frame it
    held before."""
    path = root / LABELS_FILE
    ok, raw = _read_checked_yaml(path, add, "no-labels", "set keyframe states with `interreal label DS --set NAME FRAME VALUE`")
    if not ok:
        return {}, []
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        add("bad-labels", path, "expected {frame_00042: {object name: value}}")
        return {}, []
    names = set(mapping.values())
    frame_numbers = {int(fid) for fid, _ in frames}
    extracted: set[int] | None = None  # DS/images listed only when a label names a frame without a pose
    good: dict[str, dict[str, float]] = {}
    unposed: list[int] = []

    official = is_official_data(root)
    for key, entry in raw.items():
        where = f"{path.name}[{key}]"
        try:
            idx = frame_index(str(key))
        except ValueError:
            add("bad-labels", where, "key does not end in a frame number (use frame_00042)")
            continue
        if frames and idx not in frame_numbers:
            extracted = _extracted_frames(root) if extracted is None else extracted
            if idx in extracted:  # SfM left it out: the label is not used, and the dataset stays usable
                unposed.append(idx)
                continue
            add("label-unknown-frame", where, f"frame {idx} is not in transforms.json")
        if not isinstance(entry, dict):
            add("bad-labels", where, "expected {object name: value}")
            continue
        for name, value in entry.items():
            if mapping and name not in names:
                add("label-unknown-object", where, f"object {name!r} is not in mapping.yaml ({sorted(names)})")
                continue
            why = label_value_problem(value)
            if why is not None and not (official and raw_value_ok(value)):  # official raw values: load_dataset
                add("label-bad-value", where, f"{name}: {why} (states are numbers in [0, 1]; fix it with "
                    f"`interreal label DS --set {name!r} {key} VALUE` or --unset)")
                continue
            good.setdefault(str(key), {})[str(name)] = float(value)
    return good, unposed


def _extracted_frames(root: Path) -> set[int]:
    """Frame numbers of the images in DS/images/, posed or not."""
    out = set()
    for p in list_images(root / IMAGES_DIR):
        try:
            out.add(frame_index(p.stem))
        except ValueError:
            continue
    return out


# fewer state labels than these leave a part's states unpinned (bench_train label sweep: state MAE 0.15 at 5 % labels
# vs 0.057 at 10 %); `validate` warns on all frames, `livescene train` on its training frames, with the same figures
MIN_LABELS = 3
MIN_LABEL_FRACTION = 0.08


def label_shortage(labelled: dict[str, int], n_frames: int) -> list[tuple[str, str]]:
    """(object, message) for each object whose labelled frames (of n_frames) are too few to pin its states down."""
    n = max(n_frames, 1)
    return [(name, f"'{name}' has state labels on only {k} of {n} frames ({k / n:.0%}): its states on the other "
                   f"frames may be wrong; label about 10 % of the frames (`interreal label DS --set '{name}' FRAME "
                   f"VALUE`)")
            for name, k in labelled.items() if k < MIN_LABELS or k / n < MIN_LABEL_FRACTION]


def _labels_per_object(labels: dict, mapping: dict[int, str]) -> dict[str, int]:
    counts = {mapping[i]: 0 for i in sorted(mapping)}
    for entry in labels.values():
        for name in entry:
            if name in counts:
                counts[name] += 1
    return counts


def _validate_images(root: Path, frames: list[tuple[str, dict]], meta: dict | None, add,
                     decode: bool = True) -> dict[str, tuple[int, int]]:
    sizes: dict[str, tuple[int, int]] = {}
    for fid, entry in frames:
        path = root / entry["file_path"]
        if not path.exists():
            add("missing-image", path, "image listed in transforms.json does not exist")
            continue
        size = image_size(path, decode)
        if size is None:
            add("bad-image", path, "not a readable image (truncated or not an image file)")
            continue
        sizes[fid] = size
        merged = {**(meta or {}), **entry}
        if "w" in merged and "h" in merged:
            try:
                if (int(merged["w"]), int(merged["h"])) != size:
                    add("image-size", path, f"image is {size[0]}x{size[1]} but transforms.json says {merged['w']}x{merged['h']}")
            except (TypeError, ValueError):
                pass
    if len(set(sizes.values())) > 1:
        add("mixed-sizes", root / IMAGES_DIR, f"images have different sizes: {sorted(set(sizes.values()))}")
    return sizes


def _validate_masks(root: Path, frames, mapping: dict[int, str], sizes: dict[str, tuple[int, int]], add,
                    pixels: bool = True) -> None:
    """Each mask's header (shape, dtype, channels: fast) and, with `pixels`, that every pixel has one channel."""
    if not frames:
        return
    n_channels = len(mapping) + 1 if mapping else None

    official = is_official_data(root)
    for fid, entry in frames:
        path = mask_file(root, fid)
        if not path.exists():
            add("missing-mask", path, f"no mask for {entry['file_path']} (run `interreal masks DS --keyframes DIR`)")
            continue
        try:
            shape, dtype = npy_header(path)
        except (OSError, ValueError) as exc:
            add("bad-mask", path, f"unreadable .npy: {exc}; re-run `interreal masks`")
            continue
        if len(shape) != 3:
            add("bad-mask", path, f"{len(shape)}-D array of shape {shape}: expected (H, W, objects + 1) with one "
                "channel per object and the background last; re-run `interreal masks`")
            continue
        if dtype != np.dtype(bool):
            add("bad-mask", path, f"stored as {dtype}, not bool: a mask is true/false per channel (a float 0.5 would "
                "read as true everywhere); re-run `interreal masks`")
            continue
        if fid in sizes and (shape[1], shape[0]) != sizes[fid]:
            add("mask-size", path, f"mask is {shape[1]}x{shape[0]}, image is {sizes[fid][0]}x{sizes[fid][1]}")
            continue
        if n_channels is not None and shape[2] != n_channels:
            add("mask-channels", path, f"{shape[2]} channels, expected {n_channels} ({len(mapping)} objects + "
                "background last): the object list changed after the masks were made; re-run `interreal masks`")
            continue
        if not pixels:
            continue
        try:
            m = np.load(path, allow_pickle=False)
        except Exception as exc:  # noqa: BLE001 - truncated/garbage .npy is a listed problem
            add("bad-mask", path, f"unreadable .npy: {exc}; re-run `interreal masks`")
            continue
        count = m.sum(axis=2)
        wrong = (count > 1) if official else (count != 1)  # official data: a pixel with no channel is unknown
        bad = int(wrong.sum())
        if bad:
            ys, xs = np.nonzero(wrong)
            add("mask-not-onehot", path, f"{bad} pixels do not have exactly one channel set (first at x={xs[0]}, y={ys[0]})")


def _validate_articulation(root: Path, mapping: dict[int, str], add) -> list[str]:
    """Objects with a motion in the optional `articulation.json` (each must name an object of mapping.yaml)."""
    if not (root / ARTICULATION_FILE).exists():
        return []
    try:
        motions = read_articulation(root)
    except DatasetError as exc:
        add("bad-articulation", root / ARTICULATION_FILE, str(exc))
        return []
    names = set(mapping.values())
    for name in motions:
        if mapping and name not in names:
            add("bad-articulation", root / ARTICULATION_FILE, f"object {name!r} is not in mapping.yaml ({sorted(names)})")
    return [n for n in motions if n in names]


def _validate_reports(root: Path, add) -> None:
    folder = root / REPORTS_DIR
    if not folder.is_dir():
        return
    for path in sorted(folder.glob("*.json")):
        try:
            rep = json.loads(path.read_text())
        except (OSError, ValueError, UnicodeDecodeError):
            add("bad-report", path, "not valid JSON")
            continue
        status = rep.get("status") if isinstance(rep, dict) else None
        if not isinstance(rep, dict) or status not in ("running", "failed", "ok"):
            add("bad-report", path, f"no valid status ({status!r}): the stage's report is damaged; re-run the stage")
            continue
        if status in ("running", "failed"):
            add("stage-incomplete", path, f"stage '{rep.get('stage', path.stem)}' is {status}: "
                f"{rep.get('error', 'it did not finish')}; re-run it")


def _validate_provenance(root: Path, add) -> None:
    """Stages whose inputs changed since they ran (frames from another video, masks propagated again, ...)."""
    try:
        stale = stale_stages(root)
    except OSError as exc:
        add("stale", root / REPORTS_DIR, f"cannot compare the stages' inputs ({exc})")
        return
    for s in stale:
        add("stale", root / REPORTS_DIR / f"{s.stage}.json", s.message.removeprefix("stale: "))


def format_summary(result: ValidationResult) -> str:
    s = result.summary
    lines = [f"LiveScene dataset {s['root']}: OK",
             f"  frames   {s.get('frames', 0)}  (poses: {s.get('poses', 0)}, masks: {'yes' if s.get('masks') else 'no'}"
             + (f", transients: {s['transients']}" if s.get("transients") else "") + ")",
             f"  size     {', '.join(s.get('size', [])) or '?'}",
             f"  objects  {len(s.get('objects', []))}"]
    for name, n in s.get("labels_per_object", {}).items():
        lines.append(f"    - {name}: {n} labelled frames")
    return "\n".join(lines)


def _read_prompts_or_none(root: Path, add) -> dict[str, str] | None:
    """DS/prompts.yaml, or None (and a `bad-prompts` problem) when it cannot be read."""
    try:
        return read_prompts(root)
    except (DatasetError, OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        add("bad-prompts", root / PROMPTS_FILE, f"unreadable ({exc}); it maps object names to one-line descriptions")
        return None


def format_problems(result: ValidationResult, per_kind: int = 0) -> str:
    """Every problem (or the first `per_kind` of each kind), after a count per kind."""
    counts: dict[str, int] = {}
    for p in result.problems:
        counts[p.kind] = counts.get(p.kind, 0) + 1
    lines = [f"{result.root}: {len(result.problems)} problem(s): "
             + ", ".join(f"{n} {k}" for k, n in counts.items())]
    shown: dict[str, int] = {}
    for p in result.problems:
        shown[p.kind] = shown.get(p.kind, 0) + 1
        if per_kind and shown[p.kind] > per_kind:
            if shown[p.kind] == per_kind + 1:
                lines.append(f"  ... and {counts[p.kind] - per_kind} more [{p.kind}] (without --brief: all of them)")
            continue
        lines.append(f"  {p}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------------------------
# CLI: interreal validate
# ----------------------------------------------------------------------------------------------------------------
def add_arguments(p) -> None:
    p.add_argument("dataset", type=Path, help="dataset folder")
    p.add_argument("--no-masks", action="store_true",
                   help="quick mode: image and mask headers only, no per-pixel decoding (what livescene runs)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--brief", action="store_true", help="list only the first 10 problems of each kind")
    p.epilog = ("examples:\n  interreal validate out/room\n  interreal validate out/room --brief\n"
                "  interreal validate out/room --json | jq .problems")


def main(args) -> int:
    result = validate(args.dataset, check_masks=not args.no_masks)
    if args.json:
        print(json.dumps({"ok": result.ok, "summary": result.summary, "warnings": result.warnings,
                          "problems": [p.__dict__ for p in result.problems]}, indent=2))
    else:
        print(format_summary(result) if result.ok else format_problems(result, per_kind=10 if args.brief else 0))
        for w in result.warnings:  # a warning, not a problem: the dataset is usable, its exit status stays 0
            print(f"  warning: {w}")
    return 0 if result.ok else 1
