"""Maximum-probability retrieval: a text query -> the object it most probably means, with ranked candidates.

As in LiveScene, language is decoupled from the 3-D field at the object level: each object carries text
embeddings (its name and its description), a query is compared with them, and the object of maximum probability
is selected; its rendered probability map is then its mask in any view. Similarity of a query to an object is the
best cosine over the object's texts; probabilities are a softmax of similarities over the scene's objects.
A query whose best similarity is below `threshold` matches nothing (the user gets the ranked candidates instead).
The embeddings are cached with the run in RUN/language.npz (atomic), keyed by encoder id and texts.
"""

from __future__ import annotations

import io
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from interreal import atomic
from interreal.errors import InputError
from livescene.errors import LiveSceneError

from .encoders import TextEncoder

CACHE_FILE = "language.npz"


@dataclass
class RetrievalConfig:
    """threshold: minimum cosine similarity of the best object (MiniLM: unrelated text scores ~0.1-0.3,
    a name or paraphrase 0.45-0.9); temperature: softmax temperature turning similarities into probabilities."""

    threshold: float = 0.4
    temperature: float = 0.05


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

    @property
    def best(self) -> Candidate:
        return self.candidates[0]

    @property
    def ok(self) -> bool:
        return bool(self.candidates) and self.best.score >= self.threshold

    def table(self, top: int | None = None) -> str:
        rows = [f"  {i + 1}. {c.name!r:28s} score {c.score:.3f}  p {c.prob:.3f}  (by {c.matched})"
                for i, c in enumerate(self.candidates[:top])]
        return "\n".join(rows)

    def to_json(self) -> dict:
        return {"query": self.query, "threshold": self.threshold, "ok": self.ok,
                "object": self.best.name if self.ok else None,
                "candidates": [asdict(c) for c in self.candidates]}


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
    return q


def retrieve(index: ObjectIndex, query: str, encoder: TextEncoder,
             config: RetrievalConfig | None = None) -> Retrieval:
    """Rank the index's objects for `query` (never raises on a poor match: see `require_match`)."""
    cfg = config or RetrievalConfig()
    q = check_query(query)
    if encoder.id != index.encoder_id:
        raise LiveSceneError(f"the object embeddings were made with {index.encoder_id}, the query encoder is "
                             f"{encoder.id}: rebuild the index with the same encoder")
    qe = encoder.encode([q])[0]
    score, by_desc = index.similarities(qe)
    logits = score / max(cfg.temperature, 1e-6)
    prob = np.exp(logits - logits.max())
    prob /= prob.sum()
    order = np.argsort(-score, kind="stable")
    cands = [Candidate(int(i), index.names[i], float(score[i]), float(prob[i]),
                       "description" if by_desc[i] else "name") for i in order]
    return Retrieval(q, cands, cfg.threshold)


def require_match(result: Retrieval) -> Candidate:
    """The chosen object, or LiveSceneError "no object matches" listing the ranked candidates."""
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
