"""`interreal demo`: the whole job end to end, on a simulated capture (with truth scores) or on your own video.

simulate -> process (frames -> masks from keyframes -> poses -> labels -> motions) -> validate -> livescene train (CPU preset)
-> eval (against the simulator's truth) -> render a video sweeping each object's state from 0 to 1.
Each step is skipped when its output is already there, so a killed demo resumes where it stopped.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from . import atomic
from .dataset import load_dataset, read_articulation, validate
from .errors import DatasetError, InputError
from .process import process
from .report import read_report, warning_lines
from .scoring import mask_ious, motion_errors, pose_errors
from .synth import SynthConfig, write_capture
from .synth.evaltruth import CaptureTruth

SWEEP_CANDIDATES = 8  # views, spread along the capture, each sweep's camera is chosen from (two renders each)


@dataclass
class DemoConfig:
    out: Path = Path("demo_out")
    video: Path | None = None  # the user's own video: no simulation, no truth scores
    keyframes: Path | None = None
    labels: Path | None = None
    frames: int = 300
    size: tuple[int, int] = (640, 480)
    seed: int = 0
    parts: int = 2
    train_long_side: int = 320
    preset: str = "cpu"
    minutes: float = 10.0
    steps: int = 0  # 0 = the preset's
    sweep_frames: int = 24
    eval_frames: int = 8  # held-out frames to score, evenly spread (0 = all)
    eval_scale: float = 1.0  # render scale for the scores (0.5 = a quicker estimate)
    novel: int = 4  # held-out cameras rendered at state combinations never seen in training
    device: str = "auto"
    rows: list[dict[str, Any]] = field(default_factory=list)


def _row(cfg: DemoConfig, stage: str, seconds: float, quality: str) -> None:
    cfg.rows.append({"stage": stage, "seconds": round(seconds, 1), "quality": quality})
    print(f"[demo] {stage:<9} {seconds:7.1f} s  {quality}", flush=True)


def simulate(cfg: DemoConfig) -> Path:
    cap = cfg.out / "capture"
    t0 = time.perf_counter()
    if not (cap / "gt" / "meta.json").exists():
        write_capture(SynthConfig(frames=cfg.frames, width=cfg.size[0], height=cfg.size[1], seed=cfg.seed,
                                  parts=cfg.parts), cap)
    dt = time.perf_counter() - t0
    _row(cfg, "simulate", dt, f"{cfg.frames} frames {cfg.size[0]}x{cfg.size[1]}" + (f", {cfg.frames / dt:.1f} frames/s" if dt > 1 else " (reused)"))
    return cap


def process_capture(cfg: DemoConfig, video: Path, keyframes: Path | None, labels: Path | None,
                    capture: Path | None) -> Path:
    ds = cfg.out / "dataset"
    done = read_report(ds, "process")
    res = validate(ds) if done and done.get("status") == "ok" else None
    if res is not None and res.ok:
        fig = dict(read_report(ds, "poses").get("figures", {}))  # a finished run: reuse it
    else:
        fig = process(video, ds, keyframes=keyframes, labels=labels, long_side=cfg.train_long_side)
        res = validate(ds)
    if not res.ok:
        raise DatasetError("the processed dataset does not validate:\n" + "\n".join(str(p) for p in res.problems))
    rep = read_report(ds, "process") or {}
    steps = rep.get("steps", {})
    _row(cfg, "frames", steps.get("frames", {}).get("wall_s", 0.0), f"{steps.get('frames', {}).get('frames', '?')} frames selected")
    if keyframes is not None:
        q = _mask_quality(ds, capture) if capture is not None else _mask_summary(ds)
        _row(cfg, "masks", steps.get("masks", {}).get("wall_s", 0.0), q)
    pq = f"{fig.get('registered')}/{fig.get('total')} registered, reproj {fig.get('mean_reproj_error_px', float('nan')):.2f} px"
    if capture is not None:
        pq += ", " + _pose_quality(ds, capture)
    _row(cfg, "poses", steps.get("poses", {}).get("wall_s", 0.0), pq)
    if labels is not None:
        d = load_dataset(ds)
        _, given = d.label_matrix()
        _row(cfg, "labels", steps.get("labels", {}).get("wall_s", 0.0), f"{int(given.sum())} labelled (frame, object) pairs "
             f"on {int(given.any(1).sum())}/{len(d.frames)} frames")
    if "motions" in steps:
        _row(cfg, "motions", steps["motions"].get("wall_s", 0.0), _motion_quality(ds, capture))
    for line in warning_lines(ds, ["frames", "masks", "poses", "labels", "motions"]):  # noticed, not only in JSON
        print(line, flush=True)
    return ds


def _motion_quality(ds: Path, capture: Path | None) -> str:
    """Each object's measured motion, and with a simulated capture how far it is from the true one."""
    if capture is None:
        motions = read_articulation(ds)
        return "; ".join(f"{n}: {motions[n].kind}" if n in motions else f"{n}: not measured"
                         for n in load_dataset(ds).object_names)
    parts = []
    for name, e in motion_errors(ds, capture).items():
        if not e.get("kind"):
            parts.append(f"{name}: not measured")
            continue
        parts.append(f"{name}: {e['kind']} (true {e['true_kind']}), axis {e['axis_deg']:.1f} deg off, range "
                     f"{100 * e['range_error']:.0f} % off")
    return "; ".join(parts) or "no motion measured"


def _mask_summary(ds: Path) -> str:
    """Without truth: what the masks stage itself measured (its confidence; its warnings are printed too)."""
    report = read_report(ds, "masks") or {}
    fig = report.get("figures", {})
    conf = ", ".join(f"{n} {v:.2f}" for n, v in fig.get("confidence_mean", {}).items())
    n_warn = len(report.get("warnings", []))
    return (f"{len(fig.get('keyframes', []))} keyframes -> {fig.get('frames', '?')} frames, mean confidence {conf}"
            + (f", {n_warn} warning{'s' if n_warn > 1 else ''}" if n_warn else ""))


def _pose_quality(ds: Path, capture: Path) -> str:
    c = pose_errors(ds, capture)
    return f"rot err median {c['rot_err_deg_median']:.3f} deg, centre err {c['center_err_pct_median']:.2f} % of path"


def _mask_quality(ds: Path, capture: Path) -> str:
    return "mask IoU " + ", ".join(f"{n} {v:.3f}" for n, v in mask_ious(ds, capture).items())


def train_run(cfg: DemoConfig, ds: Path) -> Path:
    from livescene.config import load_preset
    from livescene.trainer import train

    run = cfg.out / "run"
    t0 = time.perf_counter()
    tc = load_preset(cfg.preset)
    if cfg.steps:
        tc.steps = cfg.steps
    done = read_report(run, "train")
    if done and done.get("status") == "ok":  # a finished run: reuse it (re-running would train further)
        summary = done.get("figures", {})
    else:
        resume = (run / "latest.pt").exists()
        summary = train(ds, run, tc, device=cfg.device, resume=resume, max_minutes=cfg.minutes)
    _row(cfg, "train", time.perf_counter() - t0,
         f"{summary.get('steps', '?')} steps, {summary.get('params', '?')} params, stop: {summary.get('stop')}")
    return run


def evaluate_run(cfg: DemoConfig, run_dir: Path, capture: Path | None) -> dict[str, Any]:
    from livescene.evaluate import evaluate
    from livescene.trainer import load_run

    t0 = time.perf_counter()
    run = load_run(run_dir, device=cfg.device)
    truth = CaptureTruth(capture, run.views) if capture is not None else None
    res = evaluate(run, truth, max_frames=cfg.eval_frames, scale=cfg.eval_scale, novel=cfg.novel)
    atomic.write_json(cfg.out / "eval.json", res)

    figures = [("PSNR", "psnr", "{:.2f} dB"), ("SSIM", "ssim", "{:.3f}"), ("mask IoU", "mask_iou", "{:.3f}"),
               ("state MAE", "state_mae", "{:.3f}"), ("novel-state PSNR", "novel_state_psnr", "{:.2f} dB")]
    q = ", ".join(f"{label} {fmt.format(res[key])}" for label, key, fmt in figures if res.get(key) is not None)
    if truth is None:
        q += " (against the held-out video frames and the propagated masks; no truth)"
    _row(cfg, "eval", time.perf_counter() - t0, q)
    from livescene.unseen import support_lines

    for line in support_lines(res.get("unsupported") or []):  # states a part without a measured motion never showed
        print(f"[demo] {line}", flush=True)
    return res


def render_sweeps(cfg: DemoConfig, run_dir: Path) -> list[Path]:
    """A video per object sweeping its state 0 -> 1 -> 0 (the others closed), from the view that shows the motion
    best (`livescene.render.sweep_camera` over views spread along the capture), and one strip of them all."""
    from livescene.render import render_view, sweep_camera, sweep_states, write_video
    from livescene.trainer import load_run

    t0 = time.perf_counter()
    run = load_run(run_dir, device=cfg.device)
    views = run.views
    n = len(views.c2w_gl)
    candidates = sorted(set(np.linspace(0, n - 1, min(n, SWEEP_CANDIDATES)).round().astype(int).tolist()))
    out, shown, rows = [], [], []
    for name in views.names:
        i, share = sweep_camera(run, name, candidates)
        frames = []
        for v in np.linspace(0.0, 1.0, cfg.sweep_frames):
            r = render_view(run, views.c2w_gl[i], views.intrinsics[i], sweep_states(views.names, name, v),
                            time=float(views.times[i]))
            frames.append((r["rgb"] * 255).round().astype(np.uint8))
        rows.append(strip_row(name, frames))
        frames += frames[::-1]
        path = cfg.out / "renders" / f"sweep_{name.replace(' ', '_')}.mp4"
        path.parent.mkdir(parents=True, exist_ok=True)
        write_video(path, frames, fps=12)
        out.append(path)
        shown.append(f"{name} {100 * share:.0f} %")
    if rows:
        atomic.write_image(cfg.out / "renders" / "sweep_strip.png", np.vstack(rows))
    _row(cfg, "render", time.perf_counter() - t0,
         f"{len(out)} state sweeps, each from the view that shows it best (pixels that change: {', '.join(shown)})")
    return out


def strip_row(name: str, frames: list[np.ndarray], states: tuple[float, ...] = (0.0, 1 / 3, 2 / 3, 1.0),
              width: int = 200) -> np.ndarray:
    """One row of `renders/sweep_strip.png`: the object at a few states of its sweep (`frames`, state 0 to 1),
    each captioned: the picture to look at first."""
    tiles = []
    for t in states:
        im = frames[round(t * (len(frames) - 1))]
        im = np.ascontiguousarray(cv2.resize(im, (width, round(im.shape[0] * width / im.shape[1])),
                                             interpolation=cv2.INTER_AREA))
        cv2.putText(im, f"{name} {t:.2f}", (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1,
                    cv2.LINE_AA)
        tiles.append(im)
    return np.hstack(tiles)


def format_table(rows: list[dict[str, Any]]) -> str:
    w = max(len(r["quality"]) for r in rows) if rows else 10
    lines = [f"| {'stage':<9} | {'time (s)':>8} | {'quality':<{w}} |", f"|{'-' * 11}|{'-' * 10}|{'-' * (w + 2)}|"]
    lines += [f"| {r['stage']:<9} | {r['seconds']:>8.1f} | {r['quality']:<{w}} |" for r in rows]
    return "\n".join(lines)


def run_demo(cfg: DemoConfig) -> list[dict[str, Any]]:
    cfg.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if cfg.video is None:
        capture = simulate(cfg)
        video = capture / "video.mp4"
        keyframes = capture / "annotations" / "keyframes"
        labels = capture / "annotations" / "states.yaml"
    else:
        if not cfg.video.is_file():
            raise InputError(f"--video {cfg.video} does not exist")
        capture, video, keyframes, labels = None, cfg.video, cfg.keyframes, cfg.labels
    ds = process_capture(cfg, video, keyframes, labels, capture)
    from livescene.device import configure_threads

    # torch threads per stage, from what OTHER processes use right now: two OpenMP threads on cores that another
    # job also wants run several times slower than one (a render took 19 s instead of 3.6 s per frame)
    configure_threads(0)
    run = train_run(cfg, ds)
    configure_threads(0)
    evaluate_run(cfg, run, capture)
    configure_threads(0)
    render_sweeps(cfg, run)
    cfg.rows.append({"stage": "total", "seconds": round(time.perf_counter() - t0, 1), "quality": str(cfg.out)})
    atomic.write_json(cfg.out / "demo.json", {"rows": cfg.rows})
    atomic.write_text(cfg.out / "demo.md", format_table(cfg.rows) + "\n")
    print()
    print(format_table(cfg.rows))
    print(f"\nopen: livescene view {run}   (orbit the scene, a slider per object)\n"
          f"      {cfg.out / 'renders'}/sweep_*.mp4   (each object from closed to open and back; sweep_strip.png)\n"
          "the table: each stage's time and how well it did (poses against the simulator's cameras, masks against "
          "its masks, held-out PSNR and state error of the trained scene; on your own video, what each stage "
          "measured itself)")
    return cfg.rows


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = text.lower().split("x")
        return int(w), int(h)
    except ValueError as exc:
        raise InputError(f"--size {text!r}: expected WxH, e.g. 640x480") from exc


def add_arguments(p) -> None:
    p.add_argument("out", nargs="?", type=Path, default=Path("demo_out"), help="output folder (default demo_out/)")
    p.add_argument("--video", type=Path, help="your own video instead of the simulated capture (no truth scores)")
    p.add_argument("--keyframes", type=Path, help="with --video: keyframe masks folder")
    p.add_argument("--labels", type=Path, help="with --video: keyframe states file")
    p.add_argument("--frames", type=int, default=300, help="simulated frames (default 300)")
    p.add_argument("--size", default="640x480", help="simulated video size (default 640x480)")
    p.add_argument("--parts", type=int, default=2, help="interactive parts in the simulated room (default 2)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--train-long-side", type=int, default=320, help="training image long side (default 320)")
    p.add_argument("--preset", default="cpu", help="livescene training preset (default cpu)")
    p.add_argument("--minutes", type=float, default=10.0, help="training time limit in minutes (default 10)")
    p.add_argument("--steps", type=int, default=0, help="training steps (default: the preset's)")
    p.add_argument("--eval-frames", type=int, default=8, help="held-out frames to score, evenly spread (default 8; 0 = all)")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda")
    p.epilog = ("examples:\n"
                "  interreal demo                        # simulate, process, train (<= 10 min on 2 cores), eval, render\n"
                "  interreal demo out/demo --frames 120 --minutes 3\n"
                "  interreal demo out/mine --video room.mp4 --keyframes ann/keyframes --labels ann/states.yaml\n"
                "Re-running resumes: finished steps are reused.")


def main(args) -> int:
    if args.video is None and (args.keyframes or args.labels):
        raise InputError("--keyframes / --labels go with --video (the simulated capture brings its own)")
    from livescene.device import reexec_with_jemalloc

    reexec_with_jemalloc(("interreal", "demo"))
    cfg = DemoConfig(out=args.out, video=args.video, keyframes=args.keyframes, labels=args.labels,
                     frames=args.frames, size=_size(args.size), seed=args.seed, parts=args.parts,
                     train_long_side=args.train_long_side, preset=args.preset, minutes=args.minutes,
                     steps=args.steps, eval_frames=args.eval_frames, device=args.device)
    run_demo(cfg)
    print(json.dumps({"out": str(cfg.out)}))
    return 0
