"""What each stage was computed from: fingerprints of its inputs, recorded in its report and compared by `validate`.

Why: a stage's outputs stay on disk when an upstream stage runs again (frames from another video, masks propagated
again from the annotation app), so a dataset can look complete while its poses describe other images. Each stage
records one fingerprint per input kind in `reports/<stage>.json` under `inputs.fingerprints` before it reads them;
`stale_stages` recomputes them and names every stage whose inputs changed since, and the stages downstream of it.

A fingerprint has two parts: `files` (names, sizes and modification times: one stat per file, compared first) and
`content` (a hash of the bytes, compared only when `files` differs, so a copied dataset, whose files have new
modification times, is not called stale while a rewritten file with other bytes is).
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable

from .conventions import IMAGES_DIR, LABELS_FILE, MAPPING_FILE, MASKS_DIR, TRANSFORMS_FILE
from . import atomic
from .images import list_images
from .layout import SFM_MASKS_DIR
from .report import read_report, report_path

# stages in the order they run; each may depend on the outputs of the ones before it
STAGES = ("frames", "masks", "poses", "labels", "motions")
# input kinds each stage's outputs are (a stage downstream of a stale one is stale too)
OUTPUTS: dict[str, tuple[str, ...]] = {
    "frames": ("images", "capture"),
    "masks": ("masks", "sfm_masks", "transients"),
    "poses": ("transforms",),
    "labels": ("labels", "mapping"),
    "motions": (),
}
MOTION_INPUTS = ("transforms", "labels", "masks", "mapping", "transients")  # what `interreal motions` reads
WHAT = {  # "<stage> were computed from ..."
    "images": "other images", "masks": "other masks", "sfm_masks": "other masks",
    "transients": "other transient masks", "transforms": "other poses",
    "labels": "other labels", "mapping": "another object list (mapping.yaml)", "keyframes": "other keyframes",
    "capture": "the frames of another capture (video or folder)",
}
KEYFRAME_SUFFIXES = (".png", ".json")
_CHUNK = 4 << 20
SOURCE_SAMPLE = 1 << 20  # bytes hashed at each end of a source video / file to identify it


def _image_files(ds: Path) -> list[Path]:

    return list_images(ds / IMAGES_DIR)


def _glob(sub: str, pattern: str) -> Callable[[Path], list[Path]]:
    def files(ds: Path) -> list[Path]:
        folder = ds / sub
        return sorted(p for p in folder.glob(pattern) if p.is_file()) if folder.is_dir() else []
    return files


def _one(name: str) -> Callable[[Path], list[Path]]:
    return lambda ds: [ds / name] if (ds / name).is_file() else []


FILES: dict[str, Callable[[Path], list[Path]]] = {
    "images": _image_files,
    "masks": _glob(MASKS_DIR, "*.npy"),
    "sfm_masks": _glob(SFM_MASKS_DIR, "*.png"),
    "transients": _glob("transients", "*.png"),  # interreal.transients
    "transforms": _one(TRANSFORMS_FILE),
    "labels": _one(LABELS_FILE),
    "mapping": _one(MAPPING_FILE),
}


# ----------------------------------------------------------------------------------------------------------------
# Fingerprints
# ----------------------------------------------------------------------------------------------------------------
def _digest(parts: Any) -> str:
    return hashlib.blake2b(json.dumps(parts, sort_keys=True, default=str).encode(), digest_size=10).hexdigest()


def files_key(paths: Iterable[Path]) -> str:
    """Names, sizes and modification times: a stat per file."""
    out = []
    for p in paths:
        st = p.stat()
        out.append((p.name, st.st_size, st.st_mtime_ns))
    return _digest(out)


def content_key(paths: Iterable[Path]) -> str:
    """Names and a hash of every byte (SHA-256: the fastest hashlib has where the CPU has SHA instructions)."""
    h = hashlib.sha256()
    for p in paths:
        h.update(p.name.encode() + b"\0")
        with open(p, "rb") as fh:
            for chunk in iter(lambda: fh.read(_CHUNK), b""):
                h.update(chunk)
        h.update(b"\1")
    return h.hexdigest()[:20]


def source_key(path: str | Path) -> str | None:
    """Identifies a capture cheaply (size and both ends of each file, by name): the same video copied elsewhere keeps
    its key, another video does not. None when it cannot be read."""
    path = Path(path)
    try:
        files = [path] if path.is_file() else sorted(p for p in path.iterdir() if p.is_file() and not p.name.startswith("."))
        h = hashlib.blake2b(digest_size=10)
        for p in files:
            size = p.stat().st_size
            h.update(f"{p.name if path.is_dir() else ''}\0{size}\0".encode())
            with open(p, "rb") as fh:
                h.update(fh.read(SOURCE_SAMPLE))
                if size > 2 * SOURCE_SAMPLE:
                    fh.seek(-SOURCE_SAMPLE, os.SEEK_END)
                    h.update(fh.read(SOURCE_SAMPLE))
        return h.hexdigest()
    except OSError:
        return None


def _keyframe_files(folder: Path) -> list[Path]:
    # mapping.yaml is left out: renaming an object rewrites it without changing any mask
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in KEYFRAME_SUFFIXES)


def _capture(ds: Path) -> str | None:
    """The frames' capture: the source key `interreal frames` recorded (None without a finished frames report)."""

    rep = read_report(ds, "frames") or {}
    fp = ((rep.get("inputs") or {}).get("fingerprints") or {}).get("source") if isinstance(rep, dict) else None
    return fp.get("content") if isinstance(fp, dict) else None


def fingerprint(ds: str | Path, kind: str) -> dict[str, Any] | None:
    """{"files", "content"} of one dataset input kind ("images", "masks", "transforms", ...); None for "capture"
    when the dataset has no frames report."""
    ds = Path(ds)
    if kind == "capture":
        cap = _capture(ds)
        return None if cap is None else {"files": cap, "content": cap}
    paths = FILES[kind](ds)
    return {"files": files_key(paths), "content": content_key(paths), "count": len(paths)}


def keyframes_fingerprint(ds: str | Path, folder: str | Path) -> dict[str, Any] | None:
    """Fingerprint of a keyframe folder (kept relative to DS when inside it, so a moved dataset still compares)."""
    ds, folder = Path(ds), Path(folder)
    try:
        paths = _keyframe_files(folder)
        fp = {"files": files_key(paths), "content": content_key(paths), "count": len(paths)}
    except OSError:
        return None
    try:
        fp["path"] = str(folder.resolve().relative_to(ds.resolve()))
        fp["inside"] = True
    except ValueError:
        fp["path"] = str(folder.resolve())
    return fp


def fingerprints(ds: str | Path, kinds: Iterable[str], keyframes: str | Path | None = None) -> dict[str, Any]:
    """What a stage records in `inputs.fingerprints` before it reads its inputs."""
    out: dict[str, Any] = {}
    for kind in kinds:
        fp = fingerprint(ds, kind)
        if fp is not None:
            out[kind] = fp
    if keyframes is not None:
        kf = keyframes_fingerprint(ds, keyframes)
        if kf is not None:
            out["keyframes"] = kf
    return out


def recorded(rep: dict | None) -> dict[str, Any]:
    """The fingerprints a report holds ({} for reports written before they were recorded)."""
    if not isinstance(rep, dict):
        return {}
    fps = (rep.get("inputs") or {}).get("fingerprints") if isinstance(rep.get("inputs"), dict) else None
    return fps if isinstance(fps, dict) else {}


# ----------------------------------------------------------------------------------------------------------------
# Staleness
# ----------------------------------------------------------------------------------------------------------------
@dataclass
class Stale:
    stage: str
    reasons: list[str]  # the input kinds that changed, or ["via <upstream stage>"]
    message: str


class _Current:
    """Current fingerprints, computed once per kind and only as far as needed (stat first, bytes on a mismatch)."""

    def __init__(self, ds: Path):
        self.ds = ds
        self._paths: dict[str, list[Path]] = {}
        self._files: dict[str, str] = {}
        self._content: dict[str, str] = {}

    def changed(self, kind: str, rec: dict) -> bool | None:
        """True / False, or None when it cannot be told (an external keyframe folder that is gone)."""
        if not isinstance(rec, dict):
            return None
        if kind == "capture":
            cap = _capture(self.ds)
            return None if cap is None else cap != rec.get("content")
        if kind == "keyframes":
            folder = Path(str(rec.get("path", "")))
            folder = self.ds / folder if rec.get("inside") else folder
            if not folder.is_dir():
                return None
            paths = _keyframe_files(folder)
            return files_key(paths) != rec.get("files") and content_key(paths) != rec.get("content")
        if kind not in FILES:
            return None
        if kind not in self._paths:
            self._paths[kind] = FILES[kind](self.ds)
            self._files[kind] = files_key(self._paths[kind])
        if self._files[kind] == rec.get("files"):
            return False
        if kind not in self._content:
            self._content[kind] = content_key(self._paths[kind])
        return self._content[kind] != rec.get("content")


def rerun_hint(ds: Path, stage: str, rep: dict | None = None) -> str:
    if stage == "masks":
        kf = recorded(rep).get("keyframes", {}).get("path") if rep else None
        kf = str(ds / kf) if kf and recorded(rep)["keyframes"].get("inside") else kf
        return f"run `interreal masks {ds} --keyframes {kf or 'DIR'}`"
    if stage == "poses":
        return f"run `interreal poses {ds}`"
    if stage == "motions":
        return f"run `interreal motions {ds}`"
    if stage == "labels":
        return (f"check them with `interreal label {ds} --list`, then import this capture's labels with "
                f"`interreal label {ds} --from FILE --replace` (or keep these ones, when they are right for it, "
                f"with `--from {ds / LABELS_FILE} --replace`)")
    return f"run `interreal {stage}` again"


def stale_stages(ds: str | Path) -> list[Stale]:
    """Every finished stage whose recorded inputs changed since it ran, then those computed from a stale stage."""

    ds = Path(ds)
    cur = _Current(ds)
    reports = {s: read_report(ds, s) for s in STAGES}
    out: list[Stale] = []
    stale: set[str] = set()
    for stage in STAGES:
        rep = reports[stage]
        if not isinstance(rep, dict) or rep.get("status") != "ok":
            continue
        fps = recorded(rep)
        changed = []
        for kind, rec in fps.items():
            try:
                if cur.changed(kind, rec):
                    changed.append(kind)
            except OSError:
                changed.append(kind)
        if changed:
            what = " and ".join(dict.fromkeys(WHAT.get(k, k) for k in changed))
            verb = "were set on" if stage == "labels" else "were computed from"
            out.append(Stale(stage, changed, f"stale: {stage} {verb} {what}; {rerun_hint(ds, stage, rep)}"))
            stale.add(stage)
            continue
        for upstream in STAGES[:STAGES.index(stage)]:
            if upstream in stale and any(k in fps for k in OUTPUTS[upstream]):
                out.append(Stale(stage, [f"via {upstream}"], f"stale: {stage} were computed from {upstream} that are "
                                 f"stale themselves; {rerun_hint(ds, upstream, reports[upstream])}, then "
                                 f"{rerun_hint(ds, stage, rep).removeprefix('run ')}"))
                stale.add(stage)
                break
    return out


def refresh(ds: str | Path, stage: str, kinds: Iterable[str]) -> None:
    """Record the current fingerprints of `kinds` in a stage's report after an edit known to keep its outputs valid
    (renaming an object rewrites keyframe annotations without changing a mask). Call it only when `unchanged` said
    so before the edit, so a real change is never hidden."""

    ds = Path(ds)
    rep = read_report(ds, stage)
    fps = recorded(rep)
    if not fps or rep.get("status") != "ok":
        return
    for kind in kinds:
        if kind not in fps:
            continue
        if kind == "keyframes":
            folder = Path(fps[kind].get("path", ""))
            new = keyframes_fingerprint(ds, ds / folder if fps[kind].get("inside") else folder)
        else:
            new = fingerprint(ds, kind)
        if new is not None:
            fps[kind] = new
    atomic.write_json(report_path(ds, stage), rep)


def unchanged(ds: str | Path, stage: str, kinds: Iterable[str]) -> bool:
    """Whether none of `kinds` changed since `stage` last ran (False without a finished report)."""
    ds = Path(ds)

    rep = read_report(ds, stage)
    fps = recorded(rep)
    if not fps or rep.get("status") != "ok":
        return False
    cur = _Current(ds)
    return not any(cur.changed(k, fps[k]) for k in kinds if k in fps)


