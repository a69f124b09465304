"""Data-parallel training (livescene.ddp) on CPU with 2 gloo processes: N steps of 2 ranks with batch B give the
parameters of N steps of one process with batch 2B; Lvar needs the global renormalisation to get there; one
writer; a resumed DDP run ends where an uninterrupted one does."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest
import torch

from conftest import make_tiny_dataset

B = 48  # rays per rank
STEPS = 5
WORLD = 2


def _cfg(batch: int, steps: int):
    from livescene.config import apply_overrides, load_preset

    cfg = apply_overrides(load_preset("tiny"), ["loss.repulsion=0", "lr_final_ratio=1", "warmup=0",
                                                "keyframe_fraction=0.25", "final_eval_max_side=32",
                                                "error_rays=0.5"])  # the ranks' error maps must stay alike
    cfg.batch_rays, cfg.steps = batch, steps
    return cfg


def _steps(trainer, n: int) -> dict[str, torch.Tensor]:
    trainer.gen_dev = None  # no sample jitter: each rank's jitter is its own stream, only its absence can match
    for _ in range(n):
        info = trainer.train_step()
        assert torch.isfinite(torch.tensor(info["loss"]))
    return {k: v.detach().clone() for k, v in trainer.model.state_dict().items() if v.is_floating_point()}


def _worker(rank: int, ds: str, root: str, port: int) -> None:
    import torch.distributed as dist

    from livescene.ddp import DDPTrainer, Ranks, train_ddp

    torch.set_num_threads(1)
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=WORLD)
    ranks = Ranks(rank, WORLD, rank, torch.device("cpu"), "gloo")
    root_p = Path(root)
    try:
        for name, normalise in (("ddp", True), ("ddp_raw", False)):
            t = DDPTrainer(ds, root_p / name, _cfg(B, STEPS), ranks, show_progress=False)
            t.normalise_counts = normalise
            state = _steps(t, STEPS)
            if rank == 0:
                torch.save(state, root_p / f"{name}.pt")
        # fit() with jitter on: straight, and stopped at 3 then resumed to 6; rank 0 writes everything
        train_ddp(ds, root_p / "A", _cfg(B, 6), ranks, show_progress=False)
        train_ddp(ds, root_p / "B", _cfg(B, 3), ranks, show_progress=False)
        train_ddp(ds, root_p / "B", _cfg(B, 6), ranks, resume=True, show_progress=False)
    finally:
        dist.destroy_process_group()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def ddp_runs(tmp_path_factory):
    """The single-process reference first (its imports, torch's lazy ones included, are then inherited by forked
    ranks: a spawned rank spent 10-20 s importing on a loaded 2-core machine), then the 2 ranks."""
    import torch.multiprocessing as mp

    from livescene.trainer import Trainer

    root = tmp_path_factory.mktemp("ddp")
    ds = make_tiny_dataset(root / "ds", n_frames=6)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        start = Trainer(ds, root / "start", _cfg(B, STEPS), device="cpu",  # same seed
                        show_progress=False).model.state_dict()
        start = {k: v.clone() for k, v in start.items() if v.is_floating_point()}
        single = _steps(Trainer(ds, root / "single", _cfg(WORLD * B, STEPS), device="cpu", show_progress=False),
                        STEPS)  # on the ranks' device: a CUDA machine would otherwise pick its GPU
        # fork inherits the imports, but not where CUDA is: autograd then keeps device threads a fork cannot copy
        method = "spawn" if torch.cuda.is_available() else "fork"
        mp.start_processes(_worker, args=(str(ds), str(root), _free_port()), nprocs=WORLD, join=True,
                           start_method=method)
    finally:
        torch.set_num_threads(threads)
    return root, start, single


def test_two_ranks_batch_b_equal_one_process_batch_2b(ddp_runs):
    root, start, single = ddp_runs
    ddp = torch.load(root / "ddp.pt")
    raw = torch.load(root / "ddp_raw.pt")
    moved = max(float((single[k] - start[k]).abs().max()) for k in single)
    diff = {k: float((single[k] - ddp[k]).abs().max()) for k in single}
    assert moved > 0.05  # the steps moved the weights (lr 0.03 x 5 Adam steps)
    assert max(diff.values()) < 1e-4, sorted(diff.items(), key=lambda kv: -kv[1])[:3]
    # the per-frame variable (its line over time, and the decoder) is among what matches; without the global
    # count, a rank's Lvar mean would weigh its few labelled rays as much as the other rank's many
    assert any(k.startswith("variable.") for k in diff)
    raw_diff = max(float((single[k] - raw[k]).abs().max()) for k in single if k.startswith("variable."))
    assert raw_diff > 100 * max(diff.values()) and raw_diff > 1e-4
    print(f"DDP vs one process: max |diff| {max(diff.values()):.2e} after moving {moved:.3f}; without the global "
          f"Lvar count {raw_diff:.2e}")


def test_one_writer_and_resume_matches_uninterrupted(ddp_runs):
    import json

    root = ddp_runs[0]
    a, b = root / "A", root / "B"
    records = [json.loads(line) for line in (a / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records if r["type"] == "train"] == [6]  # written once, not once per rank
    assert json.loads((a / "reports" / "train.json").read_text())["status"] == "ok"
    assert sorted(p.name for p in (a / "checkpoints").glob("*.pt")) == ["step_0000000.pt", "step_0000006.pt"]
    sa = torch.load(a / "latest.pt", weights_only=False)
    sb = torch.load(b / "latest.pt", weights_only=False)
    assert sa["step"] == sb["step"] == 6
    worst = max(float((sa["model"][k] - sb["model"][k]).abs().max()) for k in sa["model"]
                if sa["model"][k].is_floating_point())
    assert worst < 1e-6, worst
    assert [r["step"] for r in map(json.loads, (b / "metrics.jsonl").read_text().splitlines())
            if r["type"] == "train"] == [3, 6]


def test_ddp_flag_relaunches_the_command_under_torchrun(monkeypatch):
    """`livescene train ... --ddp --nproc 3` outside torchrun runs itself again under torchrun (which would read
    --nproc as its own --nproc-per-node, so it is taken out); under torchrun, `under_torchrun` holds."""
    import sys

    from livescene import ddp
    from livescene.errors import LiveSceneError

    calls = []
    monkeypatch.setattr(ddp.os, "execv", lambda exe, argv: calls.append(argv))
    monkeypatch.setattr(sys, "argv", ["livescene", "train", "ds", "--out", "run", "--ddp", "--nproc", "3",
                                      "--steps", "10"])
    ddp.relaunch(3)
    assert calls[0][1:6] == ["-m", "torch.distributed.run", "--standalone", "--nproc-per-node=3", "-m"]
    assert calls[0][6:] == ["livescene", "train", "ds", "--out", "run", "--ddp", "--steps", "10"]
    with pytest.raises(LiveSceneError, match="--nproc -1"):
        ddp.relaunch(-1)
    for var in ddp.TORCHRUN_VARS:
        monkeypatch.delenv(var, raising=False)
    assert not ddp.under_torchrun()
    monkeypatch.setenv("RANK", "0"), monkeypatch.setenv("WORLD_SIZE", "2"), monkeypatch.setenv("LOCAL_RANK", "0")
    monkeypatch.setenv("MASTER_ADDR", "127.0.0.1"), monkeypatch.setenv("MASTER_PORT", "29500")
    assert ddp.under_torchrun()
