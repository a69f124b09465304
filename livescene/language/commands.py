"""Spoken-style commands: "open the fridge" -> ("the fridge", 1.0) -> {"fridge door": 1.0}; grounding a query
among a run's objects (`livescene ground` is `livescene/commands/ground.py`).

Verbs: open / close / shut, "half open" (0.5), "open X halfway" (0.5), "open X 30%" / "open X to 30 %" (0.3),
"set X to 0.3". The official viewer understands only `^(open|close) (.*)`; the rest are the obvious extensions.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from interreal.dataset import load_dataset
from interreal.errors import InputError

from ..errors import LiveSceneError
from .encoders import TextEncoder, check_extra, get_encoder
from .retrieval import Retrieval, RetrievalConfig, check_query, require_match, retrieve, run_index


@dataclass(frozen=True)
class Command:
    query: str  # the object phrase, e.g. "the fridge"
    value: float  # target interaction state in [0, 1]
    verb: str  # normalised verb: open | close | half open | set


_POLITE = re.compile(r"^(please\s+|could you\s+|can you\s+)+|(\s+please)$")
_HALF_PREFIX = re.compile(r"^(half[\s-]*(?:way\s+)?open|partly open|partially open|open (?:it )?halfway)\s+(.+)$")
_HALF_SUFFIX = re.compile(r"^(open|close|shut)\s+(.+?)\s+(halfway|half[\s-]way|half|partly|partially|a bit)$")
_FULL_SUFFIX = re.compile(r"^(open|close|shut)\s+(.+?)\s+(fully|completely|all the way)$")
_PERCENT = re.compile(r"^(open|set)\s+(.+?)\s+(?:to\s+)?(\d+(?:\.\d+)?)\s*(%|percent)$")
_SET = re.compile(r"^set\s+(.+?)\s+to\s+(\d*\.?\d+)$")
_VERB = re.compile(r"^(open|close|shut)\s+(.+)$")


def parse_command(text: str) -> Command:
    """Parse a command; InputError (with the accepted forms) when it has no known verb or no object."""
    t = " ".join(str(text or "").lower().split()).strip(" .!?")
    t = _POLITE.sub("", t).strip()
    if not t:
        raise InputError("empty command: say e.g. \"open the fridge\", \"close the drawer\", \"half open the door\"")
    if m := _HALF_PREFIX.match(t):
        return Command(m.group(2), 0.5, "half open")
    if m := _PERCENT.match(t):
        value = float(m.group(3)) / 100.0
        return Command(m.group(2), _check(value, text), "set")
    if m := _SET.match(t):
        return Command(m.group(1), _check(float(m.group(2)), text), "set")
    if m := _HALF_SUFFIX.match(t):
        return Command(m.group(2), 0.5, "half open")
    if m := _FULL_SUFFIX.match(t):
        return Command(m.group(2), 1.0 if m.group(1) == "open" else 0.0, "open" if m.group(1) == "open" else "close")
    if m := _VERB.match(t):
        verb = "open" if m.group(1) == "open" else "close"
        return Command(m.group(2), 1.0 if verb == "open" else 0.0, verb)
    raise InputError(f"cannot read the command {text!r}: start with a verb, e.g. \"open the fridge\", "
                     f"\"close the drawer\", \"half open the door\", \"open the door 30%\", \"set the lid to 0.3\"")


def _check(value: float, text: str) -> float:
    if not 0.0 <= value <= 1.0:
        raise InputError(f"state {value:g} in {text!r} is outside [0, 1] (0 = closed, 1 = fully open)")
    return value


# ----------------------------------------------------------------------------------------------------------------
# Objects of a run, grounding a query
# ----------------------------------------------------------------------------------------------------------------
def object_texts(run_dir: str | Path, run: Any = None) -> tuple[list[str], dict[str, str]]:
    """Object names (id order) and descriptions of a run, without loading its model when possible.

    Names come from RUN/objects.yaml (written by the trainer), else from the run's dataset (mapping.yaml);
    descriptions from objects.yaml when it has them, else from the dataset's prompts.yaml.
    """
    run_dir = Path(run_dir)
    names, descs = _read_objects_yaml(run_dir / "objects.yaml")
    dataset = getattr(run, "dataset", None)
    if (not names or not descs) and dataset is None:
        dataset = _dataset_of(run_dir)
    if not names and dataset is not None:
        names = list(dataset.object_names)
    if not descs and dataset is not None:
        descs = dict(getattr(dataset, "prompts", {}) or {})
    if not names:
        raise LiveSceneError(f"{run_dir} names no objects (no objects.yaml, no readable dataset): is it a run "
                             f"folder written by `livescene train`?")
    return names, descs


def _read_objects_yaml(path: Path) -> tuple[list[str], dict[str, str]]:
    if not path.exists():
        return [], {}
    raw = yaml.safe_load(path.read_text()) or {}
    if isinstance(raw, dict) and "objects" in raw:
        raw = raw["objects"]
    names: list[str] = []
    descs: dict[str, str] = {}
    items = sorted(raw.items(), key=lambda kv: int(kv[0])) if isinstance(raw, dict) else list(enumerate(raw or []))
    for _, entry in items:
        if isinstance(entry, dict):
            name = str(entry.get("name", ""))
            if entry.get("description"):
                descs[name] = str(entry["description"])
        else:
            name = str(entry)
        names.append(name)
    return names, descs


def _dataset_of(run_dir: Path) -> Any:
    cfg_path = run_dir / "config.yaml"
    if not cfg_path.exists():
        return None
    cfg = yaml.safe_load(cfg_path.read_text()) or {}
    ds = cfg.get("dataset") or cfg.get("data") or (cfg.get("config") or {}).get("dataset")
    if not ds:
        return None
    path = Path(ds)
    if not path.is_absolute() and not path.exists():
        path = run_dir / ds
    try:
        return load_dataset(path)
    except Exception:  # noqa: BLE001 - a moved dataset only costs us the descriptions
        return None


def ground_query(run_dir: str | Path, query: str, *, encoder: TextEncoder | None = None, run: Any = None,
                 config: RetrievalConfig | None = None) -> Retrieval:
    """Ranked candidates for `query` among the run's objects (embeddings cached in RUN/language.npz)."""
    q = check_query(query)
    enc = encoder or get_encoder()
    names, descs = object_texts(run_dir, run)
    index = run_index(run_dir, names, descs, enc)
    return retrieve(index, q, enc, config)


def _run_dir_of(run: Any) -> Path:
    value = getattr(run, "run_dir", None)
    if value is None:
        raise LiveSceneError("cannot tell the run's folder: pass a Run from livescene.trainer.load_run")
    return Path(value)


def apply_command(run: Any, text: str, *, encoder: TextEncoder | None = None,
                  config: RetrievalConfig | None = None) -> dict[str, float]:
    """"open the fridge" -> {"fridge door": 1.0}: the state change a command asks for (for `livescene render`).

    `run` is a Run (from load_run) or a run folder. Raises InputError for an unreadable command and
    LiveSceneError "no object matches" (with the ranked candidates) when no object is close enough.
    """
    check_extra("livescene render --command")
    cmd = parse_command(text)
    run_dir = Path(run) if isinstance(run, (str, Path)) else _run_dir_of(run)
    result = ground_query(run_dir, cmd.query, encoder=encoder, run=None if isinstance(run, (str, Path)) else run,
                          config=config)
    return {require_match(result).name: cmd.value}
