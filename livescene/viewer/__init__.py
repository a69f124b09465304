"""The browser viewer of a trained run: look around it, with a slider per object (`livescene view RUN` is
`livescene/commands/view.py`).

- `session`: the run, views parsed from the page, one render at a time (stale requests dropped), save, sweep, command.
- `server`: the FastAPI routes and the uvicorn server, behind `interreal.localserver`'s rules (127.0.0.1, token,
  Host and Origin checks, request-size limit); the page is livescene/viewer_static/ (no build step, no CDN).
"""

from __future__ import annotations

from .server import ViewerServer, create_app, require_web

__all__ = ["ViewerServer", "create_app", "require_web"]  # the rest: livescene.viewer.session (torch)
