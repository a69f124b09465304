"""Maximum-probability retrieval: a text query -> the object it most probably means, with ranked candidates.

As in LiveScene, language is decoupled from the 3-D field at the object level: each object carries text
embeddings (its name and its description), a query is compared with them, and the object of maximum probability
is selected; its rendered probability map is then its mask in any view. Similarity of a query to an object is the
best cosine over the object's texts; probabilities are a softmax of similarities over the scene's objects.
A command ("open the top drawer") is also compared by its object phrase alone ("the top drawer"), and the words an
object's name shares with the query break near ties ("the right wardrobe door", not the left one).

Absent objects are refused by what else the query could mean, not by a bare similarity cut: the query is compared
with a vocabulary of common household things (`HOUSEHOLD`) less the entries nearest the scene's own objects (a
scene with a fridge door keeps "refrigerator" out of it); when some other thing reads clearly closer (by
`absent_margin`) than every object in the scene ("the dishwasher" -> "dishwasher", not the top drawer at 0.40), the
query is not in the scene. Below
`threshold` (the encoder's noise level) nothing matches either. The user gets the ranked candidates instead.
The embeddings are cached with the run in RUN/language.npz (atomic), keyed by encoder id and texts.
"""

from __future__ import annotations

import io
import re
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Sequence

import numpy as np

from interreal import atomic
from interreal.errors import InputError
from livescene.errors import LiveSceneError

from .encoders import TextEncoder

CACHE_FILE = "language.npz"
# things found in homes, for telling an absent object from a present one (none is specific to our scenes)
HOUSEHOLD = (
    "refrigerator", "freezer", "dishwasher", "washing machine", "clothes dryer", "oven", "stove", "microwave",
    "toaster", "kettle", "coffee machine", "sink", "tap", "kitchen cabinet", "cupboard", "pantry", "drawer",
    "dresser", "wardrobe", "closet", "bookshelf", "shelf", "table", "desk", "chair", "sofa", "armchair", "bed",
    "nightstand", "lamp", "ceiling light", "light switch", "window", "curtain", "blinds", "front door", "garage door",
    "gate", "door", "television", "TV", "remote control", "computer", "laptop", "monitor", "keyboard", "phone",
    "speaker", "radio", "bathtub", "shower", "toilet", "mirror", "medicine cabinet", "trash can", "laundry basket",
    "box", "chest", "suitcase", "backpack", "plant", "painting", "clock", "fan", "air conditioner", "heater",
    "radiator", "fireplace", "stairs", "carpet", "rug", "pillow", "blanket", "book", "bottle", "cup", "plate", "car",
    "bicycle")
OWN_NEAREST = 2  # each object text keeps its this many nearest household entries out of the absent vocabulary ...
OWN_SIM = 0.5  # ... when they are at least this close (a paraphrase of the object, not another thing)
TIE_WEIGHT = 0.1  # the share of an object's name words the query repeats, times this, is added to its score
_COMMAND = re.compile(r"^(?:please\s+)?(?:open|close|shut|pull(?: out| open)?|push(?: in)?|lift|lower|raise|"
                      r"slide(?: out| in)?|swing(?: open)?)\s+(.+)$")
_STOP = {"the", "a", "an", "of", "to", "my", "this", "that", "on", "in", "with"}

@dataclass
class RetrievalConfig:
    """threshold: minimum cosine similarity of the best object (MiniLM: unrelated text scores ~0.1-0.3, a name or
    paraphrase 0.3-0.9; absent objects are refused by `refuse_absent`, not by this); temperature: softmax temperature
    turning similarities into probabilities; refuse_absent: refuse a query that reads closer to a household thing
    the scene does not hold than to any of its objects."""

    threshold: float = 0.3
    temperature: float = 0.05
    refuse_absent: bool = True
    # by this much: on a development set of 20 absent and 40 present queries over two simulated scenes (the
    # benchmark, recipes/bench_ground.py, scores a separate set), absent ones read 0.14-0.5 closer to a household
    # thing; present ones, with their objects known by name alone (no prompts), at most 0.1 closer but for one
    absent_margin: float = 0.1


@dataclass
class Candidate:
    index: int
    name: str
    score: float  # best cosine similarity over the object's texts
    prob: float  # softmax(score / temperature) over the scene's objects
    matched: str  # which text matched best: "name" or "description"


@dataclass
class Retrieval:
    query: str
    candidates: list[Candidate]  # best first
    threshold: float
    reads_as: str | None = None  # a household thing the query reads closer to than any object here: absent
    reads_as_score: float = 0.0

    @property
    def best(self) -> Candidate:
        return self.candidates[0]

    @property
    def ok(self) -> bool:
        return bool(self.candidates) and self.best.score >= self.threshold and self.reads_as is None

    def table(self, top: int | None = None) -> str:
        rows = [f"  {i + 1}. {c.name!r:28s} score {c.score:.3f}  p {c.prob:.3f}  (by {c.matched})"
                for i, c in enumerate(self.candidates[:top])]
        return "\n".join(rows)

    def to_json(self) -> dict:
        return {"query": self.query, "threshold": self.threshold, "ok": self.ok,
                "object": self.best.name if self.ok else None, "reads_as": self.reads_as,
                "reads_as_score": round(self.reads_as_score, 4), "candidates": [asdict(c) for c in self.candidates]}


@dataclass
class ObjectIndex:
    """Text embeddings of a scene's objects: one name (+ optional description) per object, id order."""

    names: list[str]
    descriptions: list[str]  # "" where an object has none
    encoder_id: str
    name_emb: np.ndarray  # (M, D) float32, L2-normalised
    desc_emb: np.ndarray  # (M, D); rows without a description are zero
    extra: dict = field(default_factory=dict)

    @classmethod
    def build(cls, names: Sequence[str], descriptions: dict[str, str] | Sequence[str] | None,
              encoder: TextEncoder) -> "ObjectIndex":
        names = [str(n) for n in names]
        if not names:
            raise LiveSceneError("the run has no objects: grounding needs at least one named object (mapping.yaml)")
        descs = _descriptions_list(names, descriptions)
        name_emb = encoder.encode([n.replace("_", " ") for n in names])
        desc_emb = np.zeros_like(name_emb)
        have = [i for i, d in enumerate(descs) if d]
        if have:
            desc_emb[have] = encoder.encode([descs[i] for i in have])
        return cls(names, descs, encoder.id, name_emb.astype(np.float32), desc_emb.astype(np.float32))

    def matches(self, names: Sequence[str], descriptions, encoder_id: str) -> bool:
        return (self.encoder_id == encoder_id and list(self.names) == [str(n) for n in names]
                and self.descriptions == _descriptions_list(list(self.names), descriptions))

    def save(self, path: str | Path) -> None:
        buf = io.BytesIO()
        np.savez(buf, names=np.array(self.names, dtype=str), descriptions=np.array(self.descriptions, dtype=str),
                 encoder_id=np.array(self.encoder_id), name_emb=self.name_emb, desc_emb=self.desc_emb)
        atomic.write_bytes(path, buf.getvalue())

    @classmethod
    def load(cls, path: str | Path) -> "ObjectIndex":
        with np.load(path, allow_pickle=False) as z:
            return cls([str(s) for s in z["names"]], [str(s) for s in z["descriptions"]], str(z["encoder_id"]),
                       z["name_emb"].astype(np.float32), z["desc_emb"].astype(np.float32))

    def similarities(self, query_emb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(M,) best cosine per object and (M,) bool "description matched better than the name"."""
        s_name = self.name_emb @ query_emb
        has = np.linalg.norm(self.desc_emb, axis=1) > 0
        s_desc = np.where(has, self.desc_emb @ query_emb, -np.inf)
        return np.maximum(s_name, s_desc), s_desc > s_name


def _descriptions_list(names: list[str], descriptions) -> list[str]:
    if descriptions is None:
        return [""] * len(names)
    if isinstance(descriptions, dict):
        return [str(descriptions.get(n, "") or "").strip() for n in names]
    descs = [str(d or "").strip() for d in descriptions]
    if len(descs) != len(names):
        raise ValueError(f"{len(descs)} descriptions for {len(names)} objects")
    return descs


def check_query(query: str | None) -> str:
    q = " ".join(str(query or "").split())
    if not q:
        raise InputError("empty query: say which object, e.g. \"the fridge\" or \"the thing that keeps food cold\"")
    if not _words(q):
        raise InputError(f"the query {q!r} names nothing (only words like 'the', 'a', 'of'): say which object, e.g. "
                         f"\"the fridge\" or \"the thing that keeps food cold\"")
    return q


def object_phrase(query: str) -> str:
    """The object a command names: "open the top drawer" -> "the top drawer" (the query itself otherwise)."""
    m = _COMMAND.match(query.lower().strip(" .!?"))
    return m.group(1) if m else query


def _words(text: str) -> set[str]:
    return {w for w in re.findall(r"[a-z0-9]+", text.lower()) if w not in _STOP}


def name_overlap(name: str, query: str) -> float:
    """The share of `name`'s words that `query` repeats (0..1): breaks near ties between similar names."""
    words = _words(name.replace("_", " "))
    return len(words & _words(query)) / len(words) if words else 0.0


@lru_cache(maxsize=4)
def _household(encoder: TextEncoder) -> np.ndarray:
    return encoder.encode(list(HOUSEHOLD))


def absent_vocabulary(index: ObjectIndex, encoder: TextEncoder) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The household things this scene does not hold, as (words, (K, D) embeddings), and (J, D) those it does: each
    object text's OWN_NEAREST nearest `HOUSEHOLD` entries at OWN_SIM or closer (a scene's fridge door owns
    "refrigerator"; a query close to an owned word is about the scene, "the notebook computer" for a laptop lid)."""
    vocab = _household(encoder)
    own = [index.name_emb] + [index.desc_emb[np.linalg.norm(index.desc_emb, axis=1) > 0]]
    sims = np.concatenate(own, 0) @ vocab.T
    drop = {int(j) for row in sims for j in np.argsort(-row)[:OWN_NEAREST] if row[j] >= OWN_SIM}
    keep = [j for j in range(len(HOUSEHOLD)) if j not in drop]
    return [HOUSEHOLD[j] for j in keep], vocab[keep], vocab[sorted(drop)]


def retrieve(index: ObjectIndex, query: str, encoder: TextEncoder,
             config: RetrievalConfig | None = None) -> Retrieval:
    """Rank the index's objects for `query` (never raises on a poor match: see `require_match`)."""
    cfg = config or RetrievalConfig()
    q = check_query(query)
    if encoder.id != index.encoder_id:
        raise LiveSceneError(f"the object embeddings were made with {index.encoder_id}, the query encoder is "
                             f"{encoder.id}: rebuild the index with the same encoder")
    phrase = object_phrase(q)
    qes = encoder.encode([q] if phrase == q else [q, phrase])
    pairs = [index.similarities(qe) for qe in qes]
    pick = int(np.argmax([p[0].max() for p in pairs]))
    score, by_desc = pairs[pick]
    ranked = score + TIE_WEIGHT * np.array([name_overlap(n, q) for n in index.names])
    logits = score / max(cfg.temperature, 1e-6)
    prob = np.exp(logits - logits.max())
    prob /= prob.sum()
    order = np.argsort(-ranked, kind="stable")
    cands = [Candidate(int(i), index.names[i], float(score[i]), float(prob[i]),
                       "description" if by_desc[i] else "name") for i in order]
    out = Retrieval(q, cands, cfg.threshold)
    if cfg.refuse_absent:
        words, vocab, owned = absent_vocabulary(index, encoder)
        if len(words):
            other = vocab @ qes[pick]
            here = max(float(score.max()), float((owned @ qes[pick]).max()) if len(owned) else -1.0)
            j = int(np.argmax(other))
            if other[j] > here + cfg.absent_margin:
                out.reads_as, out.reads_as_score = words[j], float(other[j])
    return out


def require_match(result: Retrieval) -> Candidate:
    """The chosen object, or LiveSceneError "no object matches" listing the ranked candidates."""
    if result.reads_as is not None:
        raise LiveSceneError(f"no object matches {result.query!r}: it is not in this scene (it reads as "
                             f"{result.reads_as!r}, {result.reads_as_score:.3f}, clearly closer than any object "
                             f"here); nearest objects:\n"
                             f"{result.table()}\nname one of them, or describe an object with "
                             f"`interreal label DS --describe NAME TEXT`")
    if not result.ok:
        raise LiveSceneError(f"no object matches {result.query!r} (best similarity {result.best.score:.3f} < "
                             f"threshold {result.threshold:.3f}); candidates:\n{result.table()}\n"
                             f"rephrase the query with an object's name, or lower --threshold")
    return result.best


def run_index(run_dir: str | Path, names: Sequence[str], descriptions, encoder: TextEncoder) -> ObjectIndex:
    """The run's cached object embeddings (RUN/language.npz), computed and stored atomically on first use."""
    path = Path(run_dir) / CACHE_FILE
    if path.exists():
        try:
            cached = ObjectIndex.load(path)
        except (OSError, ValueError, KeyError):
            cached = None
        if cached is not None and cached.matches(names, descriptions, encoder.id):
            return cached
    index = ObjectIndex.build(names, descriptions, encoder)
    try:
        index.save(path)
    except OSError:  # a read-only run folder still grounds; it just recomputes next time
        pass
    return index
