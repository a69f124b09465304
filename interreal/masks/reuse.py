"""What a masks re-run takes from the last one: the stretches of frames a keyframe change does not touch.

Every frame between two keyframes is made by the two chains of that gap alone, every frame before the first (after
the last) keyframe by the one chain that starts there (`track`). So a stretch's labels, health cues, re-detections
and flow motion depend on nothing but its frames' images, its keyframes' annotations and the settings. A run stores
each stretch under a key of exactly those (`DS/cache/masks/<key>/`); the next run, one keyframe more, makes again only
the gap that keyframe splits: a round in the annotate app takes seconds, not the whole video. A stretch whose
keyframe leaves pixels unannotated is never stored (the keyframe's own labels take what its chains bring there).
The figures are the same as a run from scratch (`tests/test_masks_reuse.py` checks the masks bit for bit).
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Iterator

import cv2
import numpy as np

from .. import __version__, atomic
from ..conventions import UNANNOTATED
from ..report import files_fingerprint, fingerprint
from .redetect import Event

CACHE_VERSION = 2  # raise when a change makes stored stretches differ from what the chains now make
EVENT_LISTS = ("redetections", "refusals", "exits")  # the Propagator's lists of `redetect.Event`
DONE_FILE = "segment.npz"  # written last: a stretch without it was cut short and is made again


@dataclass(frozen=True)
class Segment:
    """A stretch the chains make on their own: "before" (frames 0..b-1, from keyframe b), "gap" (the frames between
    keyframes a and b) or "after" (frames a+1..b, from keyframe a). Its flow pairs are t -> t+1 for t in a..b-1."""

    kind: str
    a: int
    b: int

    @property
    def frames(self) -> range:
        return {"before": range(self.a, self.b), "gap": range(self.a + 1, self.b)}.get(self.kind,
                                                                                       range(self.a + 1, self.b + 1))

    @property
    def pairs(self) -> range:
        return range(self.a, self.b)

    @property
    def keys(self) -> tuple[int, ...]:
        return {"before": (self.b,), "gap": (self.a, self.b)}.get(self.kind, (self.a,))


def chain_segments(keys: list[int], n: int) -> list[Segment]:
    """The stretches of an n-frame run with these (sorted) keyframe positions, in the order the chains make them;
    every gap, even one with no frame between its keyframes (its flow pair's motion is a health cue)."""
    out = [Segment("before", 0, keys[0])] if keys[0] > 0 else []
    out += [Segment("gap", a, b) for a, b in zip(keys[:-1], keys[1:])]
    return out + ([Segment("after", keys[-1], n - 1)] if keys[-1] < n - 1 else [])


class Reuse:
    """One run's stretches, their keys, those stored by an earlier run (`found`) and the store they go to."""

    def __init__(self, root: Path, images: list[Path], anchors: dict[int, np.ndarray], settings: Any):
        self.root = root
        self.segments = chain_segments(sorted(anchors), len(images))
        digest = {k: hashlib.sha1(m.tobytes()).hexdigest() + str(m.shape) for k, m in anchors.items()}
        open_ends = {k for k, m in anchors.items() if (m == UNANNOTATED).any()}
        self.key: dict[Segment, str | None] = {
            s: None if open_ends.intersection(s.keys) else
            fingerprint("masks-segment", CACHE_VERSION, __version__, s.kind, s.a, s.b,
                        files_fingerprint(images[s.a:s.b + 1]), [digest[k] for k in s.keys], settings)
            for s in self.segments}
        self.found = {s for s, k in self.key.items() if k is not None and (root / k / DONE_FILE).is_file()
                      and all(self._frame(k, t).is_file() for t in s.frames)}
        self._of = {t: s for s in self.segments for t in s.frames}
        self._records: dict[Segment, dict[str, Any]] = {}  # the found stretches' DONE_FILE, read once
        self.failed: str | None = None  # why this run's stretches could not be kept (a full or read-only disk)

    def _frame(self, key: str, pos: int) -> Path:
        return self.root / key / f"{pos:06d}.png"

    def _record(self, s: Segment) -> dict[str, Any]:
        """A found stretch's health cue rows (by name), events (by list) and flow motion (per pair)."""
        if s not in self._records:
            with np.load(self.root / self.key[s] / DONE_FILE) as z:
                self._records[s] = {"cues": {name[5:]: z[name] for name in z.files if name.startswith("cues_")},
                                    "events": json.loads(str(z["events"])), "motion": z["motion"].tolist()}
        return self._records[s]

    @property
    def reused_frames(self) -> int:
        return sum(len(s.frames) for s in self.found)

    def save_frame(self, pos: int, labels: np.ndarray) -> None:
        """A made frame's labels ((H, W) uint8), kept for the next run when its stretch has a key."""
        s = self._of.get(pos)
        key = None if s is None or s in self.found or self.failed else self.key[s]
        if key is not None:
            try:
                atomic.write_bytes(self._frame(key, pos), cv2.imencode(".png", labels)[1].tobytes())
            except OSError as exc:  # the cache is a convenience: the run's own outputs do not wait on it
                self.failed = str(exc)

    def replay(self) -> Iterator[tuple[int, np.ndarray, dict[str, np.ndarray]]]:
        """(position, labels, health cue rows) of every frame of the stretches found, read back."""
        for s in sorted(self.found, key=lambda x: x.a):
            rows = self._record(s)["cues"]
            for i, t in enumerate(s.frames):
                labels = cv2.imread(str(self._frame(self.key[s], t)), cv2.IMREAD_UNCHANGED)
                if labels is None:
                    raise FileNotFoundError(f"{self._frame(self.key[s], t)} is unreadable: delete {self.root} and "
                                            f"run again")
                yield t, labels, {name: v[i] for name, v in rows.items()}

    def finish(self, cues: Any, prop: Any) -> None:
        """Store the stretches this run made (their cues, events and motion; the frames are there already), put the
        found ones' events and motion into `prop`, and delete every stretch this run did not use."""
        for s in self.segments:
            key, frames = self.key[s], list(s.frames)
            if s in self.found:
                rec = self._record(s)
                prop.motion.update(zip(s.pairs, rec["motion"]))
                for name in EVENT_LISTS:
                    getattr(prop, name).extend(Event(**{**e, "sides": tuple(e["sides"])}) for e in rec["events"][name])
            elif key is not None and not self.failed:
                events = {name: [asdict(e) for e in getattr(prop, name) if e.pos in s.frames] for name in EVENT_LISTS}
                arrays = {f"cues_{name}": v for name, v in cues.rows(frames).items()}
                try:
                    with atomic.atomic_open(self.root / key / DONE_FILE) as fh:
                        np.savez(fh, events=np.array(json.dumps(events)),
                                 motion=np.array([prop.motion.get(t, 0.0) for t in s.pairs]), **arrays)
                except OSError as exc:
                    self.failed = str(exc)
        for name in EVENT_LISTS:  # the chains append from two threads: one order, whatever ran first
            getattr(prop, name).sort(key=lambda e: (e.pos, e.obj, e.how))
        keep = {k for k in self.key.values() if k is not None}
        for d in (self.root.iterdir() if self.root.is_dir() else []):
            if d.name not in keep:
                shutil.rmtree(d, ignore_errors=True)


__all__ = ["Segment", "chain_segments", "Reuse", "CACHE_VERSION"]
