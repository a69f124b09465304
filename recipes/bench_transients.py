"""Transients: is a person who walks through the capture kept out of the trained scene?

A simulated capture where a person walks across the view (`occluder`); the person is painted as the ignore class
(254) on the keyframes, `interreal masks` propagates it into DS/transients/, and the same dataset is trained four
times: with the transient layer and without it (the folder removed), each with the plain colour loss and with the
trimmed one (`livescene.losses.trimmed_mse`, RobustNeRF-style: the 20 % of each batch's rays with the largest error
left out). Each training camera that saw the person is rendered
and compared with the simulator's clean render of that camera (no person): PSNR inside the person's pixels (the
person baked into the scene shows there) and outside them. Also: the propagated layer's IoU against the truth.

    python recipes/bench_transients.py --quick --out bench/
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from benchlib import bench_args, print_table, scatter_chart, write_results


def psnr(a: np.ndarray, b: np.ndarray) -> float | None:
    if a.size == 0:
        return None
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 100.0 if mse <= 1e-10 else -10.0 * np.log10(mse)


def make_dataset(root: Path, frames: int, size: tuple[int, int], occluder: float, seed: int) -> tuple[Path, Any]:
    """Capture -> truth dataset (true poses and labels) -> propagated masks and transients from painted keyframes."""
    from interreal import atomic
    from interreal.conventions import fid_of_index
    from interreal.masks import propagate
    from interreal.synth import Capture, SynthConfig, truth_dataset, write_capture
    from interreal.transients import IGNORE

    cap_dir = write_capture(SynthConfig(frames=frames, width=size[0], height=size[1], occluder=occluder, seed=seed,
                                        keyframe_every=max(10, frames // 6)), root / "cap", progress=False)
    cap = Capture.open(cap_dir)
    ds = truth_dataset(cap_dir, root / "ds", size=size)
    keys = root / "keys"
    for k in cap.keyframes:
        m = cap.instance(k).copy()
        m[m == 255] = IGNORE
        atomic.write_image(keys / f"{fid_of_index(k)}.png", m)
    atomic.write_yaml(keys / "mapping.yaml", dict(enumerate(cap.names)))
    fig = propagate(ds, keys, preview="none", progress=False)
    return ds, cap, fig


def layer_iou(ds: Path, cap) -> float:
    from interreal.conventions import fid_of_index
    from interreal.transients import read_transient

    vals = []
    for i in range(len(cap)):
        if i in cap.keyframes:
            continue
        truth = cap.instance(i) == 255
        pred = read_transient(ds, fid_of_index(i), truth.shape)
        pred = np.zeros_like(truth) if pred is None else pred
        u = (truth | pred).sum()
        if u:
            vals.append((truth & pred).sum() / u)
    return float(np.mean(vals))


def score(run_dir: Path, cap, most: int) -> dict[str, Any]:
    """PSNR against the clean scene inside / outside the person, on training cameras that saw the person."""
    from livescene.render import render_view
    from livescene.run import load_run

    run = load_run(run_dir, device="cpu")
    views = run.views
    scene = cap.scene()
    picks = [i for i in views.train if (cap.instance(i) == 255).mean() > 0.05]
    picks = [picks[int(j)] for j in np.linspace(0, len(picks) - 1, min(most, len(picks))).round().astype(int)]
    inside, outside = [], []
    for i in picks:
        intr = views.intrinsics[i]
        states = {n: float(v) for n, v in zip(cap.names, cap.states[i])}
        out = render_view(run, views.c2w_gl[i], intr, states, time=float(views.times[i]))
        clean = scene.render(views.c2w_gl[i], cap.states[i], intrinsics=intr).rgb.astype(np.float32) / 255.0
        person = cv2.resize((cap.instance(i) == 255).astype(np.uint8), (intr.w, intr.h),
                            interpolation=cv2.INTER_NEAREST) > 0
        inside.append(psnr(out["rgb"][person], clean[person]))
        outside.append(psnr(out["rgb"][~person], clean[~person]))
    return {"psnr_person_region": float(np.mean(inside)), "psnr_elsewhere": float(np.mean(outside)),
            "views": len(picks)}


def main() -> None:
    args = bench_args("transients", __doc__.splitlines()[0])
    import torch

    from livescene.config import load_preset
    from livescene.trainer import train

    torch.set_num_threads(1)
    frames, size, steps = (48, (160, 120), 1500) if args.quick else (120, (320, 240), 4000)
    work = args.out / "transients_work"
    shutil.rmtree(work, ignore_errors=True)
    ds, cap, fig = make_dataset(work, frames, size, occluder=0.5, seed=0)
    iou = layer_iou(ds, cap)
    runs = []
    bare = work / "ds_no_transients"
    shutil.copytree(ds, bare)
    shutil.rmtree(bare / "transients")
    # (name, dataset, trimmed colour loss): the painted layer; nothing; nothing but the loss that trims what the
    # scene cannot explain (`--set loss.rgb=0 --set loss.rgb_trimmed=1`); both
    arms = [("with layer", ds, False), ("without", bare, False), ("without, trimmed loss", bare, True),
            ("with layer, trimmed loss", ds, True)]
    for name, ds_run, robust in arms:
        cfg = load_preset("tiny")
        cfg.steps = steps
        cfg.holdout_every = 0
        if robust:
            cfg.loss.rgb, cfg.loss.rgb_trimmed = 0.0, 1.0
        run_dir = work / f"run_{name.replace(', ', '_').replace(' ', '_').replace('-', '')}"
        t0 = time.perf_counter()
        train(ds_run, run_dir, cfg, device="cpu", show_progress=False)
        train_s = time.perf_counter() - t0
        rec = {"transients": name, "frames": frames, "size": f"{size[0]}x{size[1]}",
               "steps": steps, "train_s": round(train_s, 1), "layer_iou": round(iou, 4),
               "person_frames": fig["transients"]["frames"], **score(run_dir, cap, most=8)}
        runs.append(rec)
    write_results(args.out, "transients", runs)
    scatter_chart(args.out / "transients.png", runs, x="psnr_elsewhere", y="psnr_person_region",
                  label=lambda r: r["transients"],
                  title="person region vs elsewhere: PSNR against the clean scene")
    print_table(runs, ["transients", "frames", "size", "steps", "train_s", "layer_iou", "psnr_person_region",
                       "psnr_elsewhere", "views"])


if __name__ == "__main__":
    main()
