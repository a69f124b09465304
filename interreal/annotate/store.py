"""The annotation app's view of a dataset: reads with versions, atomic merge-safe edits.

Two browser tabs (or a tab and the `interreal label` CLI) may edit one dataset at once. Every read returns a
version of what was read; every edit sends back what it was based on. Under the dataset's edit lock
(`interreal.labels.edit_lock`) the store re-reads the file, applies edits whose item is unchanged since it was
read, and refuses the whole request with `Conflict` (HTTP 409) when another writer changed the same item.
Items are (frame, object): a label value, or one object's pixels on one keyframe.
"""

from __future__ import annotations

import hashlib
import math
import threading
from pathlib import Path
from typing import Any

import numpy as np

from .. import atomic, labels as L
from ..conventions import (IMAGES_DIR, LABELS_FILE, MAPPING_FILE, MASKS_DIR, UNANNOTATED, fid_of_index, frame_id,
                           frame_index, onehot_to_index)
from ..dataset import list_images, read_labels, read_prompts, read_yaml, write_labels, write_prompts
from ..errors import InputError
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
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise InputError(f"{path} is not a readable index PNG; delete it or fix it")
    return img[..., 0] if img.ndim == 3 else img


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
        if not str(fid).isdigit() or int(fid) not in self._frames:
            raise UnknownFrame(fid)
        return fid_of_index(int(fid))

    def key(self, fid: str) -> str:
        return self._frames[int(self.fid(fid))]

    def frame_list(self) -> list[dict[str, Any]]:
        return [{"fid": fid_of_index(i), "key": k, "index": i} for i, k in self._frames.items()]

    def image_file(self, fid: str) -> Path:
        path = self._files.get(self.fid(fid))
        if path is None or not path.is_file():
            raise UnknownFrame(fid)
        return path

    def image_size(self, fid: str) -> tuple[int, int]:
        """(w, h) from the image header."""
        from PIL import Image

        with Image.open(self.image_file(fid)) as im:
            return im.size

    def image_bytes(self, fid: str) -> tuple[bytes, str]:
        """The frame as the browser can show it (PNG/JPEG as stored; other formats re-encoded as PNG)."""
        path = self.image_file(fid)
        if path.suffix.lower() in BROWSER_IMAGE_SUFFIXES:
            media = {".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".webp": "image/webp", ".bmp": "image/bmp"}
            return path.read_bytes(), media.get(path.suffix.lower(), "image/png")
        from ..dataset import read_image_rgb

        return _png_bytes_rgb(read_image_rgb(path)), "image/png"

    def thumbnail(self, fid: str) -> bytes:
        """A THUMB_WIDTH-wide JPEG, cached in memory by file modification time."""
        import cv2

        path = self.image_file(fid)
        key = (str(path), path.stat().st_mtime_ns)
        with self._cache_lock:
            hit = self._thumbs.get(key)
        if hit is not None:
            return hit
        from ..dataset import read_image_rgb

        rgb = read_image_rgb(path)
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
        key = (str(path), path.stat().st_mtime_ns)
        with self._cache_lock:
            hit = self._masks.get(key)
        if hit is not None:
            return hit
        onehot = np.load(path, allow_pickle=False)
        if onehot.ndim != 3:
            raise InputError(f"{path} has shape {onehot.shape}, expected (H, W, objects + 1)")
        data = _png_bytes(onehot_to_index(onehot.astype(bool)))
        with self._cache_lock:
            if len(self._masks) > 500:
                self._masks.clear()
            self._masks[key] = data
        return data

    def suggested(self) -> list[dict[str, Any]]:
        """Frames the masks report suggests annotating next: [{fid, reason}] ([] when there is no report)."""
        rep = read_report(self.ds, "masks") or {}
        figures = rep.get("figures") or {}
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
                idx = int(item) if str(item).isdigit() else int(frame_id(str(item)))
            except (TypeError, ValueError):
                continue
            if idx in self._frames:
                fid = fid_of_index(idx)
                if not reason:
                    reason = _low_confidence(confidence, fid)
                out.append({"fid": fid, "reason": reason})
        return out

    # ---------------------------------------------------------------------------------------------------- objects
    def objects(self) -> tuple[dict[int, str], str]:
        return L.read_objects(self.ds), file_version(self.ds / MAPPING_FILE)

    def add_object(self, name: str, description: str | None = None) -> int:
        with L.edit_lock(self.ds):
            name = L.check_object_name(name)
            if name in L.read_objects(self.ds).values():
                raise Conflict(f"an object called {name!r} exists already (perhaps added in another tab); reload")
            oid = L.add_object(self.ds, name, description)
            if oid + 1 >= UNANNOTATED:
                raise InputError("at most 254 objects fit in a keyframe index PNG")
            return oid

    def rename_object(self, old: str, new: str) -> None:
        with L.edit_lock(self.ds):
            if old not in L.read_objects(self.ds).values():
                raise Conflict(f"there is no object {old!r} any more (renamed in another tab?); reload")
            L.rename_object(self.ds, old, new)

    def describe_object(self, name: str, text: str) -> None:
        with L.edit_lock(self.ds):
            L.require_object(L.read_objects(self.ds), name)
            write_prompts(self.ds, {**read_prompts(self.ds), name: str(text)})

    # ---------------------------------------------------------------------------------------------------- labels
    def labels(self) -> tuple[dict[str, dict[str, float]], str]:
        with L.edit_lock(self.ds):
            return read_labels(self.ds), file_version(self.ds / LABELS_FILE)

    def edit_labels(self, edits: list[dict[str, Any]], version: str | None) -> dict[str, Any]:
        """Apply [{frame, object, value (None = unset), base (the value read; None = none)}] all-or-nothing.

        Merges with changes made since `version` unless one of them touched the same (frame, object).
        """
        if not isinstance(edits, list) or not edits:
            raise InputError("no edits given")
        with L.edit_lock(self.ds):
            mapping = L.read_objects(self.ds)
            current = read_labels(self.ds)
            cur_version = file_version(self.ds / LABELS_FILE)
            parsed, conflicts = [], []
            for e in edits:
                if not isinstance(e, dict):
                    raise InputError(f"edit {e!r} is not an object")
                name = str(e.get("object", ""))
                if name not in mapping.values():  # the page only offers existing objects: its view is stale
                    raise Conflict(f"unknown object {name!r} (renamed in another tab?): reload the page")
                key = L.resolve_frame(self._frames, e.get("frame"))
                value = e.get("value")
                value = None if value is None else L.normalise_value(value, where=f"{name} @ {key}")
                base = e.get("base")
                base = None if base is None else float(base)
                now = current.get(key, {}).get(name)
                if not _same(now, base):
                    was = "no label" if base is None else f"{base:.3f}"
                    is_ = "removed" if now is None else f"{now:.3f}"
                    conflicts.append(f"{name} on {key} was changed elsewhere ({was} -> {is_}) since this page read it")
                parsed.append((key, name, value))
            if conflicts:
                raise Conflict("; ".join(conflicts) + ". Your edit was not saved: check the new value and set it again.")
            for key, name, value in parsed:
                if value is None:
                    current.get(key, {}).pop(name, None)
                    if key in current and not current[key]:
                        del current[key]
                else:
                    current.setdefault(key, {})[name] = value
            write_labels(self.ds, current)
            return {"labels": current, "version": file_version(self.ds / LABELS_FILE),
                    "merged": version is not None and version != cur_version}

    # ---------------------------------------------------------------------------------------------------- keyframes
    def keyframe_path(self, fid: str) -> Path:
        return self.ds / KEYFRAMES_DIR / f"{self.fid(fid)}.png"

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
                    out[fid] = max(out.get(fid, 0), (self.ds / KEYFRAMES_DIR / f"{fid}{suffix}").stat().st_mtime_ns)
                except FileNotFoundError:
                    continue
        return out

    def keyframe(self, fid: str) -> tuple[np.ndarray | None, dict[str, str]]:
        """The keyframe's index map (PNG, else rasterised LabelMe JSON, else None) and its per-object versions."""
        with L.edit_lock(self.ds):
            index = _read_index_png(self.keyframe_path(fid))
            if index is None and (self.ds / KEYFRAMES_DIR / f"{self.fid(fid)}.json").exists():
                index = self._labelme_index(fid)
            return index, _mask_versions(index)

    def _labelme_index(self, fid: str) -> np.ndarray | None:
        import json

        path = self.ds / KEYFRAMES_DIR / f"{self.fid(fid)}.json"
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError):
            return None
        w, h = self.image_size(fid)
        ids = {name: oid for oid, name in L.read_objects(self.ds).items()}
        index = np.zeros((h, w), dtype=np.uint8)
        for shape in doc.get("shapes", []) if isinstance(doc, dict) else []:
            if not isinstance(shape, dict) or shape.get("label") not in ids:
                continue
            kind = {"polygon": "polygon", "rectangle": "box"}.get(shape.get("shape_type", "polygon"))
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
        if (self.ds / KEYFRAMES_DIR / f"{fid}.json").exists():
            raise InputError(f"frame {fid} is annotated in keyframes/{fid}.json (LabelMe): edit it in LabelMe, "
                             f"or delete that file to draw this keyframe here")
        w, h = self.image_size(fid)
        region = _rasterise(op, w, h)
        mode = op.get("mode", "paint")
        if mode not in ("paint", "erase"):
            raise InputError(f"mode {mode!r}: use paint or erase")
        with L.edit_lock(self.ds):
            mapping = L.read_objects(self.ds)
            try:
                oid = int(op.get("object"))
            except (TypeError, ValueError):
                raise InputError(f"object {op.get('object')!r} is not an object id") from None
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
            seen = op.get("versions") or {}
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
        path = self.ds / KEYFRAMES_DIR / MAPPING_FILE
        have = read_yaml(path) if path.exists() else None
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
        raise InputError("points must be a list of finite [x, y] pairs")
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
