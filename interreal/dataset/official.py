"""Official data in our reader: raw label values normalised the official way (with a note, never a clip), mask pixels
with no channel set read as unknown. Only for folders interreal did not write that are in an official camera layout;
our own datasets stay strict (a 5.0 is a mistake there, not a fully open door).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from ..conventions import LABELS_FILE, REPORTS_DIR, TRANSFORMS_FILE, frame_id
from ..errors import DatasetError

def is_blender(meta: dict[str, Any]) -> bool:
    return "camera_angle_x" in meta and "fl_x" not in meta


def label_key_index(key: Any) -> int:
    """The frame number of a key_frame_value.yaml key as the official reader parses it (last `_` token)."""
    return int(str(key).split("_")[-1])


def label_columns(fids: list[str], labels: dict[Any, Any], names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(values, given) (N, M) as `read_attributes(fewshot=True)` builds them: the yaml value where a (frame, object)
    pair is labelled, 0 elsewhere."""
    by_frame: dict[int, dict[str, float]] = {}
    for key, entry in (labels or {}).items():
        by_frame[label_key_index(key)] = entry or {}
    values = np.zeros((len(fids), len(names)), np.float64)
    given = np.zeros_like(values, dtype=bool)
    for i, fid in enumerate(fids):
        entry = by_frame.get(int(fid), {})
        for j, name in enumerate(names):
            if name in entry:
                values[i, j] = float(entry[name])
                given[i, j] = True
    return values, given


# stages whose report means interreal wrote the dataset's images, masks, poses or labels (so its labels are states)
MAKING_STAGES = ("frames", "masks", "poses", "labels", "process", "synth_truth")


def is_official_data(root: str | Path, meta: dict[str, Any] | None = None) -> bool:
    """True for a folder interreal did not make (no report of a stage that writes images, masks, poses or labels;
    `interreal motions` on official data keeps it official) whose cameras are in an official layout: OmniSim
    (`camera_angle_x`) or Polycam (intrinsics on every frame). Only such folders may hold raw label values and
    mask pixels with no channel set."""
    root = Path(root)
    if any((root / REPORTS_DIR / f"{stage}.json").exists() for stage in MAKING_STAGES):
        return False
    if meta is None:
        try:
            meta = json.loads((root / TRANSFORMS_FILE).read_text())
        except (OSError, ValueError):
            return False
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        return False
    return is_blender(meta) or all(isinstance(f, dict) and "fl_x" in f for f in meta["frames"])


def raw_value_ok(value: Any) -> bool:
    """A finite number (official raw values need not lie in [0, 1])."""
    return (not isinstance(value, bool)) and isinstance(value, (int, float)) and math.isfinite(float(value))


_NOTED: set[tuple[str, str]] = set()


def note(root: Path, text: str) -> None:
    """One line on stderr, once per folder and message (the reader runs several times a command)."""
    key = (str(Path(root).resolve()), text)
    if key not in _NOTED:
        _NOTED.add(key)
        print(f"note: {root}: {text}", file=sys.stderr)


def normalise_raw_labels(root: Path, labels: dict[str, dict[str, Any]], frame_keys: list[str],
                         names: list[str]) -> dict[str, dict[str, float]]:
    """Labels with values outside [0, 1] (official raw values) min-max normalised per object over all frames, the
    unlabelled ones counted as 0, as the official reader does (over the whole sequence here, not per split); with
    a note. Labels already in [0, 1] are returned as they are."""
    flat = [float(v) for e in labels.values() for v in e.values()]
    if all(0.0 <= v <= 1.0 for v in flat):
        return {k: {n: float(v) for n, v in e.items()} for k, e in labels.items()}
    fids = [frame_id(k) for k in frame_keys]
    values, given = label_columns(fids, labels, names)
    lo, hi = values.min(axis=0), values.max(axis=0)
    out: dict[str, dict[str, float]] = {}
    spans = []
    for j, name in enumerate(names):
        if not given[:, j].any():
            continue
        if hi[j] - lo[j] <= 0:
            raise DatasetError(f"{root / LABELS_FILE}: '{name}' has the same value on every frame (unlabelled ones "
                               f"count as 0), so the official normalisation is 0 / 0; label a frame with another "
                               f"value")
        spans.append(f"'{name}' [{lo[j]:g}, {hi[j]:g}]")
    idx_of = {int(f): i for i, f in enumerate(fids)}
    for key, entry in labels.items():
        i = idx_of.get(label_key_index(key))
        row = out.setdefault(key, {})
        for name, v in entry.items():
            j = names.index(name) if name in names else -1
            if i is None or j < 0:
                continue  # a label of a frame / object that is not in the dataset: never read
            row[name] = float((float(v) - lo[j]) / (hi[j] - lo[j]))
    note(root, "key_frame_value.yaml holds raw values outside [0, 1] (official data): each object's values are "
               "min-max normalised over all frames, unlabelled frames counted as 0, as the official reader does "
               "(not clipped): " + ", ".join(spans) + " -> [0, 1]")
    return out
