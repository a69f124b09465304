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

import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from PIL import UnidentifiedImageError

from .. import atomic, labels as L
from ..conventions import (IMAGES_DIR, LABELS_FILE, MAPPING_FILE, MASKS_DIR, PROMPTS_FILE, REPORTS_DIR, UNANNOTATED,
                           fid_of_index, frame_index, onehot_to_index)
from ..dataset import (image_hw, list_images, read_image_rgb, read_labels_raw, read_prompts, read_yaml, write_labels,
                       write_prompts)
from ..errors import DatasetError, InputError, InterRealError
from ..layout import KEYFRAMES_DIR
from ..masks.labelme import rasterise as rasterise_labelme
from ..motions import flagged_labels, frames_asked
from ..report import read_report
from ..transients import IGNORE, read_transient
from .clicking import check_object, click_region, parse_clicks, propagated
from .label_view import BadLabel, Conflict, finite_number, parse_label_edit, split_labels
from .pixels import encode_index_png, file_version, mask_versions, png_bytes, png_bytes_rgb, read_index_png
from .pixels import rasterise as rasterise_shape

_read_index_png = read_index_png  # the name the tests use

FOUND_SNAP = 6  # px: a click this close to a found region picks it
IGNORE_OBJECT = -1  # `object` of a stroke that paints the ignore class (people, hands: value 254 in the PNG)
THUMB_WIDTH = 160
UNDO_DEPTH = 50  # strokes remembered per keyframe (in memory, for this server run)
BROWSER_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp", ".bmp")


class UnknownFrame(LookupError):
    """A frame id that is not among the dataset's frames (HTTP 404)."""


class Outside(Exception):
    """A dataset path that resolves outside the dataset (a symlink out of it): refused (HTTP 403)."""


FID_MAX_DIGITS = 9  # frame numbers are small; a longer id is not a frame (and int() of 5000 digits raises)


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
        path = self.image_file(fid)
        try:
            h, w = image_hw(path)
            return w, h
        except (UnidentifiedImageError, ValueError) as exc:
            raise DatasetError(f"{IMAGES_DIR}/{path.name} is not a readable image ({exc}); replace or remove it") from None

    def image_bytes(self, fid: str) -> tuple[bytes, str]:
        """The frame as the browser can show it (PNG/JPEG as stored; other formats re-encoded as PNG)."""
        path = self.image_file(fid)
        if path.suffix.lower() in BROWSER_IMAGE_SUFFIXES:
            media = {".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".webp": "image/webp", ".bmp": "image/bmp"}
            return path.read_bytes(), media.get(path.suffix.lower(), "image/png")
        return png_bytes_rgb(self._rgb(path)), "image/png"

    def _rgb(self, path: Path) -> np.ndarray:
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
        index = onehot_to_index(onehot.astype(bool))
        try:
            transient = read_transient(self.ds, self.fid(fid), index.shape)
        except DatasetError:
            transient = None  # `interreal validate` names a broken transient mask; the objects still show
        if transient is not None:
            index[transient] = IGNORE  # shown as the ignore class
        data = png_bytes(index)
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
        return self._label_flags() + self._draw_asks() + _fine_part_flags(rep, figures) + out

    def _draw_asks(self) -> list[dict[str, Any]]:
        """Frames the motions report asks a part's mask on (an end of its motion is the labels' guess there, or a
        drawn mask decides what moves it), with its words why."""
        try:
            asks = frames_asked(self.ds)
        except (OSError, ValueError):
            return []
        have = {fid_of_index(i) for i in self._frames}
        return [{"fid": a["fid"], "reason": f"draw '{a['object']}' here: {a['why']}"}
                for a in asks if a["fid"] in have]

    def _label_flags(self) -> list[dict[str, Any]]:
        """Labels the motions report names as likely mistakes (the geometry measured another state there)."""
        try:
            flags = flagged_labels(self.ds)
        except (OSError, ValueError):
            return []
        return [{"fid": f["fid"], "reason": f"label {f['label']:.2f} of '{f['object']}' disagrees with its measured "
                                           f"motion ({f['measured']:.2f}): likely a mistake",
                 "fix": {"object": f["object"], "value": round(float(np.clip(f["measured"], 0.0, 1.0)), 2)}}
                for f in flags if isinstance(f["label"], (int, float)) and isinstance(f["measured"], (int, float))]

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
            if oid + 1 >= IGNORE:
                raise InputError(f"at most {IGNORE - 1} objects fit in a keyframe index PNG (254 = ignore, "
                                 f"255 = not annotated)")
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
        return split_labels(read_labels_raw(self.ds))

    def edit_labels(self, edits: list[dict[str, Any]], version: str | None) -> dict[str, Any]:
        """Apply [{frame, object, value (None = unset), base (the value read; None = none)}] all-or-nothing.

        Merges with changes made since `version` unless one of them touched the same (frame, object).
        """
        if not isinstance(edits, list) or not edits:
            raise InputError("no edits given")
        with L.edit_lock(self.ds):
            mapping = self.read_objects()
            self.check_files()
            raw = read_labels_raw(self.ds)
            current, bad = split_labels(raw)
            cur_version = file_version(self.ds / LABELS_FILE)
            parsed, conflicts = [], []
            for e in edits:
                key, name, value, conflict = parse_label_edit(e, mapping, self._frames, current)
                parsed.append((key, name, value))
                conflicts += [conflict] if conflict else []
            if conflicts:
                raise Conflict("; ".join(conflicts) + ". Your edit was not saved: check the new value and set it again.")
            merged = L.merge_labels(raw, parsed)  # bad entries nobody edited are kept exactly as they were
            write_labels(self.ds, merged)
            current, bad = split_labels(merged)
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
            index = read_index_png(self.keyframe_path(fid))
            if index is None and self.labelme_path(fid).exists():
                index = self._labelme_index(fid)
            return index, mask_versions(index)

    def _labelme_index(self, fid: str) -> np.ndarray | None:
        """The LabelMe keyframe rasterised as `interreal masks` reads it (GrabCut for rectangles), shapes it would
        refuse left out; None when the file is not LabelMe JSON."""
        objects = self.read_objects()
        try:
            return rasterise_labelme(self.labelme_path(fid), self.image_size(fid), [objects[i] for i in sorted(objects)],
                                     lambda: self._rgb(self.image_file(fid)), strict=False)
        except InputError:
            return None

    def edit_keyframe(self, fid: str, op: dict[str, Any]) -> tuple[np.ndarray | None, dict[str, str]]:
        """Paint or erase a polygon / box for one object on a keyframe, refusing if an affected object changed.

        op = {object: id, name, shape: polygon|box, points: [[x, y], ...] in image pixels, mode: paint|erase,
        versions: the per-object versions read with the keyframe}; or shape clicks, clicks: [[x, y, positive], ...]:
        the object's pixels become the clicks' answer (`clicking`), other objects' pixels stay. object -1
        (`IGNORE_OBJECT`) paints the ignore class (a person, a hand: value 254), which `interreal masks` propagates
        into the transient layer.
        """
        fid = self.fid(fid)
        if self.labelme_path(fid).exists():
            raise InputError(f"frame {fid} is annotated in keyframes/{fid}.json (LabelMe): edit it in LabelMe, "
                             f"or delete that file to draw this keyframe here")
        clicking = op.get("shape") == "clicks"
        w, h = self._clicked_size(fid) if clicking else self.image_size(fid)
        if clicking:  # the region is the clicks' answer, computed from the keyframe as read under the lock
            region, mode = None, "set"
            parse_clicks(op.get("clicks"), w, h)  # a click outside the frame: 400 before anything is read
        else:
            region = self._found_region(fid, op, w, h) if op.get("shape") == "found" else rasterise_shape(op, w, h)
            mode = op.get("mode", "paint")
        if mode not in ("paint", "erase", "set"):
            raise InputError(f"mode {str(mode)[:40]!r}: use paint or erase")
        oid = check_object(op.get("object"), self.read_objects(), IGNORE_OBJECT) if clicking else op.get("object")
        if isinstance(oid, bool) or not isinstance(oid, int):
            raise InputError(f"object {str(oid)[:40]!r} is not an object id (an integer: 0 for the first object)")
        seen = op.get("versions") or {}
        if not isinstance(seen, dict):
            raise InputError("versions must be the {value: hash} object read with the keyframe")
        with L.edit_lock(self.ds):
            mapping = self.read_objects()
            if oid != IGNORE_OBJECT and oid not in mapping:
                raise Conflict(f"object id {oid} does not exist (objects changed in another tab?); reload")
            if oid != IGNORE_OBJECT and op.get("name") is not None and mapping[oid] != op.get("name"):
                raise Conflict(f"object {oid} is now called {mapping[oid]!r}, not {op.get('name')!r}; reload")
            path = self.keyframe_path(fid)
            index = read_index_png(path)
            if index is None:
                index = np.zeros((h, w), dtype=np.uint8)  # a new keyframe: everything not drawn is background
            if index.shape != (h, w):
                raise InputError(f"{path} is {index.shape[1]}x{index.shape[0]} but the frame is {w}x{h}")
            current = mask_versions(index)
            k = IGNORE if oid == IGNORE_OBJECT else oid + 1
            if mode == "paint":
                affected = {k} | {int(v) for v in np.unique(index[region])} - {0, k, UNANNOTATED}
            else:
                affected = {k}
            changed = [mapping.get(v - 1, "ignore" if v == IGNORE else f"object {v - 1}") for v in sorted(affected) if current.get(str(v)) != seen.get(str(v))]
            if changed:
                raise Conflict(f"the mask of {', '.join(map(repr, changed))} on frame {fid} was changed elsewhere since "
                               f"this page read it; your stroke was not saved: look at the new mask and draw it again")
            if clicking:
                region = click_region(index, k, op, lambda: self._rgb(self.image_file(fid)),
                                      lambda: propagated(self.ds, fid, oid, IGNORE_OBJECT, (h, w)))
                if not region.any() and not path.exists():
                    return None, {}  # nothing asked for on a frame without a keyframe: no keyframe of background
            before = path.read_bytes() if path.exists() else None
            if mode == "paint":
                index[region] = k
            elif mode == "erase":
                index[region & (index == k)] = 0
            else:  # set (clicks): the object is the region; other objects' pixels are not in it and stay
                index[(index == k) & ~region] = 0
                index[region] = k
            self._ensure_keyframe_mapping(mapping)
            atomic.write_bytes(path, png_bytes(index))
            after = mask_versions(index)
            stack = self._undo.setdefault(fid, [])
            stack.append((before, after))
            del stack[:-UNDO_DEPTH]
            return index, after

    def _clicked_size(self, fid: str) -> tuple[int, int]:
        """(w, h) of a frame clicked on; a frame of the dataset without an image is an InputError (HTTP 400)."""
        try:
            return self.image_size(fid)
        except UnknownFrame:
            raise InputError(f"frame {self.fid(fid)} has no image in {IMAGES_DIR}/: there is nothing to click on") from None

    def _found_region(self, fid: str, op: dict[str, Any], w: int, h: int) -> np.ndarray:
        """The part of the frame's transient layer (a hand or arm `--transients auto` found, or the propagated ignore
        class) connected to the one clicked point: one click keeps it as painted ignore, or erases that painting."""
        if op.get("object") != IGNORE_OBJECT:
            raise InputError("a found hand or arm is kept as the ignore class: select 'ignore' (people, hands) first")
        pts = op.get("points")
        try:
            x, y = (float(v) for v in np.asarray(pts, dtype=np.float64).reshape(2))
        except (TypeError, ValueError):
            raise InputError("a found region is picked by one [x, y] point in image pixels") from None
        if not (np.isfinite(x) and np.isfinite(y)):
            raise InputError("a found region is picked by one finite [x, y] point")
        try:
            layer = read_transient(self.ds, fid, (h, w))
        except DatasetError as exc:
            raise InputError(f"the transient layer of frame {fid} is unreadable ({exc}); re-run `interreal masks`") from None
        col, row = min(w - 1, max(0, int(x))), min(h - 1, max(0, int(y)))
        if layer is None or not layer.any():
            raise InputError(f"nothing was found on frame {fid} (no transient layer there): run `interreal masks` "
                             f"(--transients auto finds hands and arms), or draw the hand with the polygon")
        n, comp = cv2.connectedComponents(layer.astype(np.uint8))
        k = comp[row, col]
        if k == 0:
            near = comp[max(0, row - FOUND_SNAP): row + FOUND_SNAP + 1, max(0, col - FOUND_SNAP): col + FOUND_SNAP + 1]
            hits = near[near > 0]
            if not hits.size:
                raise InputError(f"no found hand or arm at ({col}, {row}) on frame {fid}: click inside a grey region")
            k = int(np.bincount(hits).argmax())
        return comp == k

    def undo_keyframe(self, fid: str, versions: dict[str, str]) -> tuple[np.ndarray | None, dict[str, str]]:
        """Take back the last stroke on a keyframe, if the keyframe is still exactly as that stroke left it."""
        fid = self.fid(fid)
        with L.edit_lock(self.ds):
            stack = self._undo.get(fid) or []
            if not stack:
                raise InputError(f"nothing to undo on frame {fid}")
            path = self.keyframe_path(fid)
            current = mask_versions(read_index_png(path))
            before, after = stack[-1]
            if current != after or (versions or {}) != after:
                raise Conflict(f"keyframe {fid} was changed elsewhere after your last stroke; it cannot be undone "
                               f"safely: erase or redraw instead")
            stack.pop()
            if before is None:
                path.unlink()
                return None, {}
            atomic.write_bytes(path, before)
            index = read_index_png(path)
            return index, mask_versions(index)

    def delete_keyframe(self, fid: str, versions: dict[str, str]) -> None:
        with L.edit_lock(self.ds):
            path = self.keyframe_path(fid)
            index = read_index_png(path)
            if index is None:
                return
            if mask_versions(index) != (versions or {}):
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


def _fine_part_flags(rep: dict[str, Any], figures: dict[str, Any]) -> list[dict[str, Any]]:
    """The masks stage's `masks-fine-parts` warnings, each on the keyframe holding most of the object's fine parts
    (the first keyframe in an older report): where the user painted the lines and cables that propagation leaves
    out, and can leave them out of the object."""
    fine = figures.get("fine_parts") if isinstance(figures.get("fine_parts"), dict) else {}
    where = fine.get("keyframe") if isinstance(fine.get("keyframe"), dict) else {}
    keys = figures.get("keyframes") if isinstance(figures.get("keyframes"), list) else []
    out = []
    for w in rep.get("warnings") if isinstance(rep.get("warnings"), list) else []:
        if isinstance(w, dict) and w.get("cause") == "masks-fine-parts":
            fid = where.get(w.get("object"), keys[0] if keys else None)
            if fid is not None:
                out.append({"fid": str(fid), "reason": str(w.get("message", ""))})
    return out


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


__all__ = ["DatasetStore", "Conflict", "UnknownFrame", "Outside", "file_version", "encode_index_png", "finite_number"]
