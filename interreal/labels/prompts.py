"""Object descriptions for language grounding (DS/prompts.yaml) carried in from a capture's annotations.

A capture's annotations hold `prompts.yaml` (object name -> one line of what it is or does) beside its keyframes;
`interreal process` imports it with the keyframes, so "the thing that keeps food cold" finds the fridge door in the
trained run. Objects without a description are grounded by name alone (`validate` says which).
"""

from __future__ import annotations

from difflib import get_close_matches
from pathlib import Path
from typing import Any

import yaml

from ..dataset import read_prompts, write_prompts
from ..errors import InputError
from ..layout import PROMPTS_FILE
from .objects import edit_lock, read_objects


def find_prompts(*near: Path | None) -> Path | None:
    """The `prompts.yaml` a capture keeps beside (or in) its keyframe folder or labels file; None when none."""
    for p in near:
        if p is None:
            continue
        p = Path(p)
        for folder in ((p, p.parent) if p.is_dir() else (p.parent,)):
            if (folder / PROMPTS_FILE).is_file():
                return folder / PROMPTS_FILE
    return None


def read_prompt_file(path: Path) -> dict[str, str]:
    """{object name: description} from a YAML mapping; InputError naming the file and entry otherwise."""
    try:
        raw: Any = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise InputError(f"{path}: not a readable YAML file ({exc}); it maps object names to one-line "
                         f"descriptions, e.g. 'fridge door: the thing that keeps food cold'") from None
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise InputError(f"{path}: expected object name -> description, got a {type(raw).__name__}")
    out = {}
    for name, text in raw.items():
        if not isinstance(text, str) or not text.strip():
            raise InputError(f"{path}: the description of {name!r} must be a line of text, got {text!r}")
        out[str(name).strip()] = " ".join(text.split())
    return out


def import_prompts(ds: str | Path, path: Path, overwrite: bool = True) -> dict[str, Any]:
    """Merge `path`'s descriptions into DS/prompts.yaml for the dataset's objects (`overwrite`: a description the
    dataset already has is replaced; else only objects without one get it). Names the dataset does not have are
    skipped and reported (with the closest object name). Returns figures: imported, skipped, without."""
    ds = Path(ds)
    given = read_prompt_file(path)
    with edit_lock(ds):
        objects = list(read_objects(ds).values())
        prompts = read_prompts(ds)
        imported, skipped = [], {}
        for name, text in given.items():
            if name not in objects:
                close = get_close_matches(name, objects, n=1)
                skipped[name] = close[0] if close else None
                continue
            if overwrite or not prompts.get(name):
                prompts[name] = text
                imported.append(name)
        if imported:
            write_prompts(ds, prompts)
    return {"file": str(path), "imported": imported, "skipped": skipped,
            "without": [n for n in objects if not prompts.get(n)]}
