"""Data-parallel training: `livescene train --ddp`, or `livescene train` under `torchrun`.

Every process torchrun starts (a rank) holds the whole dataset and the same model. Each step:
- the global batch: every rank draws the same `world x batch_rays` rays from the sampling generator it holds in the
  same state (one seed, restored by --resume), and keeps every world-th ray. So the batch is the single-process
  batch of `world x batch_rays` rays, split; a frame's rays fall on any rank, and the per-frame variable's
  gradient is the sum of what each rank's rays give it;
- the loss of a rank is its share of the global mean: terms that are means over rays stay means (the average over
  ranks is the global mean), terms that are means over a subset whose size differs between ranks are renormalised
  by the global count - Lvar over the labelled (ray, object) pairs, the focal loss over rays with a known mask
  (without it, a rank that drew 3 labelled rays would weigh each as much as one that drew 30 weighs ten);
- gradients are averaged (one flat all-reduce before the optimiser step; NCCL on GPUs, gloo on CPUs), so every rank
  takes the same step, and the parameters stay identical without being sent;
- what is random per ray and not part of the batch (the stratified jitter of samples, the repulsion loss's pairs)
  comes from generators seeded from (seed, rank, step): independent between ranks, reproducible on resume;
- rank 0 alone writes checkpoints, metrics, reports and renders the evaluations; the others wait at a barrier after
  each checkpoint, and agree with rank 0 on NaN rollbacks and on the `--max-minutes` stop.

`batch_rays` is per rank: N ranks train with N times the batch (a larger batch at the same learning rate).
With the sample jitter and the repulsion loss off, N ranks with batch B take exactly the steps of one process with
batch N x B (tests/test_ddp.py); with them on, the same steps in distribution.
"""

from __future__ import annotations

import datetime as _dt
import os
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist

from .errors import LiveSceneError
from .run import checkpoint_files, remove_stale_temporaries, run_lock
from .trainer import Trainer, _train, finished_summary

TORCHRUN_VARS = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


@dataclass(frozen=True)
class Ranks:
    """This process's place in the group."""

    rank: int
    world: int
    local_rank: int
    device: torch.device
    backend: str

    @property
    def writer(self) -> bool:
        return self.rank == 0


def under_torchrun() -> bool:
    """Started by torchrun (or `torch.distributed.run`): this process is one rank of a group (of one, even)."""
    return all(v in os.environ for v in TORCHRUN_VARS)


def default_nproc() -> int:
    """Processes `--ddp` starts when not under torchrun: one per GPU, else 2 (CPU ranks share the cores)."""
    return torch.cuda.device_count() if torch.cuda.is_available() else 2


def init(device: str = "auto", timeout_s: float = 1800.0) -> Ranks:
    """Join the process group torchrun set up (env://): NCCL with one GPU per rank, gloo on CPUs."""
    if not dist.is_available():
        raise LiveSceneError("--ddp needs torch.distributed, which this torch build lacks")
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    cuda = torch.cuda.is_available() and device in ("auto", "cuda") or device.startswith("cuda:")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise LiveSceneError("--device cuda was asked for but torch sees no CUDA device; use --device cpu or auto")
    if cuda:
        if local_rank >= torch.cuda.device_count():
            raise LiveSceneError(f"rank {local_rank} on this node has no GPU ({torch.cuda.device_count()} visible): "
                                 f"start at most as many processes per node as GPUs (--nproc)")
        torch.cuda.set_device(local_rank)
        dev, backend = torch.device("cuda", local_rank), "nccl"
    else:
        dev, backend = torch.device("cpu"), "gloo"
    if not dist.is_initialized():
        extra = {"device_id": dev} if backend == "nccl" else {}  # NCCL binds the group to this rank's GPU
        dist.init_process_group(backend, timeout=_dt.timedelta(seconds=timeout_s), **extra)
    return Ranks(dist.get_rank(), dist.get_world_size(), local_rank, dev, backend)


def stream_seed(seed: int, rank: int, step: int, stream: int) -> int:
    """A seed per (run seed, rank, step, stream): per-rank randomness that a resume reproduces."""
    return (seed * 1_000_003 + rank * 7_919 + step * 104_729 + stream * 15_485_863) % (2 ** 63 - 1)


class ShardedRays:
    """The trainer's `RayData`, whose `sample` returns this rank's share of the global batch."""

    def __init__(self, data: Any, ranks: Ranks):
        self._data = data
        self._ranks = ranks

    def __getattr__(self, name: str) -> Any:
        return getattr(self._data, name)

    def sample(self, n: int, gen: torch.Generator, keyframe_fraction: float,
               error_share: float = 0.0) -> dict[str, torch.Tensor]:
        full = self._data.sample(n * self._ranks.world, gen, keyframe_fraction, error_share)
        return {k: v[self._ranks.rank:: self._ranks.world] for k, v in full.items()}

    def record(self, batch: dict[str, torch.Tensor], err: torch.Tensor) -> None:
        """Every rank records the whole global batch, in its order: each draws the next global batch from its own
        error map, so the maps must stay alike."""
        w = self._ranks.world
        mine = torch.cat([batch["pixel"].float(), err.detach()[:, None].float()], -1)
        parts = [mine]
        if w > 1:
            parts = [torch.empty_like(mine) for _ in range(w)]
            dist.all_gather(parts, mine)
        rows = torch.stack(parts, 1).reshape(-1, 4).cpu()  # rank r held global rays r, r + w, ...: interleaved back
        pixel = rows[:, :3].long()
        self._data.errors.record(pixel[:, 0], pixel[:, 1], pixel[:, 2], rows[:, 3])


def average_gradients(params: list[torch.Tensor], ranks: Ranks) -> None:
    """Mean of every rank's gradients, in place. A parameter no rank gave a gradient keeps none (the optimiser
    then skips it, as a single process would); one that some rank did not reach counts zero there."""
    reached = torch.tensor([p.grad is not None for p in params], dtype=torch.float32, device=ranks.device)
    dist.all_reduce(reached)
    grads = []
    for p, hit in zip(params, reached.tolist()):
        if hit > 0:
            if p.grad is None:
                p.grad = torch.zeros_like(p)
            grads.append(p.grad)
    if not grads:
        return
    flat = torch.cat([g.reshape(-1) for g in grads])
    dist.all_reduce(flat)
    flat /= ranks.world
    offset = 0
    for g in grads:
        g.copy_(flat[offset: offset + g.numel()].view_as(g))
        offset += g.numel()


def broadcast_model(model: torch.nn.Module, ranks: Ranks) -> None:
    """Rank 0's weights everywhere (the seeds already make them equal; this makes it certain)."""
    for t in model.state_dict().values():
        if isinstance(t, torch.Tensor):
            dist.broadcast(t, 0)


class DDPTrainer(Trainer):
    """`Trainer` as one rank of a data-parallel group (module docstring)."""

    def __init__(self, dataset: str | Path, run_dir: str | Path, cfg, ranks: Ranks, resume: bool = False,
                 max_minutes: float = 0.0, show_progress: bool = True):
        self.ranks = ranks
        super().__init__(dataset, run_dir, cfg, device=str(ranks.device), resume=resume, max_minutes=max_minutes,
                         show_progress=show_progress and ranks.writer)
        self.data = ShardedRays(self.data, ranks)
        broadcast_model(self.model, ranks)
        self._rank_gen = torch.Generator()
        self.normalise_counts = True  # Lvar / focal over the global count (False only to show why it is needed)
        params = [p for g in self.opt.param_groups for p in g["params"]]
        self.opt.register_step_pre_hook(lambda *_: average_gradients(params, ranks))

    # -- one step ------------------------------------------------------------------------------------------------
    def losses(self, batch: dict[str, torch.Tensor]):
        seed, r, step = self.cfg.seed, self.ranks.rank, self.step
        shared, self.gen = self.gen, self._rank_gen.manual_seed(stream_seed(seed, r, step, 0))
        if self.gen_dev is not None:
            self.gen_dev.manual_seed(stream_seed(seed, r, step, 1))
        try:
            terms, out = super().losses(batch)
        finally:
            self.gen = shared  # the sampling generator: the same state on every rank
        self._share_of_global_mean(terms, batch)
        return terms, out

    def _share_of_global_mean(self, terms: dict[str, torch.Tensor], batch: dict[str, torch.Tensor]) -> None:
        """Renormalise subset means by the global subset size, and make every rank see a NaN any rank saw (all
        ranks then skip the step and roll back together)."""
        m = self.model.n_objects
        given = batch["given"][:, :m].sum() if m else torch.zeros((), device=batch["t"].device)
        valid = (batch["mask"] >= 0).sum()
        bad = sum(1 for v in terms.values() if not bool(torch.isfinite(v.detach())))
        local = torch.tensor([float(given), float(valid), float(bad)], dtype=torch.float64, device=self.ranks.device)
        total = local.clone()
        dist.all_reduce(total)
        if self.normalise_counts:
            for name, i in (("var", 0), ("focal", 1)):
                if name in terms and float(total[i]) > 0:
                    terms[name] = terms[name] * float(local[i] * self.ranks.world / total[i])
        if float(total[2]) > 0 and not bad:
            terms["rgb"] = terms["rgb"] * float("nan")

    def train_step(self) -> dict[str, float]:
        if self.max_minutes:  # rank 0's clock: the learning-rate decay of a time limit is the same everywhere
            self.elapsed = self._from_writer(self.elapsed)
        return super().train_step()

    def train_budget(self) -> float:
        """Rank 0's remaining time, so every rank stops at the same step under --max-minutes (called by every
        rank the same number of times: once per step in train_step, once in the loop's check)."""
        left = self._from_writer(super().train_budget() - self.elapsed)
        return self.elapsed + left

    def _from_writer(self, value: float) -> float:
        t = torch.tensor([value], dtype=torch.float64, device=self.ranks.device)
        dist.broadcast(t, 0)
        return float(t)

    # -- one writer ------------------------------------------------------------------------------------------------
    def save_checkpoint(self) -> Path:
        path = super().save_checkpoint() if self.ranks.writer else self.run_dir / "latest.pt"
        dist.barrier()  # a rollback on any rank reads it next
        return path

    def _log(self, record: dict[str, Any]) -> None:
        if self.ranks.writer:
            super()._log(record)

    def _truncate_metrics(self) -> dict[str, Any]:
        return super()._truncate_metrics() if self.ranks.writer else {}

    def heldout_psnr(self, i: int, max_side: int) -> float:
        """Rank 0 renders the evaluations; the others would compute the same figure from the same weights."""
        return super().heldout_psnr(i, max_side) if self.ranks.writer else float("nan")


def train_ddp(dataset: str | Path, out: str | Path, cfg, ranks: Ranks, resume: bool = False,
              max_minutes: float = 0.0, show_progress: bool = True) -> dict[str, Any]:
    """`trainer.train` as one rank: rank 0 holds the run lock, writes the report and cleans up a refused run; every
    rank builds its trainer, and all agree before the first checkpoint is written."""
    out = Path(out)
    if not ranks.writer:
        trainer = DDPTrainer(dataset, out, cfg, ranks, resume, max_minutes, show_progress)
        done = finished_summary(trainer) if resume else None
        dist.barrier()
        return done if done is not None else trainer.fit()
    created = not out.exists()
    try:
        with run_lock(out):
            remove_stale_temporaries(out)
            trainer = DDPTrainer(dataset, out, cfg, ranks, resume, max_minutes, show_progress)
            done = finished_summary(trainer) if resume else None
            dist.barrier()  # every rank has looked for checkpoints before rank 0 writes its first one
            return done if done is not None else _train(trainer, out)
    except Exception:
        if created and out.is_dir() and not checkpoint_files(out):
            shutil.rmtree(out, ignore_errors=True)
        raise


def run_rank(dataset: str | Path, out: str | Path, cfg, device: str = "auto", resume: bool = False,
             max_minutes: float = 0.0, show_progress: bool = True, threads: int = 0, **_: Any) -> dict[str, Any]:
    """The `livescene train` of one torchrun process: join the group, split the CPU threads among this node's
    ranks, silence the other ranks' stdout (their errors still reach stderr), train, leave the group."""
    ranks = init(device)
    if ranks.device.type == "cpu":
        per_node = int(os.environ.get("LOCAL_WORLD_SIZE", ranks.world))
        torch.set_num_threads(threads or max(1, (os.cpu_count() or 1) // per_node))
    if not ranks.writer:
        sys.stdout = open(os.devnull, "w")
    try:
        return train_ddp(dataset, out, cfg, ranks, resume, max_minutes, show_progress)
    finally:
        dist.destroy_process_group()


def relaunch(nproc: int) -> None:
    """`livescene train ... --ddp` outside torchrun: run this same command again under torchrun with `nproc`
    processes on this machine (replaces this process)."""
    if nproc < 1:
        raise LiveSceneError(f"--nproc {nproc}: give at least 1 process")
    own = list(sys.argv[1:])
    for i, a in reversed(list(enumerate(own))):  # torchrun's parser would take --nproc for its --nproc-per-node
        if a == "--nproc":
            del own[i: i + 2]
        elif a.startswith("--nproc="):
            del own[i]
    argv = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={nproc}",
            "-m", "livescene", *own]
    sys.stdout.flush()
    os.execv(sys.executable, argv)
