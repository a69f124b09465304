"""Per-frame appearance benchmark: captures trained with and without `model.appearance` for the same steps.

The same number of steps (not the same time: on a shared machine time measures the neighbours); each run evaluated
on its held-out frames both neutral (identity, as a new view renders) and with each held-out frame's code
interpolated in time from the training frames around it (`livescene eval`: `psnr`, `psnr_interpolated`).

    python recipes/bench_appearance.py --data laptop=bench/real_ds --steps 800 --out bench/
    python recipes/bench_appearance.py --data drift=out/syn_ds,still=out/syn0_ds --variants off,gain,affine
    python recipes/bench_appearance.py --quick --out bench/     # a simulated capture with exposure drift, 300 steps

A variant is a mode with optional settings: `gain:loss.appearance=0.001:model.appearance_lr=0.01`. Per run: steps,
training seconds per step (and its overhead over `off` on the same capture: noisy on a shared machine, so the modes
are also timed taking turns in one process, `interleaved_s_per_step`), held-out PSNR / SSIM neutral and
interpolated, with `--gt` the neutral render against the simulator's clean one (`clean_psnr`: the scene as it is,
without the exposure of any frame), and the spread of the learned gains over the training frames.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchlib import bench_args, print_table, write_results


def _extra(p) -> None:
    p.add_argument("--data", default="", help="NAME=DATASET[,NAME=DATASET...] (default: a simulated capture with "
                   "+-20 %% exposure drift, written to OUT/appearance_synth)")
    p.add_argument("--gt", default="", help="NAME=CAPTURE[,...]: the simulated capture of a dataset: its held-out "
                   "cameras are also scored against the simulator's clean renders (no exposure change), `clean_psnr`")
    p.add_argument("--variants", default="off,gain", help="comma-separated MODE[:KEY=VALUE...] (default off,gain)")
    p.add_argument("--steps", type=int, default=0, help="training steps of every run (default 800, quick 300)")
    p.add_argument("--preset", default="cpu", help="training preset (default cpu)")
    p.add_argument("--threads", type=int, default=2, help="training threads (default 2)")
    p.add_argument("--eval-frames", type=int, default=8, help="held-out frames evaluated (default 8)")
    p.add_argument("--scale", type=float, default=0.5, help="evaluation render scale (default 0.5)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-train", action="store_true", help="only time the steps (interleaved_s_per_step)")


def synth_dataset(out: Path, drift: float) -> Path:
    """A small simulated capture (120 frames, 320x240) with `drift` auto-exposure swing, as a truth dataset; the
    camera sweeps its arc there and back (speed 2), so the same surfaces are seen again at another exposure (seen
    once, a surface's brightness and the exposure of the frames that saw it cannot be told apart)."""
    from interreal.synth.capture import write_capture
    from interreal.synth.config import SynthConfig, load_preset
    from interreal.synth.truth import truth_dataset

    cap, ds = out / f"synth_{drift:g}", out / f"synth_{drift:g}_ds"
    if not (ds / "transforms.json").exists():
        cfg = SynthConfig.from_dict({**load_preset("small"), "frames": 120, "exposure_drift": drift,
                                     "speed": 2.0}).check()
        write_capture(cfg, cap, progress=False)
        truth_dataset(cap, ds, size=(320, 240))
    return ds


def parse_variant(text: str) -> tuple[str, list[str]]:
    """`gain:loss.appearance=0.001` -> ("gain", ["model.appearance=gain", "loss.appearance=0.001"])."""
    mode, *sets = text.split(":")
    return mode, [f"model.appearance={mode}", *sets]


def run_one(ds: Path, run: Path, sets: list[str], args, gt: str | None = None) -> dict:
    """Train and evaluate one variant; the figures."""
    shutil.rmtree(run, ignore_errors=True)
    cmd = [sys.executable, "-m", "livescene", "train", str(ds), "--out", str(run), "--preset", args.preset,
           "--steps", str(args.steps), "--threads", str(args.threads), "--seed", str(args.seed), "--no-progress",
           "--set", "eval_every=0", "--set", "final_eval_max_side=160"]
    for s in sets:
        cmd += ["--set", s]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    wall = time.perf_counter() - t0
    fig = json.loads((run / "reports" / "train.json").read_text())["figures"]
    ev_path = run / "eval.json"
    truth = ["--gt", gt, "--novel", "4"] if gt else ["--novel", "0"]
    subprocess.run([sys.executable, "-m", "livescene", "eval", str(run), "--out", str(ev_path), "--max-frames",
                    str(args.eval_frames), "--scale", str(args.scale), *truth], check=True)
    ev = json.loads(ev_path.read_text())
    out = {"steps": fig["steps"], "train_wall_s": round(wall, 1),
           "s_per_step": round(fig["elapsed_s"] / max(fig["steps"], 1), 4),
           "psnr": ev["psnr"], "psnr_interpolated": ev.get("psnr_interpolated"), "ssim": ev["ssim"],
           "ssim_interpolated": ev.get("ssim_interpolated"), "eval_frames": ev["held_out_frames"]}
    if gt:  # the neutral render against the scene as it is (the simulator without exposure), 4 held-out cameras
        out["clean_psnr"] = ev.get("true_state_sim_psnr")
    out.update(gain_spread(run))
    return out


def step_overhead(ds: Path, modes: list[str], preset: str, threads: int, rounds: int = 40) -> dict[str, float]:
    """Seconds per training step of each mode, timed in one process with the modes taking turns step by step
    (`rounds` steps each, after one warm-up step), so a busy neighbour slows them all alike: the median per mode."""
    import torch

    import tempfile

    from livescene.config import load_preset
    from livescene.trainer import Trainer

    torch.set_num_threads(threads)
    trainers = {}
    with tempfile.TemporaryDirectory() as tmp:
        for mode in modes:
            cfg = load_preset(preset)
            cfg.model.appearance = mode
            trainers[mode] = Trainer(ds, Path(tmp) / mode, cfg, device="cpu", show_progress=False)
        times: dict[str, list[float]] = {m: [] for m in modes}
        for r in range(rounds + 1):
            for mode, tr in trainers.items():
                t0 = time.perf_counter()
                tr.train_step()
                if r:
                    times[mode].append(time.perf_counter() - t0)
    return {m: round(float(np.median(v)), 4) for m, v in times.items()}


def gain_spread(run_dir: Path) -> dict:
    """The learned brightness gains of the training frames (mean over channels of the diagonal): 5th-95th
    percentile, what the codes say the exposure did."""
    import torch

    ckpt = torch.load(run_dir / "latest.pt", map_location="cpu", weights_only=False)
    codes, trained = ckpt["model"].get("appearance.codes"), ckpt["model"].get("appearance.trained")
    if codes is None:
        return {}
    codes = codes[trained] - codes[trained].mean(0)
    mode = ckpt["config"]["model"]["appearance"]
    diag = codes[:, :3] if mode == "gain" else codes[:, [0, 4, 8]]
    gain = (torch.exp(diag) if mode == "gain" else 1 + diag).mean(1).numpy()
    return {"gain_p5": round(float(np.percentile(gain, 5)), 3), "gain_p95": round(float(np.percentile(gain, 95)), 3)}


def main() -> None:
    args = bench_args("appearance", __doc__.splitlines()[0], _extra)
    args.steps = args.steps or (300 if args.quick else 800)
    if args.data:
        data = dict(item.split("=", 1) for item in args.data.split(","))
    else:
        ds = synth_dataset(args.out / "appearance_synth", 0.2)
        data, args.gt = {"synth_drift0.2": str(ds)}, f"synth_drift0.2={ds.parent / 'synth_0.2'}"
    gts = dict(item.split("=", 1) for item in args.gt.split(",")) if args.gt else {}
    runs = []
    for name, ds in ({} if args.no_train else data).items():
        base = None
        for text in args.variants.split(","):
            mode, sets = parse_variant(text.strip())
            slug = text.strip().replace(":", "_").replace("=", "-")
            r = {"capture": name, "variant": text.strip(), **run_one(Path(ds), args.out / f"app_{name}_{slug}",
                                                                     sets, args, gts.get(name))}
            if mode == "off" and base is None:
                base = r
            if base is not None:
                r["step_overhead"] = round(r["s_per_step"] / base["s_per_step"] - 1, 3)
                r["psnr_vs_off"] = round(r["psnr"] - base["psnr"], 2)
            runs.append(r)
            print(json.dumps(r), flush=True)
    modes = list(dict.fromkeys(["off"] + [parse_variant(v.strip())[0] for v in args.variants.split(",")]))
    timed = step_overhead(Path(next(iter(data.values()))), modes, args.preset, args.threads)
    print(f"seconds per step, modes taking turns in one process: {timed}")
    path = write_results(args.out, "appearance", runs, steps=args.steps, preset=args.preset,
                         interleaved_s_per_step=timed)
    print_table(runs, ["capture", "variant", "steps", "s_per_step", "step_overhead", "psnr", "psnr_interpolated",
                       "psnr_vs_off", "clean_psnr", "ssim", "ssim_interpolated", "gain_p5", "gain_p95"])
    print(f"-> {path}")


if __name__ == "__main__":
    main()
