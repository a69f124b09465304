"""`livescene train DS --out RUN`: options -> a TrainConfig (preset, `--set`, flags) -> `trainer.train`."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

from .. import ddp
from ..config import apply_overrides, check_config, load_preset, preset_names
from ..device import JEMALLOC_ENV, configure_threads, reexec_with_jemalloc, select_device
from ..errors import LiveSceneError
from ..trainer import train


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
    p.add_argument("--ddp", action="store_true", help="data-parallel over --nproc processes started by torchrun "
                   "(livescene.ddp; under torchrun it is on by itself); batch_rays is per process")
    p.add_argument("--nproc", type=int, default=0, help="with --ddp: processes (default: one per GPU, else 2)")
    p.epilog = ("examples:\n"
                "  livescene train out/ds --out out/run                       # cpu preset on CPU, gpu preset on CUDA\n"
                "  livescene train out/ds --out out/run --preset cpu --max-minutes 15\n"
                "  livescene train out/ds --out out/run --resume              # after a kill, continues exactly\n"
                "  livescene train out/ds --out out/run --set model.reject_threshold=0 --steps 2000\n"
                "  livescene train out/ds --out out/run --set model.motion=none   # the paper's k-axis alone, even\n"
                "                                                   # when out/ds/articulation.json has part motions\n"
                f"{JEMALLOC_ENV}=1 re-runs it under jemalloc (slower on the machine it was measured on; see livescene.device)")


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
    # data-parallel: --ddp, or this process started by torchrun
    if args.ddp and not ddp.under_torchrun():
        ddp.relaunch(args.nproc or ddp.default_nproc())  # this same command under torchrun; does not return
    kw = {"threads": args.threads} if ddp.under_torchrun() else {"measure_threads": args.threads <= 0}
    summary = (ddp.run_rank if ddp.under_torchrun() else train)(
        args.dataset, args.out, cfg, device=str(device), resume=args.resume, max_minutes=args.max_minutes,
        show_progress=not args.no_progress, **kw)
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
