"""Where the shared real captures live (tests and benchmarks read them; they are never copied into the repo)."""

from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent


def shared_data() -> Path:
    """`$INTERREAL_SHARED`, else `../shared/data` next to the repository."""
    env = os.environ.get("INTERREAL_SHARED")
    return Path(env) if env else REPO_ROOT.parent / "shared" / "data"


def require_shared(*parts: str) -> Path:
    """Path under the shared data root; FileNotFoundError with a clear message when it is missing."""
    path = shared_data().joinpath(*parts)
    if not path.exists():
        raise FileNotFoundError(
            f"shared data {path} is missing: put the project's shared/ folder next to the repository "
            f"or set INTERREAL_SHARED to its data/ folder"
        )
    return path
