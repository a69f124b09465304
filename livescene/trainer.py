"""Training: fit the LiveScene model to a dataset and write a run (`livescene train` is `commands/train.py`).

`--resume` restores weights, optimiser, step and every random generator, so a killed run continues exactly as if
it had not stopped. A NaN/inf loss rolls back to the last good checkpoint with a halved learning rate; after
`max_divergence_retries` it stops with DivergenceError. The run folder and its checkpoints are `livescene.run`'s.

Inputs are checked before the optimiser can be blamed: the dataset must pass `interreal validate` (`load_views`),
the settings their types and ranges (`check_config`). A resume drops the metrics.jsonl records past the step it
resumes from (the steps are trained again), and leaves a finished run untouched.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import math
import os
import random
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
import torch
from tqdm import tqdm

from interreal import atomic
from interreal.dataset import Intrinsics
from interreal.report import StageReport, Terminated, read_report

from . import losses as L
from .articulation import fit_hulls
from .config import TrainConfig, check_config, resolve
from .data import RayData, Views, load_views, measured_counts, scored_mse, sparse_points, transient_at
from .device import ThreadTrial, describe, select_device
from .errors import CheckpointError, DivergenceError, LiveSceneError, writing
from .evaluate import pick_frames
from .field import LiveSceneModel, normalise
from .fitcheck import LOW_FIT_PSNR, label_warnings, learned_states, state_warnings
from .occupancy import build_cost, build_grid
from .render import render_view
from .run import (RESUME_KEYS, Run, check_run_dataset, checkpoint_config, checkpoint_files, load_checkpoint,
                  load_run, remove_stale_temporaries, run_lock, write_checkpoint)
from .sampler import render_rays
from .signals import stop_signals

__all__ = ["Run", "Trainer", "build_model", "load_run", "train"]  # Run, load_run: `livescene.run`'s, named here too
WARM_SIDE = 32  # long side of the untimed render before a time limit's first measured one

# ----------------------------------------------------------------------------------------------------------------
# The model a run trains
# ----------------------------------------------------------------------------------------------------------------
def build_model(cfg: TrainConfig, views: Views) -> tuple[TrainConfig, LiveSceneModel]:
    """Resolve the scene-driven settings (`config.resolve`) and build the model (its parameter count ignores the
    object count)."""
    cfg = resolve(cfg, views)
    motions = part_motions(cfg.model.motion, views)
    cfg.model.motion = "rigid" if motions else "none"
    model = LiveSceneModel(cfg.model, views.n_objects)
    points = sparse_points(views.dataset) if cfg.model.warp == "points" else None
    if points is not None:
        box = (torch.as_tensor(views.box_lo), torch.as_tensor(views.box_hi))
        model.warp.fit(normalise(torch.as_tensor(points, dtype=torch.float32), box), cfg.model.warp_uniform)
    if motions:
        model.motions.load(motions)
    if model.appearance is not None:
        model.appearance.set_trained(views.train)
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
                 resume: bool = False, max_minutes: float = 0.0, show_progress: bool = True,
                 clock: Callable[[], float] = time.perf_counter):
        # every duration the time budget plans with is read from `clock` (tests inject a fake one: a busy machine
        # must not change what they check)
        self.clock = clock
        self._t_init = clock()
        self.run_dir = Path(run_dir)
        self.device = select_device(device)
        self.max_minutes = max_minutes
        self.show_progress = show_progress
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
        self._saved_step = -1  # the step of the newest checkpoint on disk (-1: none yet)
        self.stop_signal: str | None = None  # set by `stop_signals` while training: stop after the current step
        self.in_loop = False  # between the first and the last step (where a stop can wait for the step to end)
        self.resumed_from: tuple[int, str | None] | None = None  # (step, the run's report status before)
        if resume_ckpt is not None:
            self._restore(resume_ckpt)
            self._saved_step = self.step
            self.resumed_from = (self.step, (read_report(self.run_dir, "train") or {}).get("status"))
            self.overhead = float(resume_ckpt["meta"].get("overhead_s", 0.0))
            self._eval_s_per_px = float(resume_ckpt["meta"].get("eval_s_per_px", 0.0))

    # -- checkpoints ---------------------------------------------------------------------------------------------
    def _state(self) -> dict[str, Any]:
        return {
            "step": self.step,
            "model": self.model.state_dict(),
            "optimizer": self.opt.state_dict(),
            "rng": {"gen": self.gen.get_state(), "gen_dev": self.gen_dev.get_state(), "torch": torch.get_rng_state(),
                    "numpy": np.random.get_state(), "python": random.getstate(),
                    "ray_errors": self.data.errors.err.clone()},  # where the next batches go (`data.ErrorMap`)
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
        if "ray_errors" in rng and rng["ray_errors"].shape == self.data.errors.err.shape:
            self.data.errors.err.copy_(rng["ray_errors"])  # checkpoints from before the map: it starts again
        meta = ckpt["meta"]
        self.lr_scale = float(meta.get("lr_scale", 1.0))
        self.retries = int(meta.get("retries", 0))
        self.elapsed = float(meta.get("elapsed_s", 0.0))
        self.eval_cursor = int(meta.get("eval_cursor", 0))

    def save_checkpoint(self) -> Path:
        t0 = self.clock()
        path = write_checkpoint(self.run_dir, self.step, self._state(), self.cfg.keep_checkpoints)
        self._ckpt_s = self.clock() - t0
        self._saved_step = self.step
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
        cfg, model = self.cfg, self.model
        m = model.n_objects
        values = model.frame_values(batch["t"])
        out = render_rays(model, batch["origins"], batch["dirs"], values, self.box, cfg.sampler,
                          step=self.step, gen=self.gen_dev, with_logits=m > 0 and self.data.has_masks)
        if model.appearance is not None:  # each frame's exposure and white balance, on its final colours only
            out = dataclasses.replace(out, rgb=model.appearance(out.rgb, batch["frame"]))
        regularise = not (cfg.reg_every > 1 and self.step % cfg.reg_every)
        terms = L.loss_terms(L.LossInputs(model, out, batch, values, self.gen), cfg.loss, regularise)
        return terms, out

    def train_step(self) -> dict[str, float]:
        cfg = self.cfg
        batch = self.data.sample(cfg.batch_rays, self.gen, cfg.keyframe_fraction, cfg.error_rays)
        terms, rendered = self.losses(batch)
        if cfg.error_rays:
            self.data.record(batch, ((rendered.rgb.detach() - batch["rgb"]) ** 2).mean(-1))
        total = L.total_loss(terms, cfg.loss, cfg.reg_every)
        time_frac = self.elapsed / self.train_budget() if self.max_minutes else 0.0
        lr = cfg.lr * self.lr_scale * lr_factor(self.step, cfg, time_frac)
        for g in self.opt.param_groups:
            g["lr"] = lr * (cfg.model.appearance_lr / cfg.lr if g.get("name") == "appearance" else 1.0)
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
        run = Run(self.run_dir, self.model, self.views, self.cfg, self.device, self.step,
                  occupancy=getattr(self, "occupancy", None))
        small = within_side(self.views.intrinsics[i], max_side)
        self.model.eval()
        out = render_view(run, self.views.c2w_gl[i], small, None, time=float(self.views.times[i]))
        self.model.train()
        gt = self.data.rgb[i].numpy()
        gt = cv2.resize(gt, (small.w, small.h), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
        return L.psnr(scored_mse(out["rgb"], gt, transient_at(self.views, i, small.w, small.h)))  # no hand scored

    def eval_pool(self) -> list[int]:
        """Frames the evaluations render: the held-out ones (the training frames when nothing is held out)."""
        return list(self.views.held_out or self.views.train)

    @functools.cached_property
    def final_frames(self) -> list[int]:
        """The final evaluation's `final_eval_frames` frames, spread through the video (fixed for the run; the time
        budget asks for them every step)."""
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
        t0 = self.clock()
        value = self.heldout_psnr(i, self.cfg.eval_max_side)
        small = within_side(self.views.intrinsics[i], self.cfg.eval_max_side)
        self._eval_s_per_px = (self.clock() - t0) / (small.w * small.h)
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

    def _loop(self, bar, trial, acc: dict[str, list[float]], last: dict[str, Any], t_start: float,
              overhead_start: float) -> dict[str, Any]:
        """The training steps until `cfg.steps` or the time limit; returns the last train log record (with
        "_stop": "max-minutes" when the clock stopped it)."""
        self.in_loop = True
        try:
            return self._steps(bar, trial, acc, last, t_start, overhead_start)
        finally:
            self.in_loop = False

    def _steps(self, bar, trial, acc: dict[str, list[float]], last: dict[str, Any], t_start: float,
               overhead_start: float) -> dict[str, Any]:
        cfg = self.cfg
        while self.step < cfg.steps:
            if self.stop_signal:  # asked to stop: here, between two steps, the model and optimizer agree
                raise Terminated("terminated (SIGTERM)") if self.stop_signal == "SIGTERM" else KeyboardInterrupt()
            t_step = self.clock()
            if trial is not None:
                trial.before_step()
            info = self.train_step()
            if trial is not None:
                trial.after_step(self.clock() - t_step)
                if trial.done:
                    bar.write(f"livescene train: {trial.summary()}")
                    self.threads_measured = {"kept": trial.chosen, "seconds_per_step": trial.medians}
                    trial = None
            if not math.isfinite(info["loss"]):
                self._rollback("loss is NaN/inf")
                continue
            for k, v in info.items():
                acc.setdefault(k, []).append(v)
            self.elapsed = self.clock() - t_start - (self.overhead - overhead_start)
            bar.update(1)
            if self.step % cfg.log_every == 0 or self.step == cfg.steps:
                rec = {k: float(np.mean(v)) for k, v in acc.items()}
                rec["psnr"] = L.psnr(rec.get("rgb", 1.0))
                acc = {}
                last = {"type": "train", "step": self.step, "elapsed_s": round(self.elapsed, 2), **rec}
                self._log(last)
                bar.set_postfix(loss=f"{rec['loss']:.4f}", psnr=f"{rec['psnr']:.2f}")
            if cfg.eval_every and self.step % cfg.eval_every == 0 and self.step < cfg.steps:
                t0 = self.clock()
                ev = self.quick_eval()
                self._log({"type": "eval", "step": self.step, "elapsed_s": round(self.elapsed, 2), **ev})
                which = "held-out" if self.views.held_out else "training-frame (none held out)"
                bar.write(f"step {self.step}: {which} PSNR {ev['psnr']:.2f} dB (frame position {ev['frame']}, the "
                          f"same every time)")
                self.overhead += self.clock() - t0
            if cfg.ckpt_every and self.step % cfg.ckpt_every == 0:
                t0 = self.clock()
                self.save_checkpoint()
                self.overhead += self.clock() - t0
            if self.max_minutes and self.elapsed >= self.train_budget():
                last["_stop"] = "max-minutes"
                break
        return last

    def _interrupted(self, exc: KeyboardInterrupt) -> KeyboardInterrupt:
        """Save the steps trained since the last checkpoint (an interrupted save leaves the one before: writes are
        atomic) and say where the run stands, for the report and the command's one line."""
        try:
            if self.step != self._saved_step:
                self.save_checkpoint()
            saved = f"checkpoint at step {self.step} saved"
        except (OSError, KeyboardInterrupt) as again:  # a second Ctrl-C, or a full disk: the last checkpoint stays
            saved = f"not saved ({type(again).__name__}); the last checkpoint, step {self._saved_step}, stays"
        return type(exc)(f"{str(exc) or 'interrupted (Ctrl-C)'} at step {self.step} of {self.cfg.steps}: {saved}; "
                         f"continue with `livescene train DS --out {self.run_dir} --resume`")

    # -- loop ----------------------------------------------------------------------------------------------------
    def fit(self) -> dict[str, Any]:
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
              f"{self.views.box_source}; samples from {cfg.sampler.near:g} in front of a camera"
              + (f"; per-frame appearance {m.appearance}" if self.model.appearance is not None else "") + ")",
              flush=True)
        if self.resumed_from is not None and self._t_init is not None:
            step, before = self.resumed_from
            print(f"  resuming from step {step} of {cfg.steps}" + {
                "interrupted": " (the run was interrupted)", "failed": " (the run had failed)",
                "running": " (the run was killed)"}.get(str(before), ""), flush=True)
        if self.model.motions is not None:
            rigid = [self.views.names[o] for o in self.model.motions.rigid(ds.n_objects)]
            print(f"  rigid parts (articulation.json): {', '.join(rigid)}; read at k = {m.part_k}", flush=True)
        measured = measured_counts(self.views) if self.cfg.measured_states else {}
        if measured:
            print("  states measured by `interreal motions` (Lvar's targets there, over the labels): "
                  + ", ".join(f"{name} {n} frames" for name, n in measured.items()), flush=True)
        if self.step == 0:
            self.save_checkpoint()
        if self.max_minutes and not self._grid_s:
            self._grid_s = build_cost(self.model, self.box, clock=self.clock)
        if self.max_minutes and not self._eval_s_per_px:  # a time limit needs the final evaluation's cost up front
            first = self.quick_frame
            self.heldout_psnr(first, WARM_SIDE)  # untimed: on CUDA the first render loads kernels for seconds
            self._log({"type": "eval", "step": self.step, "elapsed_s": round(self.elapsed, 2),
                       "psnr": self._timed_psnr(first), "frame": int(first)})
        if self._t_init is not None:  # loading, setting up and that first render, once per process
            self.overhead += self.clock() - self._t_init
            self._t_init = None
        t_start = self.clock() - self.elapsed
        overhead_start = self.overhead  # evaluations and checkpoints in the loop add to it; elapsed leaves them out
        acc: dict[str, list[float]] = {}
        bar = tqdm(total=cfg.steps, initial=self.step, desc="train", disable=not self.show_progress,
                   dynamic_ncols=True, unit="step")
        self.model.train()
        trial = ThreadTrial(os.cpu_count() or 1) if getattr(self, "measure_threads", False) else None
        try:
            last = self._loop(bar, trial, acc, last, t_start, overhead_start)
        except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM: keep every step trained so far
            raise self._interrupted(exc) from None
        finally:
            bar.close()
        stop_reason = last.pop("_stop", "steps")
        t0 = self.clock()
        # once, for the final model: saved with its checkpoint, renders skip air
        self.occupancy = build_grid(self.model, self.box, self.step, clock=self.clock)
        self.overhead += self.clock() - t0
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


def train(dataset: str | Path, out: str | Path, cfg: TrainConfig, device: str = "auto", resume: bool = False,
          max_minutes: float = 0.0, show_progress: bool = True, measure_threads: bool = False) -> dict[str, Any]:
    """Train (or resume) a run; returns a summary. Writes RUN/reports/train.json. measure_threads: on a CPU, time
    the first steps at all cores and at 1 thread and keep the faster (`device.ThreadTrial`; `--threads 0`).

    A resumed run that already finished (its steps done, its report "ok") is left untouched: the summary is its
    report's, with "finished": True. A run folder this call created is removed again when the call fails before
    it holds a checkpoint (refused input, disk full, permissions): no half run is left behind."""
    out = Path(out)
    created = not out.exists()
    holder: list[Trainer] = []
    try:
        with run_lock(out), stop_signals(holder):
            remove_stale_temporaries(out)
            trainer = Trainer(dataset, out, cfg, device=device, resume=resume, max_minutes=max_minutes,
                              show_progress=show_progress)
            holder.append(trainer)
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
