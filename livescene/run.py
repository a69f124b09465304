"""A trained run on disk: `Run`, `load_run`, and its checkpoints (read, fall back, write, migrate), the run lock.

Run folder (docs/interfaces.md "Trained run"): config.yaml, checkpoints/step_<n>.pt, latest.pt (atomic),
metrics.jsonl, objects.yaml, reports/train.json. Reading a run falls back from an unreadable latest.pt to the
newest intact checkpoints/step_*.pt, with a warning; `checkpoint_config` reads the settings of runs from older
versions (migration). The library every command reads runs through (`trainer` writes them).
"""

from __future__ import annotations

import contextlib
import fcntl
import io
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from interreal import atomic
from interreal.report import read_report

from .config import TrainConfig, from_dict
from .data import Views, load_views
from .device import select_device
from .errors import CheckpointError, LiveSceneError, OutputError, writing
from .field import LiveSceneModel
from .occupancy import OccupancyGrid


@dataclass
class Run:
    """A trained (or training) model with what is needed to render it."""

    run_dir: Path
    model: LiveSceneModel
    views: Views
    config: TrainConfig
    device: torch.device
    step: int = 0
    checkpoint: Path | None = None  # the file the model was read from (None: a model being trained)
    occupancy: OccupancyGrid | None = None  # the checkpoint's grid, or built on first use (`occupancy.grid_for`)

    @property
    def dataset(self):
        return self.views.dataset

    @property
    def names(self) -> list[str]:
        return self.views.names

    @property
    def box(self) -> tuple[torch.Tensor, torch.Tensor]:
        return (torch.as_tensor(self.views.box_lo, device=self.device),
                torch.as_tensor(self.views.box_hi, device=self.device))


def _checkpoint_path(run_dir: Path, which: str | int | None) -> Path:
    if which is None or which == "latest":
        path = run_dir / "latest.pt"
    elif isinstance(which, int) or str(which).isdigit():
        path = run_dir / "checkpoints" / f"step_{int(which):07d}.pt"
    else:
        path = Path(which)
    if not path.exists():
        raise CheckpointError(f"{path} not found: is {run_dir} a run folder of `livescene train`?")
    return path


CKPT_KEYS = ("step", "model", "config", "meta")  # what rendering needs
RESUME_KEYS = CKPT_KEYS + ("optimizer", "rng")  # what resuming needs too


def read_checkpoint(path: Path, keys: tuple[str, ...] = CKPT_KEYS) -> dict[str, Any]:
    """One checkpoint file, or CheckpointError saying why it cannot be used (truncated, not a checkpoint, NaN)."""
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means "not a usable checkpoint"
        raise CheckpointError(f"{path} is unreadable (truncated or not a checkpoint: {type(exc).__name__})") from exc
    missing = [k for k in keys if not isinstance(ckpt, dict) or k not in ckpt]
    if missing:
        raise CheckpointError(f"{path} is not a livescene checkpoint (no {', '.join(missing)})")
    if not isinstance(ckpt["meta"], dict) or not isinstance(ckpt["config"], dict) or not isinstance(ckpt["model"], dict):
        raise CheckpointError(f"{path} is not a livescene checkpoint (malformed meta/config/model)")
    bad = [k for k, t in ckpt["model"].items()
           if isinstance(t, torch.Tensor) and t.is_floating_point() and not bool(torch.isfinite(t).all())]
    if bad:
        raise CheckpointError(f"{path} holds non-finite weights ({bad[0]})")
    return ckpt


def checkpoint_files(run_dir: Path) -> list[Path]:
    """latest.pt, then checkpoints/step_*.pt newest first: the order `load_checkpoint` tries them in."""
    steps = sorted((run_dir / "checkpoints").glob("step_*.pt"), reverse=True)
    return [p for p in [run_dir / "latest.pt", *steps] if p.is_file()]


def load_checkpoint(run_dir: str | Path, which: str | int | None = None,
                    keys: tuple[str, ...] = CKPT_KEYS) -> tuple[dict[str, Any], Path]:
    """(checkpoint, path): the one asked for, or with `which` None / "latest" the newest intact one - latest.pt,
    else (a kill or a full disk truncated it) the newest checkpoints/step_*.pt that loads, with a warning."""
    run_dir = Path(run_dir)
    if which not in (None, "latest"):
        path = _checkpoint_path(run_dir, which)
        return read_checkpoint(path, keys), path
    candidates = checkpoint_files(run_dir)
    if not candidates:
        raise CheckpointError(f"{run_dir} holds no checkpoint (latest.pt, checkpoints/step_*.pt): is it a run folder "
                              f"of `livescene train`?")
    failures: list[str] = []
    for path in candidates:
        try:
            ckpt = read_checkpoint(path, keys)
        except CheckpointError as exc:
            failures.append(str(exc))
            continue
        if failures:
            print(f"livescene: warning: {failures[0]}; using {path} (step {ckpt['step']}), the newest intact "
                  f"checkpoint", file=sys.stderr)
        return ckpt, path
    raise CheckpointError(f"no intact checkpoint in {run_dir}: " + "; ".join(failures[:3])
                          + ("" if len(failures) <= 3 else f" (and {len(failures) - 3} more)"))


def checkpoint_config(ckpt: dict) -> TrainConfig:
    """The config a checkpoint was trained with; runs from before the background slice read k = 0 there, runs
    from before rigid parts or per-frame appearance have none."""
    try:
        cfg = from_dict(ckpt["config"])
    except LiveSceneError as exc:
        raise CheckpointError(f"the checkpoint's settings are unusable: {exc}") from exc
    if "background_k" not in ckpt["config"].get("model", {}):
        cfg.model.background_k = "zero"
    if cfg.model.motion == "auto":  # runs from before rigid parts
        cfg.model.motion = "none"
    if "appearance" not in ckpt["config"].get("model", {}):  # runs from before per-frame appearance have none,
        cfg.model.appearance = "off"  # whatever the default is now
    return cfg


def unfinished_note(run_dir: str | Path, step: int | None = None) -> str | None:
    """One line when the run's training did not finish (interrupted, failed, or killed while "running"): the
    commands that read it say they use its last checkpoint; None for a finished run (or one without a report)."""
    rep = read_report(run_dir, "train") or {}
    status = rep.get("status")
    if status is None:
        return None
    if status == "ok":
        return None
    at = f" (its last checkpoint, step {step}, is used)" if step is not None else ""
    why = {"interrupted": "was interrupted", "failed": f"failed ({rep.get('error', '?')})",
           "running": "is still training, or was killed"}.get(str(status), f"ended as {status!r}")
    return (f"note: {run_dir}'s training {why}{at}; continue it with "
            f"`livescene train DS --out {run_dir} --resume`")


def load_run(run_dir: str | Path, device: str = "auto", checkpoint: str | int | None = None,
             dataset: str | Path | None = None) -> Run:
    """Reopen a run: its model at the latest (or given) checkpoint, its dataset views and config."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise CheckpointError(f"{run_dir} is not a run folder: train one with `livescene train DS --out {run_dir}`")
    dev = select_device(device)
    ckpt, path = load_checkpoint(run_dir, checkpoint)
    cfg = checkpoint_config(ckpt)
    ds_path = Path(dataset) if dataset else Path(str(ckpt["meta"].get("dataset", "")))
    if not str(ds_path) or not ds_path.exists():
        # a run renders with its dataset's cameras, frame times, image size and object names: without it there is
        # nothing to place a camera or a frame time against, so a moved dataset must be pointed at
        raise LiveSceneError(f"the run's dataset {ds_path} is gone (moved or deleted): pass --dataset NEW_PATH "
                             f"(load_run(dataset=...)) to point at it")
    # validated (an invalid dataset is refused here); the masks' contents were read when the run trained, so a
    # render, eval or viewer start checks only their headers (0.4 s instead of 12 s on 300 frames at 960x540)
    views = load_views(ds_path, cfg, check_masks=False)
    check_run_dataset(ckpt["meta"], views, ds_path)
    views.box_lo = np.asarray(ckpt["meta"]["box_lo"], dtype=np.float32)
    views.box_hi = np.asarray(ckpt["meta"]["box_hi"], dtype=np.float32)
    model = LiveSceneModel(cfg.model, views.dataset.n_objects)
    try:
        model.load_state_dict(ckpt["model"])
    except RuntimeError as exc:
        raise CheckpointError(f"{path} does not fit the model its settings describe (another version, or another "
                              f"dataset's object count): {str(exc).splitlines()[0]}") from exc
    model.to(dev).eval()
    # the grid saved with the checkpoint (runs from before have none)
    grid = OccupancyGrid.from_state(ckpt.get("occupancy"), dev) if ckpt.get("occupancy") else None
    return Run(run_dir=run_dir, model=model, views=views, config=cfg, device=dev, step=int(ckpt["step"]),
               checkpoint=path, occupancy=grid if grid is not None and grid.step == int(ckpt["step"]) else None)


def check_run_dataset(meta: dict[str, Any], views: Views, ds_path: Path) -> None:
    """The dataset is the one the run was trained on: same object names and (runs that stored them) frames."""
    names = meta.get("names")
    if names is not None and list(names) != list(views.names):
        raise LiveSceneError(f"{ds_path} names the objects {views.names}, the run was trained on {list(names)}: "
                             f"it is not the run's dataset")
    frames = meta.get("frames")
    fids = [f.fid for f in views.dataset.frames]
    if frames is not None and list(frames) != fids:
        raise LiveSceneError(f"{ds_path} has {len(fids)} frames, not the {len(frames)} the run was trained on "
                             f"(or other ones): it is not the run's dataset")


def write_checkpoint(run_dir: Path, step: int, state: dict[str, Any], keep: int) -> Path:
    """checkpoints/step_<step>.pt and latest.pt, each written atomically; only the newest `keep` step files stay.
    OutputError (disk full, read-only) says which checkpoint a resume would start from."""
    buf = io.BytesIO()
    torch.save(state, buf)
    data = buf.getvalue()
    path = run_dir / "checkpoints" / f"step_{step:07d}.pt"
    try:
        with writing(path):
            atomic.write_bytes(path, data)
        with writing(run_dir / "latest.pt"):
            atomic.write_bytes(run_dir / "latest.pt", data)
    except OutputError as exc:
        intact = [p.name for p in checkpoint_files(run_dir)]
        raise OutputError(f"{exc}; " + (f"resume later with --resume (from {intact[0]})" if intact else
                                        "no checkpoint was written")) from exc
    for p in sorted((run_dir / "checkpoints").glob("step_*.pt"))[: -max(keep, 1)]:
        p.unlink(missing_ok=True)
    return path


@contextlib.contextmanager
def run_lock(run_dir: Path):
    """One process per run folder (a second `--resume` while one trains would interleave checkpoints); the lock
    goes away with the process, even on kill -9."""
    with writing(run_dir):
        run_dir.mkdir(parents=True, exist_ok=True)
        fh = open(run_dir / ".lock", "a+")
    with fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise LiveSceneError(f"{run_dir} is being trained by another process: wait for it, or stop it first") from None
        yield


def remove_stale_temporaries(run_dir: Path) -> list[Path]:
    """Delete the temporary files (`.NAME.XXXX.tmp`) an atomic write leaves when it is killed; under `run_lock`
    no other writer can own them."""
    gone = []
    for folder in (run_dir, run_dir / "checkpoints", run_dir / "reports"):
        for p in folder.glob(".*.tmp") if folder.is_dir() else []:
            with contextlib.suppress(OSError):
                p.unlink()
                gone.append(p)
    return gone
