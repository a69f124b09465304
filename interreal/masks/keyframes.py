"""Keyframe annotations (`--keyframes DIR`): index-mask PNGs or LabelMe JSON, checked before anything is written.

- `DIR/<fid>.png`: 8-bit index map, 0 = background, k = object k-1, 254 = ignore (a person, hand or arm: the
  transient layer, `interreal.transients`), 255 = not annotated. An object with no pixel on an annotated keyframe
  is out of view there (that is how leaving / re-entering is said); an object drawn on no keyframe is an error.
- `DIR/<fid>.json`: LabelMe; `shapes[].label` = object name, `shape_type` polygon or rectangle. A rectangle
  means "the object is inside this box" and is cut out with GrabCut. Pixels outside every shape are background.
  A shape labelled `ignore` / `person` / `hand` / `arm` / `transient` paints the ignore class (it wins over
  objects: a hand is in front of what it touches; a rectangle of it is taken whole).
- `DIR/mapping.yaml` names the objects (PNG ids refer to it); the dataset's mapping.yaml wins when it exists.
Every problem raises InputError naming the file and what to do.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from ..conventions import MAPPING_FILE, UNANNOTATED, frame_id, object_name_problem
from ..dataset import decode_image
from ..errors import InputError
from ..transients import IGNORE, whole_frame
from . import labelme
from .labelme import same_aspect


@dataclass
class Keyframes:
    masks: dict[str, np.ndarray]   # fid -> (H, W) uint8 index map in the dataset's object ids (254 ignore, 255 unknown)
    names: list[str]               # object names, id order
    sources: dict[str, str]        # fid -> file name

    @property
    def has_ignore(self) -> bool:
        """Whether any keyframe paints the ignore (transient) class."""
        return any((m == IGNORE).any() for m in self.masks.values())


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
        mapping = dict(enumerate(labelme.object_labels([p for _, p in sorted(by_fid.items())])))
    names = [mapping[i] for i in sorted(mapping)]
    for name in names:  # a name every later command would refuse is refused here, where it comes in
        if problem := object_name_problem(name):
            where = ("the dataset's " + MAPPING_FILE if ds_mapping else folder / MAPPING_FILE if dir_map
                     else f"a LabelMe label in {folder}")
            raise InputError(f"{where}: {problem}: rename it there (e.g. 'door left') and run again")
    if len(names) >= IGNORE:
        raise InputError(f"{len(names)} objects: at most {IGNORE - 1} fit in a keyframe index map (254 = ignore, "
                         f"255 = not annotated); split the capture's objects over two datasets")
    masks: dict[str, np.ndarray] = {}
    for fid, p in sorted(by_fid.items()):
        if p.suffix.lower() == ".png":
            masks[fid] = _read_png(p, size, names, dir_map)
        else:
            if image_of is not None:
                check_drawn_on(p, fid, frame_ids, image_of)
            masks[fid] = labelme.rasterise(p, size, names, (lambda f=fid: image_of(f)) if image_of else None)
        if whole_frame(masks[fid] == IGNORE):
            raise InputError(f"{p}: the ignore class (person / hand) covers the whole of frame {fid}, leaving "
                             f"nothing static to reconstruct or train on; paint only the person, or delete the file")
    for k, name in enumerate(names):
        if not any((m == k + 1).any() for m in masks.values()):
            raise InputError(f"object '{name}' (id {k}) is drawn on no keyframe: annotate it on at least one frame, "
                             f"or remove it from mapping.yaml")
    return Keyframes(masks, names, {fid: p.name for fid, p in by_fid.items()})


THUMB = 160  # pictures are compared this wide, in grey levels
SAME_LEVELS = 3.0  # mean absolute difference (grey levels) within which two pictures are one frame re-encoded


def _thumb(rgb: np.ndarray, aspect: float) -> np.ndarray:
    h = max(8, int(round(THUMB * aspect)))
    return cv2.resize(cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY), (THUMB, h),
                      interpolation=cv2.INTER_AREA).astype(np.float32)


def check_drawn_on(path: Path, fid: str, frame_ids: list[str], image_of) -> None:
    """InputError when a LabelMe file's embedded picture (what was drawn on) is another frame than the one it is
    named for: its shapes would mask the wrong pixels on every frame propagated from it. The named frame is checked
    first (one read); only when it differs are all frames compared, and only a clearly better match is refused."""
    picture = labelme.embedded_image(labelme.read_doc(path))
    if picture is None:
        return
    named = image_of(fid)
    aspect = named.shape[0] / named.shape[1]
    if not same_aspect((picture.shape[1], picture.shape[0]), (named.shape[1], named.shape[0])):
        return  # _scale names the other aspect ratio
    drawn = _thumb(picture, aspect)
    here = float(np.abs(drawn - _thumb(named, aspect)).mean())
    if here <= SAME_LEVELS:
        return
    diffs = {f: float(np.abs(drawn - _thumb(image_of(f), aspect)).mean()) for f in frame_ids if f != fid}
    best = min(diffs, key=diffs.get) if diffs else None
    if best is not None and diffs[best] <= SAME_LEVELS < here and diffs[best] < 0.5 * here:
        raise InputError(f"{path}: drawn on frame {best} (its embedded picture is that frame: {diffs[best]:.1f} grey "
                         f"levels apart) but named for frame {fid} ({here:.1f} levels apart): rename it to "
                         f"{best}{path.suffix}, or draw it again on frame {fid}")


def _read_png(path: Path, size: tuple[int, int], names: list[str], dir_map: dict[int, str]) -> np.ndarray:
    img = decode_image(path)
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
    values = set(np.unique(img).tolist()) - {0, IGNORE, UNANNOTATED}
    bad = sorted(v for v in values if v > len(names))
    if bad:
        raise InputError(f"{path}: values {bad} name no object (objects are 1..{len(names)}: "
                         f"{', '.join(f'{i + 1}={n}' for i, n in enumerate(names))}; 254 = ignore (person, hand), "
                         f"255 = not annotated)")
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
