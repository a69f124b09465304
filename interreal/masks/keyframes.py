"""Keyframe annotations (`--keyframes DIR`): index-mask PNGs or LabelMe JSON, checked before anything is written.

- `DIR/<fid>.png`: 8-bit index map, 0 = background, k = object k-1, 255 = not annotated. An object with no
  pixel on an annotated keyframe is out of view there (that is how leaving / re-entering is said).
- `DIR/<fid>.json`: LabelMe; `shapes[].label` = object name, `shape_type` polygon or rectangle. A rectangle
  means "the object is inside this box" and is cut out with GrabCut. Pixels outside every shape are background.
- `DIR/mapping.yaml` names the objects (PNG ids refer to it); the dataset's mapping.yaml wins when it exists.
Every problem raises InputError naming the file and what to do.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from ..conventions import MAPPING_FILE, UNANNOTATED, frame_id
from ..errors import InputError


@dataclass
class Keyframes:
    masks: dict[str, np.ndarray]   # fid -> (H, W) uint8 index map in the dataset's object ids (255 = unknown)
    names: list[str]               # object names, id order
    sources: dict[str, str]        # fid -> file name


def read_mapping_file(path: Path) -> dict[int, str]:
    try:
        raw = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except (OSError, yaml.YAMLError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not valid YAML ({exc}); write it as {{0: 'fridge door', 1: 'top drawer'}}") from exc
    if not isinstance(raw, dict) or not raw:
        raise InputError(f"{path}: expected {{0: 'fridge door', 1: 'top drawer'}}, got {raw!r}")
    try:
        mapping = {int(k): str(v) for k, v in raw.items()}
    except (TypeError, ValueError) as exc:
        raise InputError(f"{path}: object ids must be integers ({exc})") from exc
    if sorted(mapping) != list(range(len(mapping))):
        raise InputError(f"{path}: object ids {sorted(mapping)} must run 0, 1, 2, ... without gaps")
    return mapping


def load_keyframes(folder: str | Path, frame_ids: list[str], size: tuple[int, int],
                   ds_mapping: dict[int, str], image_of=None) -> Keyframes:
    """Read and check every keyframe in `folder` against the dataset's frames (ids) and image size (w, h).

    `image_of(fid)` returns the RGB frame (needed only for LabelMe rectangles, refined with GrabCut).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"keyframe folder {folder} does not exist: pass --keyframes DIR with DIR/<frame id>.png or .json")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".json") and not p.name.startswith("."))
    if not files:
        raise InputError(f"{folder} holds no keyframe files: add DIR/00042.png (index mask) or DIR/00042.json (LabelMe)")
    dir_map = read_mapping_file(folder / MAPPING_FILE) if (folder / MAPPING_FILE).exists() else {}
    mapping = ds_mapping or dir_map
    known = {int(f): f for f in frame_ids}
    by_fid: dict[str, Path] = {}
    for p in files:
        token = frame_id(p)
        if not token.isdigit():
            raise InputError(f"{p}: keyframe files are named by frame id (e.g. 00042.png); '{p.stem}' is not one")
        if int(token) not in known:
            near = min(known, key=lambda i: abs(i - int(token))) if known else None
            raise InputError(f"{p}: frame {token} is not among the dataset's frames (nearest: {known.get(near)}); "
                             f"re-run `interreal frames ... --keep {int(token)}` or rename the keyframe")
        fid = known[int(token)]
        if fid in by_fid:
            raise InputError(f"frame {fid} is annotated twice ({by_fid[fid].name} and {p.name}): keep one of them")
        by_fid[fid] = p
    if not mapping:
        if any(p.suffix.lower() == ".png" for p in by_fid.values()):
            raise InputError(f"no object names: the dataset has no mapping.yaml and {folder / MAPPING_FILE} is missing; "
                             "write {0: 'first object', 1: 'second object'} there")
        mapping = _mapping_from_labelme(by_fid)
    names = [mapping[i] for i in sorted(mapping)]
    masks: dict[str, np.ndarray] = {}
    for fid, p in sorted(by_fid.items()):
        if p.suffix.lower() == ".png":
            masks[fid] = _read_png(p, size, names, dir_map)
        else:
            masks[fid] = _read_labelme(p, size, names, (lambda f=fid: image_of(f)) if image_of else None)
    for k, name in enumerate(names):
        if not any((m == k + 1).any() for m in masks.values()):
            raise InputError(f"object '{name}' (id {k}) is drawn on no keyframe: annotate it on at least one frame, "
                             f"or remove it from mapping.yaml")
    return Keyframes(masks, names, {fid: p.name for fid, p in by_fid.items()})


def _mapping_from_labelme(by_fid: dict[str, Path]) -> dict[int, str]:
    names: list[str] = []
    for _, p in sorted(by_fid.items()):
        for shape in _labelme(p).get("shapes", []):
            label = str(shape.get("label", ""))
            if label and label not in names:
                names.append(label)
    return dict(enumerate(names))


def same_aspect(a: tuple[int, int], b: tuple[int, int], tol: float = 0.01) -> bool:
    """Whether two (w, h) sizes are the same picture at another resolution (aspect ratios within `tol`)."""
    return abs((a[0] / a[1]) / (b[0] / b[1]) - 1.0) <= tol


def _read_png(path: Path, size: tuple[int, int], names: list[str], dir_map: dict[int, str]) -> np.ndarray:
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise InputError(f"{path}: cannot decode the PNG (corrupt or not an image); re-export the mask")
    if img.ndim == 3:
        if img.shape[2] >= 3 and np.array_equal(img[..., 0], img[..., 1]) and np.array_equal(img[..., 1], img[..., 2]):
            img = img[..., 0]
        else:
            raise InputError(f"{path}: a colour image; keyframe masks are 8-bit index maps (0 = background, "
                             f"k = object k-1, 255 = not annotated)")
    if img.dtype != np.uint8:
        raise InputError(f"{path}: {img.dtype} pixels; keyframe masks are 8-bit index maps")
    if (img.shape[1], img.shape[0]) != size:
        if not same_aspect((img.shape[1], img.shape[0]), size):
            raise InputError(f"{path}: mask is {img.shape[1]}x{img.shape[0]} but the frames are {size[0]}x{size[1]} "
                             f"(another aspect ratio); draw the mask on the extracted frame DS/images/")
        # drawn on the source video, frames extracted smaller (or larger): same picture, other resolution
        img = cv2.resize(img, size, interpolation=cv2.INTER_NEAREST_EXACT)
    values = set(np.unique(img).tolist()) - {0, UNANNOTATED}
    bad = sorted(v for v in values if v > len(names))
    if bad:
        raise InputError(f"{path}: values {bad} name no object (objects are 1..{len(names)}: "
                         f"{', '.join(f'{i + 1}={n}' for i, n in enumerate(names))}; 255 = not annotated)")
    if dir_map and dir_map != dict(enumerate(names)):
        unknown = [n for n in dir_map.values() if n not in names]
        if unknown:
            raise InputError(f"{path.parent / MAPPING_FILE}: objects {unknown} are not in the dataset's mapping.yaml "
                             f"({names}); rename them or add them to the dataset")
        lut = np.arange(256, dtype=np.uint8)
        for k, n in dir_map.items():
            lut[k + 1] = names.index(n) + 1
        img = lut[img]
    if (img == UNANNOTATED).all():
        raise InputError(f"{path}: empty mask (every pixel is 255 = not annotated); draw the objects "
                         f"(0 = background), or delete the file")
    return img.copy()


def _labelme(path: Path) -> dict:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not valid LabelMe JSON ({exc}); re-save it from LabelMe") from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("shapes"), list):
        raise InputError(f"{path}: LabelMe JSON needs a 'shapes' list")
    return doc


def _read_labelme(path: Path, size: tuple[int, int], names: list[str], image) -> np.ndarray:
    doc = _labelme(path)
    w, h = size
    dw, dh = doc.get("imageWidth"), doc.get("imageHeight")
    scale = (1.0, 1.0)
    if dw is not None and dh is not None and (int(dw), int(dh)) != (w, h):
        if not same_aspect((int(dw), int(dh)), (w, h)):
            raise InputError(f"{path}: drawn on a {dw}x{dh} image but the frames are {w}x{h} (another aspect "
                             f"ratio); annotate DS/images/")
        scale = (w / int(dw), h / int(dh))  # drawn on the source video: scale the shapes to the frames
    polys = np.zeros((len(names), h, w), bool)
    boxes: list[tuple[int, tuple[int, int, int, int]]] = []
    for i, shape in enumerate(doc["shapes"]):
        label = str(shape.get("label", ""))
        if label not in names:
            raise InputError(f"{path}: shape {i} has label '{label}', not an object name ({names}); fix the label "
                             f"or add the object to mapping.yaml")
        k = names.index(label)
        kind = shape.get("shape_type", "polygon") or "polygon"
        try:
            pts = np.asarray(shape["points"], dtype=np.float64).reshape(-1, 2) * np.asarray(scale)
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{path}: shape {i} ('{label}') has no usable points ({exc})") from exc
        if not np.all(np.isfinite(pts)):
            raise InputError(f"{path}: shape {i} ('{label}') has non-finite points")
        if kind == "polygon":
            m = np.zeros((h, w), np.uint8)
            cv2.fillPoly(m, [np.round(pts).astype(np.int32)], 1)
            if not m.any() or len(pts) < 3:
                raise InputError(f"{path}: polygon {i} ('{label}') is empty (fewer than 3 points or no area)")
            polys[k] |= m > 0
        elif kind == "rectangle":
            if len(pts) != 2:
                raise InputError(f"{path}: rectangle {i} ('{label}') needs 2 corner points")
            x0, y0 = np.clip(np.floor(pts.min(0)), 0, [w - 1, h - 1]).astype(int)
            x1, y1 = np.clip(np.ceil(pts.max(0)), 0, [w, h]).astype(int)
            if x1 - x0 < 3 or y1 - y0 < 3:
                raise InputError(f"{path}: rectangle {i} ('{label}') is empty (under 3 px on a side)")
            boxes.append((k, (int(x0), int(y0), int(x1), int(y1))))
        else:
            raise InputError(f"{path}: shape {i} ('{label}') is a {kind}; use polygons or rectangles")
    _check_overlap(path, polys, names)
    index = np.zeros((h, w), np.uint8)
    for k in range(len(names)):
        index[polys[k]] = k + 1
    for k, box in sorted(boxes, key=lambda kb: -(kb[1][2] - kb[1][0]) * (kb[1][3] - kb[1][1])):
        if image is None:
            raise InputError(f"{path}: rectangles need the frame image to be refined")
        drawn = polys.any(0)
        inside = grabcut_box(image(), box, taken=drawn)
        index[inside & ~drawn] = k + 1  # polygons win over boxes; boxes go largest first, so smaller ones win
    if not index.any():
        raise InputError(f"{path}: empty annotation (no shape covers any pixel); draw the objects, or delete the file")
    return index


def _check_overlap(path: Path, polys: np.ndarray, names: list[str]) -> None:
    for a in range(len(names)):
        for b in range(a + 1, len(names)):
            both = polys[a] & polys[b]
            if both.any():
                ys, xs = np.nonzero(both)
                raise InputError(
                    f"{path}: polygons of '{names[a]}' and '{names[b]}' overlap on {len(xs)} pixels "
                    f"(x {xs.min()}..{xs.max()}, y {ys.min()}..{ys.max()}); objects are exclusive: "
                    f"cut one polygon back so each pixel belongs to one object")


def grabcut_box(image: np.ndarray, box: tuple[int, int, int, int], taken: np.ndarray | None = None,
                iterations: int = 4) -> np.ndarray:
    """Object mask inside `box` (x0, y0, x1, y1) by GrabCut; pixels in `taken` are forced background."""
    h, w = image.shape[:2]
    x0, y0, x1, y1 = box
    mask = np.full((h, w), cv2.GC_BGD, np.uint8)
    mask[y0:y1, x0:x1] = cv2.GC_PR_FGD
    if taken is not None:
        mask[taken] = cv2.GC_BGD
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.setRNGSeed(0)
    bgr = np.ascontiguousarray(image[..., ::-1])
    try:
        cv2.grabCut(bgr, mask, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        return mask == cv2.GC_PR_FGD  # too little background to model colour: keep the box
    out = (mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)
    if not out.any():
        out = mask == cv2.GC_PR_FGD
    return out
