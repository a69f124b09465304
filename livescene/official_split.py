"""`livescene eval --split official`: figures on the official LiveScene eval frames, so they compare with the paper's.

The official split (`interreal.official.official_positions`): real data evaluates on the frames left out of
`linspace(0, N-1, ceil(0.9 N))` of the frames sorted by file path (or transforms.json's explicit lists), synthetic
data on the even positions. A run only gives honest figures there when it never trained on those frames, which is
what `livescene train --set split=official` does; a run trained with our split (every 8th frame held out) is refused.
"""

from __future__ import annotations

from typing import Any

from interreal.official import SPLIT_KEYS, official_positions

from .errors import LiveSceneError

SPLITS = ("ours", "official")


def use_split(run: Any, split: str) -> dict[str, Any]:
    """Point the run's views at `split`'s held-out frames; what the result JSON records about it. LiveSceneError
    when the run trained on any official eval frame (its figures there would be on training frames)."""
    views = run.views
    if split == "ours":
        return {"split": "ours", "held_out_frames": len(views.held_out)}
    if split not in SPLITS:
        raise LiveSceneError(f"--split {split!r}: choose one of {', '.join(SPLITS)}")
    ds = views.dataset
    train, held = official_positions(ds.layout, ds.extra, [f.file_path for f in ds.frames])
    seen = sorted(set(held) & set(views.train))
    if seen:
        raise LiveSceneError(
            f"the run trained on {len(seen)} of the {len(held)} official eval frames (e.g. frame "
            f"{ds.frames[seen[0]].fid}): its figures there would not compare with the paper's; train with "
            f"`livescene train DS --out RUN --set split=official`, which holds those frames out")
    if not held:
        raise LiveSceneError(f"the official split of {ds.root} holds out no frame ({len(ds.frames)} frames)")
    views.held_out = held
    return {"split": "official", "held_out_frames": len(held),
            "how": ("even positions (synthetic data)" if ds.layout == "blender" else "transforms.json's file lists"
                    if any(k in ds.extra for k in SPLIT_KEYS) else "fraction 0.9 of the frames (real data)")}
