"""Benchmark the simulated capture: speed (frames/s, 640x480) and truth self-consistency, per preset.

    python recipes/bench_synth.py --out bench            # 300 frames per preset (~3-6 min on 2 cores)
    python recipes/bench_synth.py --quick --out bench    # 60 frames, three presets (~1 min)

Writes bench/synth.json ({"runs": [...]}) and bench/synth.png, prints a table. Speed is the wall time of
`write_capture` (render + H.264 encode + truth PNGs + annotations); the machine's other load is recorded with it
(`load_avg`), since 2 shared cores make wall times pessimistic. Consistency: static pixels of frame i warped into
frame i+3 with the gt depth, poses and distorted intrinsics (`interreal.synth.consistency`).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path


def run_one(preset: str, frames: int, work: Path) -> dict:
    from interreal.synth import SynthConfig, build_scene, load_preset, write_capture
    from interreal.synth.consistency import reprojection_summary

    settings = load_preset(preset)
    settings.update(frames=frames, width=640, height=480)
    cfg = SynthConfig.from_dict(settings)
    out = work / preset
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    write_capture(cfg, out, progress=False)
    wall = time.perf_counter() - t0
    cpu = time.process_time() - cpu0
    meta = json.loads((out / "gt" / "meta.json").read_text())
    scene = build_scene(cfg)
    pairs = [(i, i + 3) for i in range(0, frames - 3, max(1, frames // 8))][:8]
    rep = reprojection_summary(scene, pairs)
    shutil.rmtree(out, ignore_errors=True)
    t = meta["timings"]
    return {
        "preset": preset, "frames": frames, "size": "640x480", "parts": cfg.parts, "wall_s": round(wall, 2),
        "fps": round(frames / wall, 2), "cpu_s": round(cpu, 2),
        "fps_2core_cpu_bound": round(frames / (cpu / 2), 2),  # if the 2 cores were ours alone "render_cpu_s": t["render_cpu_s"],
        "video_encode_s": t["video_encode_s"], "load_avg": round(load, 2),
        "reproj_colour_mae": round(rep["colour_mae"], 3), "reproj_depth_rel": float(f"{rep['depth_rel']:.3g}"),
        "reproj_overlap": round(rep["overlap"], 3),
        "min_part_fraction": min(meta["visible_fraction"]),
    }


def plot(runs: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    names = [r["preset"] for r in runs]
    a.barh(names, [r["fps"] for r in runs], color="tab:blue")
    a.axvline(5.0, color="tab:red", ls="--", label="requirement: 300 frames in 60 s")
    a.set_xlabel("frames / s (640x480, wall, incl. encode + truth)")
    a.legend(loc="lower right", fontsize=8)
    b.barh(names, [r["reproj_colour_mae"] for r in runs], color="tab:green")
    b.set_xlabel("reprojection colour error of static pixels (8-bit levels)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="60 frames, three presets")
    p.add_argument("--out", type=Path, default=Path("bench"))
    args = p.parse_args(argv)
    presets = (["default", "stress-occluder", "stress-parts"] if args.quick else
               ["default", "stress-texture-low", "stress-noise", "stress-occluder", "stress-parts", "stress-fast"])
    frames = 60 if args.quick else 300
    args.out.mkdir(parents=True, exist_ok=True)
    runs = []
    with tempfile.TemporaryDirectory(prefix="bench_synth_") as tmp:
        for preset in presets:
            runs.append(run_one(preset, frames, Path(tmp)))
            r = runs[-1]
            print(f"{r['preset']:<20} {r['frames']:>4} frames  {r['wall_s']:>6.1f} s  {r['fps']:>5.1f} fps  "
                  f"cpu {r['cpu_s']:>5.1f} s ({r['fps_2core_cpu_bound']:.0f} fps on 2 free cores)  reproj {r['reproj_colour_mae']:.2f}/255  "
                  f"depth {r['reproj_depth_rel']:.1e}  load {r['load_avg']:.1f}", flush=True)
    from interreal import atomic

    atomic.write_json(args.out / "synth.json", {"runs": runs})
    plot(runs, args.out / "synth.png")
    print(f"wrote {args.out / 'synth.json'} and {args.out / 'synth.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
