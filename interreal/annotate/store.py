"""The annotation app's view of a dataset: reads with versions, atomic merge-safe edits.

Two browser tabs (or a tab and the `interreal label` CLI) may edit one dataset at once. Every read returns a
version of what was read; every edit sends back what it was based on. Under the dataset's edit lock
(`interreal.labels.edit_lock`) the store re-reads the file, applies edits whose item is unchanged since it was
read, and refuses the whole request with `Conflict` (HTTP 409) when another writer changed the same item.
Items are (frame, object): a label value, or one object's pixels on one keyframe.

Every file is found from a frame id and checked to resolve inside the dataset (`Outside`, HTTP 403): a symlink in
images/, keyframes/ or masks/ that leads out of the dataset is never read or written through. Labels are read
leniently (`labels()`): an entry that is not a number is reported as bad, not fatal, so the page can show it and
the user can overwrite or remove it; untouched bad entries are kept as they are when other labels are saved.
"""

from __future__ import annotations

import hashlib
import math
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .. import atomic, labels as L
from ..conventions import (IMAGES_DIR, LABELS_FILE, MAPPING_FILE, MASKS_DIR, PROMPTS_FILE, REPORTS_DIR, UNANNOTATED,
                           fid_of_index, frame_index, onehot_to_index)
from ..dataset import (label_value_problem, list_images, read_labels_raw, read_prompts, read_yaml, write_labels,
                       write_prompts)
from ..errors import DatasetError, InputError, InterRealError
from ..report import read_report

KEYFRAMES_DIR = L.KEYFRAMES_DIR
THUMB_WIDTH = 160
UNDO_DEPTH = 50  # strokes remembered per keyframe (in memory, for this server run)
BROWSER_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp", ".bmp")
_EPS = 1e-6


class Conflict(Exception):
    """Another writer changed an item this edit was based on; nothing was written."""


class UnknownFrame(LookupError):
    """A frame id that is not among the dataset's frames (HTTP 404)."""


class Outside(Exception):
    """A dataset path that resolves outside the dataset (a symlink out of it): refused (HTTP 403)."""


FID_MAX_DIGITS = 9  # frame numbers are small; a longer id is not a frame (and int() of 5000 digits raises)


def file_version(path: Path) -> str:
    """Content hash of a file ('0' when absent): the version a client read."""
    try:
        return hashlib.sha1(path.read_bytes()).hexdigest()[:16]
    except FileNotFoundError:
        return "0"


def _mask_versions(index: np.ndarray | None) -> dict[str, str]:
    """Per index value (object id + 1, 0 = background): a hash of where that value is on the keyframe."""
    if index is None:
        return {}
    out = {}
    for v in np.unique(index):
        bits = np.packbits(index == v)
        out[str(int(v))] = hashlib.sha1(bits.tobytes()).hexdigest()[:12]
    return out


def _png_bytes(index: np.ndarray) -> bytes:
    import cv2

    ok, enc = cv2.imencode(".png", np.ascontiguousarray(index.astype(np.uint8)))
    if not ok:
        raise OSError("could not encode PNG")
    return enc.tobytes()


def _read_index_png(path: Path) -> np.ndarray | None:
    import cv2

    if not path.exists():
        return None
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except IsADirectoryError:
        data = np.zeros(0, np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None or img.ndim not in (2, 3):
        raise InputError(f"{KEYFRAMES_DIR}/{path.name} is not a readable index PNG; delete it or fix it")
    return img[..., 0] if img.ndim == 3 else img


@dataclass(frozen=True)
class BadLabel:
    """An entry of key_frame_value.yaml that is not a state in [0, 1] (object '' = the whole frame entry)."""

    frame: str
    object: str
    value: Any
    problem: str

    def as_json(self) -> dict[str, str]:
        shown = repr(self.value)
        return {"frame": self.frame, "object": self.object, "value": shown[:80] + ("…" if len(shown) > 80 else ""),
                "problem": f"{LABELS_FILE}: {self.frame}{': ' + self.object if self.object else ''}: {self.problem}"}


def finite_number(value: Any) -> bool:
    """A number (not true/false) that is a finite float; False for a 400-digit integer too."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def _label_problem(value: Any) -> str:
    """Why a raw YAML label value is not a usable state, with what to do ('' when it is one)."""
    try:
        why = label_value_problem(value)
    except OverflowError:  # a 400-digit integer
        why = f"{str(value)[:20]}... is not a finite number"
    return f"{why}: set the state again (0 = closed ... 1 = open) or clear it" if why else ""


def _same(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return abs(float(a) - float(b)) <= _EPS


class DatasetStore:
    """Reads and edits one dataset folder on behalf of the web app; every path is derived from a frame id."""

    def __init__(self, ds: str | Path):
        self.ds = Path(ds).resolve()
        self._cache_lock = threading.Lock()
        self._thumbs: dict[tuple[str, int], bytes] = {}
        self._masks: dict[tuple[str, int], bytes] = {}
        self._frames: dict[int, str] = {}
        self._files: dict[str, Path] = {}
        self._undo: dict[str, list[tuple[bytes | None, dict[str, str]]]] = {}  # fid -> [(PNG before, versions after)]
        self.refresh_frames()

    # ---------------------------------------------------------------------------------------------------- frames
    def refresh_frames(self) -> None:
        """Re-list DS/images (frames may be added while the app runs)."""
        frames = L.dataset_frames(self.ds)
        files = {}
        for p in list_images(self.ds / IMAGES_DIR):
            try:
                i = frame_index(p)
            except ValueError:
                continue
            if i in frames:
                files[fid_of_index(i)] = p
        self._frames, self._files = frames, files  # swapped whole: request threads never see a half list

    def fid(self, fid: str) -> str:
        """A known frame id, normalised ('42' -> '00042'); UnknownFrame (HTTP 404) for anything else."""
        text = str(fid)
        # ASCII digits only: str.isdigit() also accepts '٤٢' and '²', which int() reads differently or not at all
        if not (text.isascii() and text.isdigit() and len(text) <= FID_MAX_DIGITS) or int(text) not in self._frames:
            raise UnknownFrame(fid)
        return fid_of_index(int(text))

    def inside(self, path: Path) -> Path:
        """`path` if it (and every link on the way) resolves inside the dataset; `Outside` otherwise."""
        real = Path(path).resolve()
        if real != self.ds and self.ds not in real.parents:
            rel = Path(path).relative_to(self.ds) if Path(path).is_relative_to(self.ds) else Path(path)
            raise Outside(f"refused: {rel} leads outside the dataset (a symbolic link?); copy the file into "
                          f"{self.ds.name}/ instead of linking it")
        return Path(path)

    def key(self, fid: str) -> str:
        return self._frames[int(self.fid(fid))]

    def frame_list(self) -> list[dict[str, Any]]:
        return [{"fid": fid_of_index(i), "key": k, "index": i} for i, k in self._frames.items()]

    def image_file(self, fid: str) -> Path:
        path = self._files.get(self.fid(fid))
        if path is None or not path.is_file():
            raise UnknownFrame(fid)
        return self.inside(path)

    def image_size(self, fid: str) -> tuple[int, int]:
        """(w, h) from the image header."""
        from PIL import Image, UnidentifiedImageError

        path = self.image_file(fid)
        try:
            with Image.open(path) as im:
                return im.size
        except (UnidentifiedImageError, ValueError) as exc:
            raise DatasetError(f"{IMAGES_DIR}/{path.name} is not a readable image ({exc}); replace or remove it") from None

    def image_bytes(self, fid: str) -> tuple[bytes, str]:
        """The frame as the browser can show it (PNG/JPEG as stored; other formats re-encoded as PNG)."""
        path = self.image_file(fid)
        if path.suffix.lower() in BROWSER_IMAGE_SUFFIXES:
            media = {".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".webp": "image/webp", ".bmp": "image/bmp"}
            return path.read_bytes(), media.get(path.suffix.lower(), "image/png")
        return _png_bytes_rgb(self._rgb(path)), "image/png"

    def _rgb(self, path: Path) -> np.ndarray:
        from ..dataset import read_image_rgb

        try:
            return read_image_rgb(path)
        except InterRealError:
            raise
        except (ValueError, OSError) as exc:
            if isinstance(exc, PermissionError):
                raise
            raise DatasetError(f"{IMAGES_DIR}/{path.name} is not a readable image ({exc}); replace or remove it") from None

    def thumbnail(self, fid: str) -> bytes:
        """A THUMB_WIDTH-wide JPEG, cached in memory by file modification time."""
        import cv2

        path = self.image_file(fid)
        key = (str(path), path.stat().st_mtime_ns)
        with self._cache_lock:
            hit = self._thumbs.get(key)
        if hit is not None:
            return hit
        rgb = self._rgb(path)
        h, w = rgb.shape[:2]
        tw = min(THUMB_WIDTH, w)
        small = cv2.resize(rgb, (tw, max(1, round(h * tw / w))), interpolation=cv2.INTER_AREA)
        ok, enc = cv2.imencode(".jpg", small[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 80])
        data = enc.tobytes()
        with self._cache_lock:
            if len(self._thumbs) > 4000:
                self._thumbs.clear()
            self._thumbs[key] = data
        return data

    # ---------------------------------------------------------------------------------------------------- masks
    def mask_fids(self) -> list[str]:
        folder = self.ds / MASKS_DIR
        if not folder.is_dir():
            return []
        known = {fid_of_index(i) for i in self._frames}
        return sorted(p.stem for p in folder.glob("*.npy") if p.stem in known)

    def mask_png(self, fid: str) -> bytes | None:
        """The propagated mask of a frame (DS/masks/<fid>.npy) as an index PNG, cached by modification time."""
        path = self.ds / MASKS_DIR / f"{self.fid(fid)}.npy"
        if not path.exists():
            return None
        self.inside(path)
        key = (str(path), path.stat().st_mtime_ns)
        with self._cache_lock:
            hit = self._masks.get(key)
        if hit is not None:
            return hit
        try:
            onehot = np.load(path, allow_pickle=False)
        except (ValueError, EOFError, OSError) as exc:
            if isinstance(exc, PermissionError):
                raise
            raise DatasetError(f"{MASKS_DIR}/{path.name} is not a readable .npy mask ({exc}); re-run propagation") from None
        if not isinstance(onehot, np.ndarray) or onehot.ndim != 3:
            raise DatasetError(f"{MASKS_DIR}/{path.name} has shape {getattr(onehot, 'shape', '?')}, expected "
                               f"(H, W, objects + 1); re-run propagation")
        data = _png_bytes(onehot_to_index(onehot.astype(bool)))
        with self._cache_lock:
            if len(self._masks) > 500:
                self._masks.clear()
            self._masks[key] = data
        return data

    def suggested(self) -> list[dict[str, Any]]:
        """Frames the masks report suggests annotating next: [{fid, reason}] ([] when there is no report)."""
        report = self.ds / REPORTS_DIR / "masks.json"
        rep = read_report(self.ds, "masks") if report.exists() and self._is_inside(report) else None
        rep = rep if isinstance(rep, dict) else {}
        figures = rep.get("figures") if isinstance(rep.get("figures"), dict) else {}
        raw = None
        for where in (rep, figures):
            for key in ("suggested", "suggested_frames"):
                if raw is None and isinstance(where.get(key), list):
                    raw = where[key]
        confidence = figures.get("confidence") if isinstance(figures.get("confidence"), dict) else {}
        out = []
        for item in raw or []:
            reason = ""
            if isinstance(item, dict):
                reason = str(item.get("reason", item.get("why", "")))
                conf = item.get("confidence", item.get("score"))
                if isinstance(conf, (int, float)) and not reason:
                    reason = f"confidence {conf:.2f}"
                item = item.get("fid", item.get("frame", item.get("index")))
            try:
                text = str(item)
                idx = int(text) if text.isascii() and text.isdigit() else frame_index(text)
            except (TypeError, ValueError):
                continue
            if idx in self._frames:
                fid = fid_of_index(idx)
                if not reason:
                    reason = _low_confidence(confidence, fid)
                out.append({"fid": fid, "reason": reason})
        return out

    # ---------------------------------------------------------------------------------------------------- objects
    def _is_inside(self, path: Path) -> bool:
        try:
            self.inside(path)
            return True
        except Outside:
            return False

    def check_files(self) -> None:
        """`Outside` when a dataset file the app reads or writes by name is a link out of the dataset."""
        for rel in (MAPPING_FILE, LABELS_FILE, PROMPTS_FILE, KEYFRAMES_DIR, f"{KEYFRAMES_DIR}/{MAPPING_FILE}"):
            path = self.ds / rel
            if path.exists() or path.is_symlink():
                self.inside(path)

    def read_objects(self) -> dict[int, str]:
        """The dataset's objects; a malformed mapping.yaml is a DatasetError naming the file (HTTP 400)."""
        self.check_files()
        try:
            mapping = L.read_objects(self.ds)
        except InterRealError:
            raise
        except (ValueError, TypeError, AttributeError, yaml.YAMLError) as exc:
            raise DatasetError(f"{MAPPING_FILE} (or {KEYFRAMES_DIR}/{MAPPING_FILE}) is malformed ({exc}); it must map "
                               f"object ids 0, 1, ... to names: fix it by hand") from None
        return mapping

    def prompts(self) -> dict[str, str]:
        self.check_files()
        try:
            return read_prompts(self.ds)
        except (ValueError, TypeError, AttributeError, yaml.YAMLError) as exc:
            raise DatasetError(f"{PROMPTS_FILE} is malformed ({exc}); it must map object names to descriptions") from None

    def objects(self) -> tuple[dict[int, str], str]:
        return self.read_objects(), file_version(self.ds / MAPPING_FILE)

    def add_object(self, name: str, description: str | None = None) -> int:
        with L.edit_lock(self.ds):
            name = L.check_object_name(name)
            if name in self.read_objects().values():
                raise Conflict(f"an object called {name!r} exists already (perhaps added in another tab); reload")
            oid = L.add_object(self.ds, name, description)
            if oid + 1 >= UNANNOTATED:
                raise InputError("at most 254 objects fit in a keyframe index PNG")
            return oid

    def rename_object(self, old: str, new: str) -> None:
        with L.edit_lock(self.ds):
            if old not in self.read_objects().values():
                raise Conflict(f"there is no object {old!r} any more (renamed in another tab?); reload")
            L.rename_object(self.ds, old, new)

    def describe_object(self, name: str, text: str) -> None:
        with L.edit_lock(self.ds):
            L.require_object(self.read_objects(), name)
            write_prompts(self.ds, {**self.prompts(), name: str(text)})

    # ---------------------------------------------------------------------------------------------------- labels
    def labels(self) -> tuple[dict[str, dict[str, float]], str, list[dict[str, str]]]:
        """(readable labels, file version, bad entries [{frame, object, value, problem}]) of key_frame_value.yaml."""
        with L.edit_lock(self.ds):
            good, bad = self._read_labels()
            return good, file_version(self.ds / LABELS_FILE), [b.as_json() for b in bad.values()]

    def _read_labels(self) -> tuple[dict[str, dict[str, float]], dict[tuple[str, str], "BadLabel"]]:
        """Lenient read: every label that is a state in [0, 1], and the entries that are not (kept raw).

        A file that is not YAML, or not {frame: {object: value}} at the top, is a DatasetError (from
        `read_labels_raw`): there is nothing to show or keep entry by entry, so the user must fix it by hand.
        """
        self.check_files()
        good: dict[str, dict[str, float]] = {}
        bad: dict[tuple[str, str], BadLabel] = {}
        for key, entry in read_labels_raw(self.ds).items():
            if not isinstance(entry, dict):
                bad[(key, "")] = BadLabel(key, "", entry, "expected {object name: value}")
                continue
            for name, value in entry.items():
                problem = _label_problem(value)
                if problem:
                    bad[(key, name)] = BadLabel(key, name, value, problem)
                else:
                    good.setdefault(key, {})[name] = float(value)
        return good, bad

    def _write_labels(self, good: dict[str, dict[str, float]], bad: dict[tuple[str, str], "BadLabel"]) -> None:
        """Write the labels, keeping the bad entries nobody edited exactly as they were (`write_labels` does)."""
        out: dict[str, Any] = {key: dict(entry) for key, entry in good.items() if entry}
        for (key, name), b in bad.items():
            if name:
                out.setdefault(key, {})[name] = b.value
            else:
                out[key] = b.value
        write_labels(self.ds, out)

    def edit_labels(self, edits: list[dict[str, Any]], version: str | None) -> dict[str, Any]:
        """Apply [{frame, object, value (None = unset), base (the value read; None = none)}] all-or-nothing.

        Merges with changes made since `version` unless one of them touched the same (frame, object).
        """
        if not isinstance(edits, list) or not edits:
            raise InputError("no edits given")
        with L.edit_lock(self.ds):
            mapping = self.read_objects()
            current, bad = self._read_labels()
            cur_version = file_version(self.ds / LABELS_FILE)
            parsed, conflicts = [], []
            for e in edits:
                if not isinstance(e, dict):
                    raise InputError(f"edit {str(e)[:80]!r} is not an object {{frame, object, value, base}}")
                name = e.get("object")
                if not isinstance(name, str):
                    raise InputError(f"edit {str(e)[:80]!r}: 'object' must be an object name (a string)")
                if name not in mapping.values():  # the page only offers existing objects: its view is stale
                    raise Conflict(f"unknown object {name!r} (renamed in another tab?): reload the page")
                frame = e.get("frame")
                if isinstance(frame, bool) or not isinstance(frame, (int, str)) or not str(frame).isascii():
                    raise InputError(f"edit of {name!r}: 'frame' {str(frame)[:40]!r} is not a frame (give its number "
                                     f"in ASCII digits, e.g. 42, or its name, e.g. frame_00042)")
                key = L.resolve_frame(self._frames, frame)
                value = e.get("value")
                if isinstance(value, (bool, list, dict)):
                    raise InputError(f"{name} @ {key}: 'value' must be a number in [0, 1] or null, not {value!r:.40}")
                try:
                    value = None if value is None else L.normalise_value(value, where=f"{name} @ {key}")
                except OverflowError:
                    raise InputError(f"{name} @ {key}: {value} is outside [0, 1]") from None
                base = e.get("base")
                if base is not None and not finite_number(base):
                    raise InputError(f"{name} @ {key}: 'base' {str(base)[:40]!r} must be the number the page read, "
                                     f"or null when there was no label")
                base = None if base is None else float(base)
                now = current.get(key, {}).get(name)  # a bad (non-numeric) entry reads as no label: it can be set
                if not _same(now, base):
                    was = "no label" if base is None else f"{base:.3f}"
                    is_ = "removed" if now is None else f"{now:.3f}"
                    conflicts.append(f"{name} on {key} was changed elsewhere ({was} -> {is_}) since this page read it")
                parsed.append((key, name, value))
            if conflicts:
                raise Conflict("; ".join(conflicts) + ". Your edit was not saved: check the new value and set it again.")
            for key, name, value in parsed:
                bad.pop((key, name), None)
                whole = bad.pop((key, ""), None)  # a frame entry that was not a dict: replaced by this edit
                if whole is not None:
                    current.pop(key, None)
                if value is None:
                    current.get(key, {}).pop(name, None)
                    if key in current and not current[key]:
                        del current[key]
                else:
                    current.setdefault(key, {})[name] = value
            self._write_labels(current, bad)
            return {"labels": current, "version": file_version(self.ds / LABELS_FILE),
                    "bad_labels": [b.as_json() for b in bad.values()],
                    "merged": version is not None and version != cur_version}

    # ---------------------------------------------------------------------------------------------------- keyframes
    def keyframe_path(self, fid: str) -> Path:
        return self.inside(self.ds / KEYFRAMES_DIR / f"{self.fid(fid)}.png")

    def labelme_path(self, fid: str) -> Path:
        return self.inside(self.ds / KEYFRAMES_DIR / f"{self.fid(fid)}.json")

    def keyframe_fids(self) -> list[str]:
        folder = self.ds / KEYFRAMES_DIR
        if not folder.is_dir():
            return []
        known = {fid_of_index(i) for i in self._frames}
        return sorted({p.stem for p in folder.iterdir() if p.suffix in (".png", ".json") and p.stem in known})

    def labelme_fids(self) -> list[str]:
        """Keyframes given as LabelMe JSON (the other `--keyframes DIR` format): shown, not edited here."""
        return [fid for fid in self.keyframe_fids() if (self.ds / KEYFRAMES_DIR / f"{fid}.json").exists()]

    def keyframe_stamps(self) -> dict[str, int]:
        """fid -> modification time (ns) of its keyframe PNG: the page re-reads a keyframe when it changes."""
        out = {}
        for fid in self.keyframe_fids():
            for suffix in (".png", ".json"):
                try:
                    out[fid] = max(out.get(fid, 0), (self.ds / KEYFRAMES_DIR / f"{fid}{suffix}").lstat().st_mtime_ns)
                except FileNotFoundError:
                    continue
        return out

    def keyframe(self, fid: str) -> tuple[np.ndarray | None, dict[str, str]]:
        """The keyframe's index map (PNG, else rasterised LabelMe JSON, else None) and its per-object versions."""
        with L.edit_lock(self.ds):
            index = _read_index_png(self.keyframe_path(fid))
            if index is None and self.labelme_path(fid).exists():
                index = self._labelme_index(fid)
            return index, _mask_versions(index)

    def _labelme_index(self, fid: str) -> np.ndarray | None:
        import json

        path = self.labelme_path(fid)
        try:
            doc = json.loads(path.read_text())
        except PermissionError:
            raise
        except (OSError, ValueError, RecursionError):
            return None
        w, h = self.image_size(fid)
        ids = {name: oid for oid, name in self.read_objects().items()}
        index = np.zeros((h, w), dtype=np.uint8)
        shapes = doc.get("shapes") if isinstance(doc, dict) else None
        for shape in shapes if isinstance(shapes, list) else []:
            if not isinstance(shape, dict) or not isinstance(shape.get("label"), str) or shape["label"] not in ids:
                continue
            shape_type = shape.get("shape_type", "polygon")
            kind = {"polygon": "polygon", "rectangle": "box"}.get(shape_type) if isinstance(shape_type, str) else None
            try:
                region = _rasterise({"shape": kind, "points": shape.get("points")}, w, h) if kind else None
            except InputError:
                continue
            if region is not None:
                index[region] = ids[shape["label"]] + 1
        return index

    def edit_keyframe(self, fid: str, op: dict[str, Any]) -> tuple[np.ndarray, dict[str, str]]:
        """Paint or erase a polygon / box for one object on a keyframe, refusing if an affected object changed.

        op = {object: id, name, shape: polygon|box, points: [[x, y], ...] in image pixels, mode: paint|erase,
        versions: the per-object versions read with the keyframe}.
        """
        fid = self.fid(fid)
        if self.labelme_path(fid).exists():
            raise InputError(f"frame {fid} is annotated in keyframes/{fid}.json (LabelMe): edit it in LabelMe, "
                             f"or delete that file to draw this keyframe here")
        w, h = self.image_size(fid)
        region = _rasterise(op, w, h)
        mode = op.get("mode", "paint")
        if mode not in ("paint", "erase"):
            raise InputError(f"mode {str(mode)[:40]!r}: use paint or erase")
        oid = op.get("object")
        if isinstance(oid, bool) or not isinstance(oid, int):
            raise InputError(f"object {str(oid)[:40]!r} is not an object id (an integer: 0 for the first object)")
        seen = op.get("versions") or {}
        if not isinstance(seen, dict):
            raise InputError("versions must be the {value: hash} object read with the keyframe")
        with L.edit_lock(self.ds):
            mapping = self.read_objects()
            if oid not in mapping:
                raise Conflict(f"object id {oid} does not exist (objects changed in another tab?); reload")
            if op.get("name") is not None and mapping[oid] != op.get("name"):
                raise Conflict(f"object {oid} is now called {mapping[oid]!r}, not {op.get('name')!r}; reload")
            path = self.keyframe_path(fid)
            index = _read_index_png(path)
            if index is None:
                index = np.zeros((h, w), dtype=np.uint8)  # a new keyframe: everything not drawn is background
            if index.shape != (h, w):
                raise InputError(f"{path} is {index.shape[1]}x{index.shape[0]} but the frame is {w}x{h}")
            current = _mask_versions(index)
            k = oid + 1
            if mode == "paint":
                affected = {k} | {int(v) for v in np.unique(index[region])} - {0, k, UNANNOTATED}
            else:
                affected = {k}
            changed = [mapping.get(v - 1, f"object {v - 1}") for v in sorted(affected) if current.get(str(v)) != seen.get(str(v))]
            if changed:
                raise Conflict(f"the mask of {', '.join(map(repr, changed))} on frame {fid} was changed elsewhere since "
                               f"this page read it; your stroke was not saved: look at the new mask and draw it again")
            before = path.read_bytes() if path.exists() else None
            if mode == "paint":
                index[region] = k
            else:
                index[region & (index == k)] = 0
            self._ensure_keyframe_mapping(mapping)
            atomic.write_bytes(path, _png_bytes(index))
            after = _mask_versions(index)
            stack = self._undo.setdefault(fid, [])
            stack.append((before, after))
            del stack[:-UNDO_DEPTH]
            return index, after

    def undo_keyframe(self, fid: str, versions: dict[str, str]) -> tuple[np.ndarray | None, dict[str, str]]:
        """Take back the last stroke on a keyframe, if the keyframe is still exactly as that stroke left it."""
        fid = self.fid(fid)
        with L.edit_lock(self.ds):
            stack = self._undo.get(fid) or []
            if not stack:
                raise InputError(f"nothing to undo on frame {fid}")
            path = self.keyframe_path(fid)
            current = _mask_versions(_read_index_png(path))
            before, after = stack[-1]
            if current != after or (versions or {}) != after:
                raise Conflict(f"keyframe {fid} was changed elsewhere after your last stroke; it cannot be undone "
                               f"safely: erase or redraw instead")
            stack.pop()
            if before is None:
                path.unlink()
                return None, {}
            atomic.write_bytes(path, before)
            index = _read_index_png(path)
            return index, _mask_versions(index)

    def delete_keyframe(self, fid: str, versions: dict[str, str]) -> None:
        with L.edit_lock(self.ds):
            path = self.keyframe_path(fid)
            index = _read_index_png(path)
            if index is None:
                return
            if _mask_versions(index) != (versions or {}):
                raise Conflict(f"keyframe {fid} was changed elsewhere since this page read it; reload before deleting it")
            path.unlink()

    def _ensure_keyframe_mapping(self, mapping: dict[int, str]) -> None:
        path = self.inside(self.ds / KEYFRAMES_DIR / MAPPING_FILE)
        try:
            have = read_yaml(path) if path.exists() else None
        except (yaml.YAMLError, UnicodeDecodeError):
            have = None  # the app owns this copy of the mapping: a broken one is rewritten
        want = {int(k): str(v) for k, v in sorted(mapping.items())}
        if have != want:
            atomic.write_yaml(path, want)
        if not (self.ds / MAPPING_FILE).exists():
            atomic.write_yaml(self.ds / MAPPING_FILE, want)


def _low_confidence(confidence: dict[str, Any], fid: str) -> str:
    """'confidence 0.42 (fridge door)' for the least confident object of a frame in the masks report."""
    scores = {}
    for name, per_frame in confidence.items():
        if isinstance(per_frame, dict) and isinstance(per_frame.get(fid), (int, float)):
            scores[name] = float(per_frame[fid])
    if not scores:
        return ""
    name = min(scores, key=scores.get)
    return f"confidence {scores[name]:.2f} ({name})"


def _png_bytes_rgb(rgb: np.ndarray) -> bytes:
    import cv2

    ok, enc = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    return enc.tobytes()


def _rasterise(op: dict[str, Any], w: int, h: int) -> np.ndarray:
    """Bool (h, w) region of a polygon or box given in image pixel coordinates."""
    shape = op.get("shape", "polygon")
    pts = op.get("points")
    try:
        arr = np.asarray(pts, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("points must be a list of [x, y] pairs") from None
    if arr.ndim != 2 or arr.shape[1] != 2 or not np.all(np.isfinite(arr)) or len(arr) > 10000:
        raise InputError("points must be a list of finite [x, y] pairs (at most 10000)")
    if len(arr) and np.abs(arr).max() > 1e6:
        raise InputError("points must be image pixel coordinates (within a million pixels of the frame)")
    canvas = np.zeros((h, w), dtype=np.uint8)
    if shape == "box":
        if len(arr) != 2:
            raise InputError("a box needs two corner points")
        (x0, y0), (x1, y1) = arr.min(axis=0), arr.max(axis=0)
        x0, y0 = max(0, math.ceil(x0 - 0.5)), max(0, math.ceil(y0 - 0.5))
        x1, y1 = min(w, math.ceil(x1 - 0.5)), min(h, math.ceil(y1 - 0.5))
        canvas[y0:y1, x0:x1] = 1
    elif shape == "polygon":
        if len(arr) < 3:
            raise InputError("a polygon needs at least three points")
        from skimage.draw import polygon as fill_polygon

        # a pixel belongs to the shape when its centre (x + 0.5, y + 0.5) does, as for the box
        rr, cc = fill_polygon(arr[:, 1] - 0.5, arr[:, 0] - 0.5, shape=(h, w))
        canvas[rr, cc] = 1
    else:
        raise InputError(f"shape {shape!r}: use polygon or box")
    region = canvas.astype(bool)
    if not region.any():
        raise InputError("the shape covers no pixel of the frame")
    return region


def encode_index_png(index: np.ndarray) -> bytes:
    return _png_bytes(index)


__all__ = ["DatasetStore", "Conflict", "UnknownFrame", "file_version", "encode_index_png"]
