"""`livescene train`: fit the LiveScene model to a dataset; `load_run` reopens a trained run.

Run folder (docs/interfaces.md "Trained run"): config.yaml, checkpoints/step_<n>.pt, latest.pt (atomic),
metrics.jsonl, objects.yaml, reports/train.json. `--resume` restores weights, optimiser, step and every random
generator, so a killed run continues exactly as if it had not stopped. A NaN/inf loss rolls back to the last
good checkpoint with a halved learning rate; after `max_divergence_retries` it stops with DivergenceError.

Inputs are checked before the optimiser can be blamed: the dataset must pass `interreal validate` (`load_views`),
the settings their types and ranges (`check_config`). Reading a run falls back from an unreadable latest.pt to the
newest intact checkpoints/step_*.pt, with a warning. A resume drops the metrics.jsonl records past the step it
resumes from (the steps are trained again), and leaves a finished run untouched.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import io
import json
import math
import os
import random
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from interreal import atomic
from interreal.dataset import Intrinsics
from interreal.report import StageReport, read_report

from . import losses as L
from .config import TrainConfig, apply_overrides, check_config, from_dict, load_preset, preset_names, resolve_sizes
from .data import RayData, Views, closest_point_depth, load_views
from .device import JEMALLOC_ENV, ThreadTrial, configure_threads, describe, reexec_with_jemalloc, select_device
from .errors import CheckpointError, DivergenceError, LiveSceneError, OutputError, writing
from .field import LiveSceneModel
from .sampler import render_rays

REGULARISERS = ("k_smooth", "k_smooth_proposal", "l1_k", "l1_k_proposal", "plane_tv", "plane_tv_proposal",
                "plane_tv_prob")


# ----------------------------------------------------------------------------------------------------------------
# Run
# ----------------------------------------------------------------------------------------------------------------
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
    occupancy: Any = None  # its `livescene.occupancy.OccupancyGrid` (the checkpoint's, or built on first use)

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


def build_model(cfg: TrainConfig, views: Views) -> tuple[TrainConfig, LiveSceneModel]:
    """Resolve the scene-driven sizes and build the model (its parameter count ignores the object count)."""
    cfg = from_dict(cfg.to_dict())
    cfg.model = resolve_sizes(cfg.model, views.scene_info())
    if cfg.sampler.near_auto > 0:
        closest = closest_point_depth(views.dataset, views.c2w_gl, views.intrinsics)
        if closest is not None:
            cfg.sampler.near = max(cfg.sampler.near, round(cfg.sampler.near_auto * closest, 4))
    n = views.dataset.n_objects
    if n > cfg.model.max_objects:
        # more objects than slots: widen the slots (only the probability field's and the variable's input and
        # output layers grow, a few hundred parameters per object) rather than refuse the scene
        print(f"livescene train: {n} objects > {cfg.model.max_objects} object slots: using {n} slots",
              file=sys.stderr)
        cfg.model.max_objects = n
    motions = part_motions(cfg.model.motion, views)
    cfg.model.motion = "rigid" if motions else "none"
    model = LiveSceneModel(cfg.model, n)
    if motions:
        model.motions.load(motions)
    return cfg, model


def part_motions(mode: str, views: Views) -> list | None:
    """The dataset's rigid part motions per object (None where an object has none) when `mode` asks for them:
    "auto" takes them when `articulation.json` names any object, "rigid" requires it, "none" never."""
    ds = views.dataset
    found = [ds.articulation.get(name) for name in views.names]
    if mode == "none" or (mode == "auto" and not any(found)):
        return None
    if not any(found):
        raise LiveSceneError(f"model.motion=rigid but {ds.root} has no part motions (articulation.json): "
                             f"run `interreal motions {ds.root}`, or train with --set model.motion=none")
    return found


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
    from before rigid parts have none."""
    try:
        cfg = from_dict(ckpt["config"])
    except LiveSceneError as exc:
        raise CheckpointError(f"the checkpoint's settings are unusable: {exc}") from exc
    if "background_k" not in ckpt["config"].get("model", {}):
        cfg.model.background_k = "zero"
    if cfg.model.motion == "auto":  # runs from before rigid parts
        cfg.model.motion = "none"
    return cfg


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
    from .occupancy import OccupancyGrid  # the grid saved with the checkpoint (runs from before have none)

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


# ----------------------------------------------------------------------------------------------------------------
# Training
# ----------------------------------------------------------------------------------------------------------------
def within_side(intr: Intrinsics, side: int) -> Intrinsics:
    """The camera scaled down (never up) so its longer side is at most `side` pixels: evaluation renders."""
    s = min(1.0, side / max(intr.w, intr.h))
    return intr.scaled(max(1, round(intr.w * s)), max(1, round(intr.h * s)))


def lr_factor(step: int, cfg: TrainConfig, time_frac: float = 0.0) -> float:
    """Linear warm-up, then cosine decay to `lr_final_ratio`.

    `time_frac` (elapsed / time budget) ends the decay with a `--max-minutes` budget too: a run stopped by the clock
    would otherwise stop at full learning rate, never taking the final small steps (0.5-1 dB on the CPU preset).
    """
    if step < cfg.warmup:
        return (step + 1) / max(cfg.warmup, 1)
    frac = min(1.0, max((step - cfg.warmup) / max(cfg.steps - cfg.warmup, 1), time_frac))
    return cfg.lr_final_ratio + (1 - cfg.lr_final_ratio) * 0.5 * (1 + math.cos(math.pi * frac))


class Trainer:
    def __init__(self, dataset: str | Path, run_dir: str | Path, cfg: TrainConfig, device: str = "auto",
                 resume: bool = False, max_minutes: float = 0.0, show_progress: bool = True):
        self._t_init = time.perf_counter()
        self.run_dir = Path(run_dir)
        self.device = select_device(device)
        self.max_minutes = max_minutes
        self.show_progress = show_progress
        self.ckpt_dir = self.run_dir / "checkpoints"
        resume_ckpt = None
        if resume:
            if not checkpoint_files(self.run_dir):
                raise CheckpointError(f"nothing to resume: {self.run_dir} holds no checkpoint (train without --resume)")
            resume_ckpt, _ = load_checkpoint(self.run_dir, None, RESUME_KEYS)
            steps = cfg.steps
            cfg = checkpoint_config(resume_ckpt)
            cfg.steps = max(steps, cfg.steps) if steps else cfg.steps
            dataset = resume_ckpt["meta"]["dataset"]
            if not Path(dataset).exists():
                raise LiveSceneError(f"the run's dataset {dataset} is gone (moved or deleted): put it back to resume")
        elif checkpoint_files(self.run_dir):
            raise LiveSceneError(f"{self.run_dir} already holds a run: add --resume to continue it or choose another --out")
        check_config(cfg)  # settings named before any data is read (not "training diverged" later)
        self.dataset_path = Path(dataset).resolve()
        torch.manual_seed(cfg.seed)
        views = load_views(self.dataset_path, cfg)
        if resume_ckpt is not None:
            check_run_dataset(resume_ckpt["meta"], views, self.dataset_path)
            views.box_lo = np.asarray(resume_ckpt["meta"]["box_lo"], dtype=np.float32)
            views.box_hi = np.asarray(resume_ckpt["meta"]["box_hi"], dtype=np.float32)
            self.cfg = cfg
            self.model = LiveSceneModel(cfg.model, views.dataset.n_objects)
        else:
            self.cfg, self.model = build_model(cfg, views)
        self.views = views
        self.model.to(self.device)
        self.data = RayData(views, self.device)
        self.hulls: dict[str, dict] = {}
        if resume_ckpt is None and self.model.motions is not None:
            from .articulation import fit_hulls

            self.hulls = fit_hulls(self.model.motions, part_motions("rigid", views), views, self.data.mask.numpy())
        self.box = (torch.as_tensor(views.box_lo, device=self.device), torch.as_tensor(views.box_hi, device=self.device))
        groups = [{"params": [p for p in ps if p.requires_grad], "name": n}
                  for n, ps in self.model.param_groups().items()]
        self.opt = torch.optim.Adam([g for g in groups if g["params"]], lr=self.cfg.lr, eps=1e-15, fused=True)
        self.gen = torch.Generator().manual_seed(self.cfg.seed)
        self.gen_dev = torch.Generator(device=self.device).manual_seed(self.cfg.seed + 1)
        self.step = 0
        self.lr_scale = 1.0
        self.retries = 0
        self.elapsed = 0.0  # training seconds (without evaluation), carried across resumes
        # seconds spent outside training steps (loading, evaluations, checkpoints): `max_minutes` bounds the whole
        # command, so they come out of the training time; carried across resumes, untouched by rollbacks
        self.overhead = 0.0
        self._eval_s_per_px = 0.0  # measured on the periodic evals, to reserve time for the final one
        self._ckpt_s = 0.0
        self._grid_s = 0.0  # the occupancy grid built after the last step (estimated up front with a time limit)
        self.eval_cursor = 0
        if resume_ckpt is not None:
            self._restore(resume_ckpt)
            self.overhead = float(resume_ckpt["meta"].get("overhead_s", 0.0))
            self._eval_s_per_px = float(resume_ckpt["meta"].get("eval_s_per_px", 0.0))

    # -- checkpoints ---------------------------------------------------------------------------------------------
    def _state(self) -> dict[str, Any]:
        return {
            "step": self.step,
            "model": self.model.state_dict(),
            "optimizer": self.opt.state_dict(),
            "rng": {"gen": self.gen.get_state(), "gen_dev": self.gen_dev.get_state(), "torch": torch.get_rng_state(),
                    "numpy": np.random.get_state(), "python": random.getstate()},
            "config": self.cfg.to_dict(),
            "meta": {"dataset": str(self.dataset_path), "names": self.views.names,
                     "box_lo": self.views.box_lo.tolist(), "box_hi": self.views.box_hi.tolist(),
                     "box_source": self.views.box_source, "lr_scale": self.lr_scale, "retries": self.retries,
                     "elapsed_s": self.elapsed, "overhead_s": self.overhead, "eval_cursor": self.eval_cursor,
                     "eval_s_per_px": self._eval_s_per_px, "frames": [f.fid for f in self.views.dataset.frames],
                     "params": self.model.param_count()},
            # the occupancy grid of the finished model (`livescene.occupancy`): fast renders of this checkpoint
            **({"occupancy": self.occupancy.state()} if getattr(self, "occupancy", None) is not None else {}),
        }

    def _restore(self, ckpt: dict[str, Any]) -> None:
        self.model.load_state_dict(ckpt["model"])
        self.opt.load_state_dict(ckpt["optimizer"])
        self.step = int(ckpt["step"])
        rng = ckpt["rng"]
        self.gen.set_state(rng["gen"])
        self.gen_dev.set_state(rng["gen_dev"])
        torch.set_rng_state(rng["torch"])
        np.random.set_state(rng["numpy"])
        random.setstate(rng["python"])
        meta = ckpt["meta"]
        self.lr_scale = float(meta.get("lr_scale", 1.0))
        self.retries = int(meta.get("retries", 0))
        self.elapsed = float(meta.get("elapsed_s", 0.0))
        self.eval_cursor = int(meta.get("eval_cursor", 0))

    def save_checkpoint(self) -> Path:
        t0 = time.perf_counter()
        buf = io.BytesIO()
        torch.save(self._state(), buf)
        data = buf.getvalue()
        path = self.ckpt_dir / f"step_{self.step:07d}.pt"
        try:
            with writing(path):
                atomic.write_bytes(path, data)
            with writing(self.run_dir / "latest.pt"):
                atomic.write_bytes(self.run_dir / "latest.pt", data)
        except OutputError as exc:
            intact = [p.name for p in checkpoint_files(self.run_dir)]
            raise OutputError(f"{exc}; " + (f"resume later with --resume (from {intact[0]})" if intact else
                                            "no checkpoint was written")) from exc
        old = sorted(self.ckpt_dir.glob("step_*.pt"))[: -max(self.cfg.keep_checkpoints, 1)]
        for p in old:
            p.unlink(missing_ok=True)
        self._ckpt_s = time.perf_counter() - t0
        return path

    def _rollback(self, reason: str) -> None:
        self.retries += 1
        if self.retries > self.cfg.max_divergence_retries:
            raise DivergenceError(f"training diverged at step {self.step} ({reason}) {self.retries - 1} times after "
                                  f"rolling back; lower --set lr=... (now {self.cfg.lr * self.lr_scale:g}) or check the data")
        ckpt, _ = load_checkpoint(self.run_dir, None, RESUME_KEYS)
        retries, scale = self.retries, self.lr_scale * 0.5
        self._restore(ckpt)
        self.retries, self.lr_scale = retries, scale
        self._log({"type": "rollback", "step": self.step, "reason": reason, "lr_scale": self.lr_scale})
        print(f"livescene train: {reason} -> rolled back to step {self.step} with lr x{self.lr_scale:g}", file=sys.stderr)

    def _log(self, record: dict[str, Any]) -> None:
        path = self.run_dir / "metrics.jsonl"
        with writing(path):
            self.run_dir.mkdir(parents=True, exist_ok=True)
            with open(path, "a", encoding="utf-8") as fh:
                fh.write(json.dumps(record) + "\n")

    def _truncate_metrics(self) -> dict[str, Any]:
        """Drop the metrics.jsonl records a resume will write again (past the step it resumes from; the final
        evaluation and rollbacks at that step; half-written lines); returns the last train record kept."""
        path = self.run_dir / "metrics.jsonl"
        if not path.exists():
            return {}
        kept, last = [], {}
        for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
            try:
                rec = json.loads(line)
                step = int(rec["step"])
            except (ValueError, TypeError, KeyError):
                continue
            if step > self.step or (step == self.step and (rec.get("final") or rec.get("type") == "rollback")):
                continue
            kept.append(line)
            if rec.get("type") == "train":
                last = rec
        with writing(path):
            atomic.write_text(path, "".join(x + "\n" for x in kept))
        return last

    # -- one step ------------------------------------------------------------------------------------------------
    def losses(self, batch: dict[str, torch.Tensor]):
        cfg, w = self.cfg, self.cfg.loss
        model = self.model
        m = model.n_objects
        values = model.frame_values(batch["t"])
        out = render_rays(model, batch["origins"], batch["dirs"], values, self.box, cfg.sampler,
                          step=self.step, gen=self.gen_dev, with_logits=m > 0 and self.data.has_masks)
        terms: dict[str, torch.Tensor] = {"rgb": ((out.rgb - batch["rgb"]) ** 2).mean()}
        if w.interlevel and out.proposals:
            terms["interlevel"] = L.interlevel_loss(out.edges, out.weights, out.proposals)
        if w.distortion:
            terms["distortion"] = L.distortion_loss(out.edges, out.weights, out.near, out.far)
        if out.logits is not None:
            target = batch["mask"].clone()
            target[target == m] = model.cfg.max_objects  # background is the last slot
            if w.focal:
                terms["focal"] = L.focal_loss(out.logits, target, w.focal_alpha, w.focal_gamma)
            if w.repulsion:
                terms["repulsion"] = L.repulsion_loss(out.logits, target, w.repulsion_k, self.gen)
        if m and w.var:
            terms["var"] = L.var_loss(values[:, :m], batch["labels"], batch["given"])
        if w.var_smooth:
            terms["var_smooth"] = L.time_smoothness(model.variable.line)
        if cfg.reg_every > 1 and self.step % cfg.reg_every:
            return terms, out
        grids = [p.grid for p in model.proposals]
        if w.k_smooth:
            terms["k_smooth"] = L.k_smoothness(model.field.grid)
        if w.k_smooth_proposal:
            terms["k_smooth_proposal"] = sum(L.k_smoothness(g) for g in grids)
        if w.l1_k:
            terms["l1_k"] = L.l1_kplanes(model.field.grid)
        if w.l1_k_proposal:
            terms["l1_k_proposal"] = sum(L.l1_kplanes(g) for g in grids)
        if w.plane_tv:
            terms["plane_tv"] = L.plane_tv(model.field.grid)
        if w.plane_tv_proposal:
            terms["plane_tv_proposal"] = sum(L.plane_tv(g) for g in grids)
        if w.plane_tv_prob:
            terms["plane_tv_prob"] = L.plane_tv(model.prob.grid)
        return terms, out

    def train_step(self) -> dict[str, float]:
        cfg = self.cfg
        batch = self.data.sample(cfg.batch_rays, self.gen, cfg.keyframe_fraction)
        terms, _ = self.losses(batch)
        weights = vars(cfg.loss)
        total = sum(weights[k] * (cfg.reg_every if k in REGULARISERS else 1) * v for k, v in terms.items())
        time_frac = self.elapsed / self.train_budget() if self.max_minutes else 0.0
        lr = cfg.lr * self.lr_scale * lr_factor(self.step, cfg, time_frac)
        for g in self.opt.param_groups:
            g["lr"] = lr
        self.opt.zero_grad(set_to_none=True)
        if not torch.isfinite(total):
            return {"loss": float("nan")}
        total.backward()
        self.opt.step()
        self.step += 1
        out = {k: float(v.detach()) for k, v in terms.items()}
        out["loss"] = float(total.detach())
        out["lr"] = lr
        return out

    # -- time budget -----------------------------------------------------------------------------------------------
    def _final_eval_cost(self, side: int) -> float:
        """Seconds the final evaluation takes at long side `side`, at the measured render speed."""
        frames = self.final_frames
        small = within_side(self.views.intrinsics[frames[0]], side)
        return len(frames) * small.w * small.h * self._eval_s_per_px

    def final_side(self) -> int:
        """`final_eval_max_side`, lowered (not below `eval_max_side`) where it would spend more than a tenth of a
        time limit: a 1.5-minute run on 1600x900 frames spent half its budget evaluating at 640 px."""
        side = self.cfg.final_eval_max_side
        cost, allowed = self._final_eval_cost(side), 0.1 * self.max_minutes * 60
        if self.max_minutes and cost > allowed:
            side = max(self.cfg.eval_max_side, int(side * math.sqrt(allowed / cost)))
        return side

    def end_reserve(self) -> float:
        """Seconds the run still needs after its last step: the final evaluation and the final checkpoint."""
        return self._final_eval_cost(self.final_side()) + self._ckpt_s + self._grid_s

    def train_budget(self) -> float:
        """Training seconds `max_minutes` leaves once loading, evaluations, checkpoints and the end are paid for."""
        return max(self.max_minutes * 60 - self.overhead - self.end_reserve(), 1e-3)

    # -- evaluation ------------------------------------------------------------------------------------------------
    def heldout_psnr(self, i: int, max_side: int) -> float:
        """PSNR of frame i rendered with its long side at most `max_side` (the ground truth area-resized to match)."""
        from .render import render_view

        run = Run(self.run_dir, self.model, self.views, self.cfg, self.device, self.step,
                  occupancy=getattr(self, "occupancy", None))
        small = within_side(self.views.intrinsics[i], max_side)
        self.model.eval()
        out = render_view(run, self.views.c2w_gl[i], small, None, time=float(self.views.times[i]))
        self.model.train()
        import cv2

        gt = self.data.rgb[i].numpy()
        gt = cv2.resize(gt, (small.w, small.h), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
        return L.psnr(np.mean((out["rgb"] - gt) ** 2))

    def eval_pool(self) -> list[int]:
        """Frames the evaluations render: the held-out ones (the training frames when nothing is held out)."""
        return list(self.views.held_out or self.views.train)

    @functools.cached_property
    def final_frames(self) -> list[int]:
        """The final evaluation's `final_eval_frames` frames, spread through the video (fixed for the run; the time
        budget asks for them every step)."""
        from .evaluate import pick_frames

        return pick_frames(self.eval_pool(), self.cfg.final_eval_frames)

    @property
    def quick_frame(self) -> int:
        """The one held-out frame (mid-video) every evaluation during training renders: the same frame each time, so
        the printed PSNRs show the fit improving, not one frame being easier than another."""
        pool = self.eval_pool()
        return int(pool[len(pool) // 2])

    def quick_eval(self) -> dict[str, float]:
        """PSNR of the held-out `quick_frame` at `eval_max_side`: cheap enough to run while training."""
        i = self.quick_frame
        self.eval_cursor += 1  # evaluations so far (kept in checkpoints)
        return {"psnr": self._timed_psnr(i), "frame": i}

    def _timed_psnr(self, i: int) -> float:
        """heldout_psnr at `eval_max_side`, recording the render speed that `end_reserve` plans with."""
        t0 = time.perf_counter()
        value = self.heldout_psnr(i, self.cfg.eval_max_side)
        small = within_side(self.views.intrinsics[i], self.cfg.eval_max_side)
        self._eval_s_per_px = (time.perf_counter() - t0) / (small.w * small.h)
        return value

    def final_eval(self) -> dict[str, Any]:
        """Mean PSNR over `final_eval_frames` held-out frames spread through the video, near full size.

        One small frame is too noisy to judge the fit on (the stress suite saw 25.0 dB there for a run whose full
        evaluation gave 23.9), so the low-fit warning reads this instead."""
        frames = self.final_frames
        side = self.final_side()
        scores = [self.heldout_psnr(i, side) for i in frames]
        return {"psnr": float(np.mean(scores)), "frames": [int(i) for i in frames], "max_side": side,
                "frame_psnr": [round(float(v), 3) for v in scores], "held_out": bool(self.views.held_out)}

    # -- loop ----------------------------------------------------------------------------------------------------
    def fit(self) -> dict[str, Any]:
        from tqdm import tqdm

        cfg = self.cfg
        ds = self.views.dataset
        with writing(self.run_dir / "config.yaml"):
            self.run_dir.mkdir(parents=True, exist_ok=True)
            atomic.write_yaml(self.run_dir / "config.yaml", {"dataset": str(self.dataset_path), **cfg.to_dict()})
            atomic.write_yaml(self.run_dir / "objects.yaml", {"objects": [
                {"id": i, "name": n, "description": ds.prompts.get(n, "")} for i, n in enumerate(ds.object_names)]})
        last = self._truncate_metrics()  # a resume trains the steps past its checkpoint again: no duplicates
        params = self.model.param_count()
        m = cfg.model
        print(f"livescene train: {len(self.views.train)} train / {len(self.views.held_out)} held-out frames at "
              f"{self.data.w}x{self.data.h}, {ds.n_objects} objects, device {describe(self.device)}\n"
              f"  model: {params:,} parameters (planes {m.resolution}x{m.scales} k={m.k_resolution} "
              f"f={m.features}; proposals {m.proposal_resolutions}; variable {m.var_resolution} nodes; box from "
              f"{self.views.box_source}; samples from {cfg.sampler.near:g} in front of a camera)", flush=True)
        if self.model.motions is not None:
            rigid = [self.views.names[o] for o in self.model.motions.rigid(ds.n_objects)]
            print(f"  rigid parts (articulation.json): {', '.join(rigid)}; read at k = {m.part_k}", flush=True)
        if self.step == 0:
            self.save_checkpoint()
        if self.max_minutes and not self._grid_s:
            from .occupancy import build_cost

            self._grid_s = build_cost(self.model, self.box)
        if self.max_minutes and not self._eval_s_per_px:  # a time limit needs the final evaluation's cost up front
            first = self.quick_frame
            self._log({"type": "eval", "step": self.step, "elapsed_s": round(self.elapsed, 2),
                       "psnr": self._timed_psnr(first), "frame": int(first)})
        if self._t_init is not None:  # loading, setting up and that first render, once per process
            self.overhead += time.perf_counter() - self._t_init
            self._t_init = None
        t_start = time.perf_counter() - self.elapsed
        overhead_start = self.overhead  # evaluations and checkpoints in the loop add to it; elapsed leaves them out
        acc: dict[str, list[float]] = {}
        bar = tqdm(total=cfg.steps, initial=self.step, desc="train", disable=not self.show_progress,
                   dynamic_ncols=True, unit="step")
        stop_reason = "steps"
        self.model.train()
        trial = ThreadTrial(os.cpu_count() or 1) if getattr(self, "measure_threads", False) else None
        while self.step < cfg.steps:
            t_step = time.perf_counter()
            if trial is not None:
                trial.before_step()
            info = self.train_step()
            if trial is not None:
                trial.after_step(time.perf_counter() - t_step)
                if trial.done:
                    bar.write(f"livescene train: {trial.summary()}")
                    self.threads_measured = {"kept": trial.chosen, "seconds_per_step": trial.medians}
                    trial = None
            if not math.isfinite(info["loss"]):
                self._rollback("loss is NaN/inf")
                continue
            for k, v in info.items():
                acc.setdefault(k, []).append(v)
            self.elapsed = time.perf_counter() - t_start - (self.overhead - overhead_start)
            bar.update(1)
            if self.step % cfg.log_every == 0 or self.step == cfg.steps:
                rec = {k: float(np.mean(v)) for k, v in acc.items()}
                rec["psnr"] = L.psnr(rec.get("rgb", 1.0))
                acc = {}
                last = {"type": "train", "step": self.step, "elapsed_s": round(self.elapsed, 2), **rec}
                self._log(last)
                bar.set_postfix(loss=f"{rec['loss']:.4f}", psnr=f"{rec['psnr']:.2f}")
            if cfg.eval_every and self.step % cfg.eval_every == 0 and self.step < cfg.steps:
                t0 = time.perf_counter()
                ev = self.quick_eval()
                self._log({"type": "eval", "step": self.step, "elapsed_s": round(self.elapsed, 2), **ev})
                which = "held-out" if self.views.held_out else "training-frame (none held out)"
                bar.write(f"step {self.step}: {which} PSNR {ev['psnr']:.2f} dB (frame position {ev['frame']}, the "
                          f"same every time)")
                self.overhead += time.perf_counter() - t0
            if cfg.ckpt_every and self.step % cfg.ckpt_every == 0:
                t0 = time.perf_counter()
                self.save_checkpoint()
                self.overhead += time.perf_counter() - t0
            if self.max_minutes and self.elapsed >= self.train_budget():
                stop_reason = "max-minutes"
                break
        bar.close()
        t0 = time.perf_counter()
        from .occupancy import build_grid  # once, for the final model: saved with its checkpoint, renders skip air

        self.occupancy = build_grid(self.model, self.box, self.step)
        self.overhead += time.perf_counter() - t0
        self.save_checkpoint()
        final = self.final_eval()
        self._log({"type": "eval", "step": self.step, "elapsed_s": round(self.elapsed, 2), "final": True, **final})
        held = final["held_out"]
        return {"steps": self.step, "elapsed_s": round(self.elapsed, 2), "params": params, "stop": stop_reason,
                "train_psnr": last.get("psnr"), "heldout_psnr": final["psnr"] if held else None,
                "heldout_eval_frames": len(final["frames"]) if held else 0, "heldout_eval_side": final["max_side"],
                # with no frame held out (a few frames, or holdout_every <= 1) the end-of-run PSNR is on
                # training frames: named as such, never as "held-out"
                "eval_psnr": final["psnr"], "eval_frames": len(final["frames"]),
                "eval_on": "held-out" if held else "training", "rollbacks": self.retries,
                **({"threads": self.threads_measured} if getattr(self, "threads_measured", None) else {})}


# ----------------------------------------------------------------------------------------------------------------
# CLI
# ----------------------------------------------------------------------------------------------------------------
def add_arguments(p) -> None:
    p.add_argument("dataset", type=Path, help="LiveScene dataset folder (ours, InterReal or OmniSim layout)")
    p.add_argument("--out", type=Path, required=True, help="run folder (checkpoints, metrics, config)")
    p.add_argument("--preset", default="auto", help=f"auto (gpu on CUDA, else cpu), one of {preset_names()} or a YAML file")
    p.add_argument("--steps", type=int, default=0, help="training steps (default: the preset's)")
    p.add_argument("--max-minutes", type=float, default=0.0,
                   help="time limit for the whole command: training stops early enough that loading, evaluations, "
                        "checkpoints and the final evaluation fit in it")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda")
    p.add_argument("--resume", action="store_true", help="continue the run in --out exactly where it stopped")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a setting, e.g. --set model.features=32 --set loss.var=0.5 (repeatable)")
    p.add_argument("--threads", type=int, default=0,
                   help="CPU threads (0 = auto: the first steps are timed at all cores and at 1 thread, and "
                        "the faster is kept; a busy machine can make more threads slower)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (logs still go to metrics.jsonl)")
    p.epilog = ("examples:\n"
                "  livescene train out/ds --out out/run                       # cpu preset on CPU, gpu preset on CUDA\n"
                "  livescene train out/ds --out out/run --preset cpu --max-minutes 15\n"
                "  livescene train out/ds --out out/run --resume              # after a kill, continues exactly\n"
                "  livescene train out/ds --out out/run --set model.reject_threshold=0 --steps 2000\n"
                "  livescene train out/ds --out out/run --set model.motion=none   # the paper's k-axis alone, even\n"
                "                                                   # when out/ds/articulation.json has part motions\n"
                f"{JEMALLOC_ENV}=1 re-runs it under jemalloc (slower on the machine it was measured on; see livescene.device)")


def train(dataset: str | Path, out: str | Path, cfg: TrainConfig, device: str = "auto", resume: bool = False,
          max_minutes: float = 0.0, show_progress: bool = True, measure_threads: bool = False) -> dict[str, Any]:
    """Train (or resume) a run; returns a summary. Writes RUN/reports/train.json. measure_threads: on a CPU, time
    the first steps at all cores and at 1 thread and keep the faster (`device.ThreadTrial`; `--threads 0`).

    A resumed run that already finished (its steps done, its report "ok") is left untouched: the summary is its
    report's, with "finished": True. A run folder this call created is removed again when the call fails before
    it holds a checkpoint (refused input, disk full, permissions): no half run is left behind."""
    out = Path(out)
    created = not out.exists()
    try:
        with run_lock(out):
            remove_stale_temporaries(out)
            trainer = Trainer(dataset, out, cfg, device=device, resume=resume, max_minutes=max_minutes,
                              show_progress=show_progress)
            done = finished_summary(trainer) if resume else None
            if done is not None:
                return done
            trainer.measure_threads = measure_threads and trainer.device.type == "cpu"
            return _train(trainer, out)
    except Exception:
        if created and out.is_dir() and not checkpoint_files(out):
            shutil.rmtree(out, ignore_errors=True)  # refused, or nothing resumable written: leave no half run behind
        raise


def _train(trainer: "Trainer", out: Path) -> dict[str, Any]:
    with writing(out / "reports" / "train.json"):
        rep = StageReport(out, "train", inputs={"dataset": str(trainer.dataset_path)}, settings=trainer.cfg.to_dict())
        rep.__enter__()
    try:
        for message, cause in label_warnings(trainer.views):
            rep.warn(message, cause=cause)
            # now, not after training: a shortage found after minutes of training costs those minutes
            print(f"livescene train: warning: {message}", file=sys.stderr)
        early = len(rep.data["warnings"])
        summary = trainer.fit()
        rep.figures.update(summary)
        for message, cause in state_warnings(*learned_states(trainer)):
            rep.warn(message, cause=cause)
        psnr, where = summary.get("eval_psnr"), ("held-out" if summary.get("eval_on") == "held-out"
                                                  else "training-frame (no frame is held out)")
        if psnr is not None and psnr < LOW_FIT_PSNR:
            rep.warn(f"{where} PSNR {psnr:.1f} dB after {summary['steps']} steps: the model "
                     f"does not fit the views yet (train longer, or check poses and masks)", cause="low-fit")
    except BaseException as exc:
        with contextlib.suppress(OSError):  # a full disk must not hide the error that stopped the run
            rep.__exit__(type(exc), exc, exc.__traceback__)
        raise
    with writing(out / "reports" / "train.json"):
        rep.__exit__(None, None, None)
    for w in rep.data["warnings"][early:]:
        print(f"livescene train: warning: {w['message']}", file=sys.stderr)
    return summary


def finished_summary(trainer: "Trainer") -> dict[str, Any] | None:
    """The report's figures, with "finished": True, when the resumed run already trained all its steps and
    reported them ("ok" at this step); None when there is training (or the final evaluation) left to do."""
    if trainer.step < trainer.cfg.steps:
        return None
    rep = read_report(trainer.run_dir, "train")
    if not rep or rep.get("status") != "ok" or (rep.get("figures") or {}).get("steps") != trainer.step:
        return None
    return {**rep["figures"], "finished": True}


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


# below this, the renders are not to be trusted (held-out PSNR of runs that are still far from converged); the
# label figures are interreal.dataset.MIN_LABELS / MIN_LABEL_FRACTION
LOW_FIT_PSNR = 24.0  # renders below this are visibly blurry (the stress suite's usable threshold)


MAX_STATE_ERROR = 0.1


def learned_states(trainer) -> tuple[np.ndarray, Any]:
    """(N, M) states the per-frame variable gives every frame after training, and the views."""
    views = trainer.views
    with torch.no_grad():
        values = trainer.model.frame_values(torch.as_tensor(views.times, device=trainer.device))
    return values[:, : len(views.names)].cpu().numpy(), views


def state_warnings(values: np.ndarray, views) -> list[tuple[str, str]]:
    """Warn when the learned states miss the labels: on training frames (not fitted) or on held-out labelled frames
    (never trained on, so their error estimates the error on every unlabelled frame)."""
    labels, given_all = views.dataset.label_matrix()
    out = []
    for k, name in enumerate(views.names):
        for which, frames in (("labelled training", views.train), ("held-out labelled", views.held_out)):
            idx = [i for i in frames if given_all[i, k]]
            if not idx:
                continue
            err = float(np.abs(values[idx, k] - labels[idx, k]).mean())
            if err > MAX_STATE_ERROR:
                out.append((f"'{name}': learned states miss the {which} frames by {err:.2f} on average: its states "
                            f"are unreliable (train longer, or add labels)", "states-unreliable"))
    return out


def label_warnings(views) -> list[tuple[str, str]]:
    """(message, cause) for each object whose state labels on the training frames are too sparse for Lvar to pin
    its states down (interreal.dataset.label_shortage: the figures `interreal validate` warns with)."""
    from interreal.dataset import label_shortage

    counts = {name: int(views.given[views.train, k].sum()) for k, name in enumerate(views.names)}
    return [(m.replace(" frames (", " training frames (", 1), "few-labels")
            for _, m in label_shortage(counts, len(views.train))]


def main(args) -> int:
    reexec_with_jemalloc(("livescene", "train"))
    configure_threads(args.threads)
    device = select_device(args.device)
    preset = args.preset if args.preset != "auto" else ("gpu" if device.type == "cuda" else "cpu")
    cfg = load_preset(preset)
    cfg = apply_overrides(cfg, args.overrides)
    if args.steps:
        cfg.steps = args.steps
    if args.seed is not None:
        cfg.seed = args.seed
    if args.resume and not args.steps:
        cfg.steps = 0
    if args.steps < 0:
        raise LiveSceneError(f"--steps {args.steps}: give a positive number of steps")
    if not args.resume:
        check_config(cfg)  # before any data is read
    elif args.overrides:
        print("livescene train: warning: --set is ignored with --resume (the run continues with its own settings)",
              file=sys.stderr)
    if args.max_minutes < 0 or not math.isfinite(args.max_minutes):
        raise LiveSceneError(f"--max-minutes {args.max_minutes}: give a positive number of minutes (0 = no limit)")
    summary = train(args.dataset, args.out, cfg, device=str(device), resume=args.resume,
                    max_minutes=args.max_minutes, show_progress=not args.no_progress,
                    measure_threads=args.threads <= 0)
    if summary.get("finished"):
        print(f"livescene train: {args.out} already finished ({summary['steps']} steps): nothing to do, its outputs "
              f"are unchanged (pass --steps N above {summary['steps']} with --resume to train further)")
        return 0
    print(f"livescene train: {summary['steps']} steps in {summary['elapsed_s'] / 60:.1f} min "
          f"({summary['stop']}); {psnr_line(summary)} -> {args.out}")
    return 0


def psnr_line(summary: dict[str, Any]) -> str:
    """'held-out PSNR (3 frames) 27.10 dB', or with nothing held out what the figure really is."""
    n = int(summary.get("eval_frames", summary.get("heldout_eval_frames", 0)))
    frames = f"{n} frame{'s' if n != 1 else ''}"
    psnr = summary.get("eval_psnr", summary.get("heldout_psnr"))
    if psnr is None:
        return "no PSNR"
    if summary.get("eval_on", "held-out") == "held-out":
        return f"held-out PSNR ({frames}) {psnr:.2f} dB"
    return f"no frame is held out (too few frames, or holdout_every <= 1): PSNR on {frames} it trained on {psnr:.2f} dB"
