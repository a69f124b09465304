"""Benchmark `livescene train` on the default simulated capture at 320x240 (2 CPU cores).

Runs (each a flat record: data, variant, minutes, steps, psnr, ssim, state_mae, novel_state_psnr, mask_iou,
params, label_fraction):
  main       the cpu preset for 15 minutes (--quick: 2), full held-out evaluation (every 8th frame); with the part
             motions `interreal motions` measured (rigid parts), scored against the simulator's (`motions`)
  motion     the same length with the paper's k-axis alone (model.motion=none), and with the true motions
  reject     probability rejection s = 0 (official) against ours (s = 0.5), and ours with the official code's
             background k = 0 instead of a background slice of its own, equal time
  labels     state MAE against the fraction of labelled frames (1, 2, 5, 10, 25 %)
  capacity   held-out PSNR against parameter count (capacity x0.25 .. x2; x1 = the auto size)
  objects    parameter count against the number of objects (1..6; no training needed)
Data: `interreal synth` (300 frames, 640x480), then (default `--source own`) our own pipeline at 320x240, as a user
runs it: `interreal process` (frames -> masks from the keyframes every 60 frames -> SfM poses -> state labels on ~10 %
of frames), scene box from SfM's sparse_pc.ply; or (`--source truth`) `truth_dataset`, the simulator's poses and
masks with the box from its depth maps. Scores are always against the simulator's truth, rendered from each frame's
own camera. Charts: DIR/train.png (4 panels).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from interreal.conventions import ARTICULATION_FILE  # noqa: E402
from interreal.scoring import motion_errors  # noqa: E402
from benchlib import bench_args, print_table, write_results  # noqa: E402

# evaluation figures copied into a run record (a re-evaluation replaces exactly these)
EVAL_KEYS = ("psnr", "ssim", "state_mae", "novel_state_psnr", "true_state_sim_psnr", "novel_state_mask_iou",
             "composition_psnr", "novel_frames", "composition_frames", "mask_iou", "depth_l1")
COLUMNS = ["data", "variant", "minutes", "steps", "psnr", "ssim", "state_mae", "novel_state_psnr", "mask_iou",
           "params", "label_fraction"]


def extra_args(p) -> None:
    p.add_argument("--data", type=Path, default=None, help="an existing `interreal synth` capture (default: make one)")
    p.add_argument("--source", choices=("own", "truth"), default="own",
                   help="dataset: our own pipeline's output (default) or the simulator's truth poses and masks")
    p.add_argument("--only", default="main,motion,reject,labels,capacity,objects", help="comma list of parts to run")
    p.add_argument("--minutes", type=float, default=None, help="main run length (default 15, --quick 2)")
    p.add_argument("--sweep-minutes", type=float, default=None, help="length of each sweep run (default 4, --quick 1)")
    p.add_argument("--eval-frames", type=int, default=None, help="held-out frames evaluated (default all, --quick 4)")
    p.add_argument("--eval-scale", type=float, default=None,
                   help="render scale of the evaluation (default 0.5 on CPU: 160x120, 1 on CUDA)")
    p.add_argument("--novel", type=int, default=None, help="held-out cameras at novel states (default 3)")
    p.add_argument("--sweep-set", action="append", default=[], metavar="KEY=VALUE",
                   help="settings for the sweep runs only, e.g. --sweep-set batch_rays=256 (repeatable)")
    p.add_argument("--threads", type=int, default=0, help="CPU threads (0 = auto: 1 on a busy machine)")
    p.add_argument("--device", default="auto")


def make_capture(out: Path, quick: bool) -> Path:
    from interreal.synth import SynthConfig, write_capture

    cap = out / "data" / "cap"
    if not (cap / "gt" / "states.json").exists():
        write_capture(SynthConfig(frames=300, width=640, height=480, seed=0), cap, progress=True)
    return cap


def make_dataset(cap: Path, out: Path, source: str = "own") -> Path:
    """The training dataset at 320x240: our pipeline's output (finished stages are reused) or the simulator's truth."""
    if source == "truth":
        from interreal.synth import truth_dataset

        ds = out / "data" / "ds"
        if not (ds / "transforms.json").exists():
            truth_dataset(cap, ds, size=(320, 240))
        return ds
    from interreal.process import process

    ds = out / "data" / "ds_own"
    process(cap / "video.mp4", ds, keyframes=cap / "annotations" / "keyframes",
            labels=cap / "annotations" / "states.yaml", long_side=320)
    return ds


def depth_box(cap_dir: Path, every: int = 10) -> list[float]:
    from interreal.synth import Capture
    from interreal.synth.truth import surface_box

    return surface_box(Capture.open(cap_dir), every)


def relabel(ds: Path, cap: Path, fraction: float, out: Path) -> Path:
    """A copy of `ds` (images/masks linked) whose labels cover `fraction` of the frames (evenly spread + ends)."""
    import shutil

    from interreal import dataset as D
    from interreal.conventions import frame_name
    from interreal.synth import Capture

    dst = out / "data" / f"ds_labels_{int(round(fraction * 1000)):03d}"
    if dst.exists():
        shutil.rmtree(dst)
    dst.mkdir(parents=True)
    for name in ("images", "masks"):
        (dst / name).symlink_to((ds / name).resolve())
    for name in ("transforms.json", "mapping.yaml", "prompts.yaml", "sparse_pc.ply"):
        if (ds / name).exists():
            shutil.copy(ds / name, dst / name)
    src = D.load_dataset(ds)
    truth = Capture.open(cap)
    states = np.asarray(json.loads((cap / "gt" / "states.json").read_text())["values"])
    n = len(src.frames)
    k = max(2, int(round(fraction * n)))
    pick = sorted(set(np.linspace(0, n - 1, k).round().astype(int).tolist()))
    labels = {}
    for j in pick:
        f = src.frames[j]
        labels[frame_name(f.index)] = {nm: float(round(states[f.index, c], 4)) for c, nm in enumerate(truth.names)}
    D.write_labels(dst, labels)
    if (ds / ARTICULATION_FILE).exists():  # the motions as these labels alone give them
        from interreal.motions import estimate_motions

        estimate_motions(dst)
    return dst


def oracle(ds: Path, cap: Path, out: Path) -> Path:
    """A copy of `ds` (folders linked) whose articulation.json holds the simulator's true motions."""
    import shutil

    from interreal import dataset as D
    from interreal.synth import truth_articulation

    dst = out / "data" / "ds_oracle"
    if dst.exists():
        shutil.rmtree(dst)
    dst.mkdir(parents=True)
    for name in ("images", "masks"):
        (dst / name).symlink_to((ds / name).resolve())
    for name in ("transforms.json", "mapping.yaml", "prompts.yaml", "sparse_pc.ply", "key_frame_value.yaml"):
        if (ds / name).exists():
            shutil.copy(ds / name, dst / name)
    D.write_articulation(dst, truth_articulation(cap, ds), {"source": "simulator truth"})
    return dst



EVAL_SCALE = 0.5
NOVEL = 3


def train_and_eval(ds: Path, cap: Path, run_dir: Path, minutes: float, box: list[float], device: str,
                   eval_frames: int, overrides: list[str] | None = None, novel: int | None = None) -> dict:
    import shutil

    from livescene.config import apply_overrides, load_preset
    from interreal.synth.evaltruth import CaptureTruth
    from livescene.evaluate import evaluate
    from livescene.trainer import load_run, train

    if run_dir.exists():
        shutil.rmtree(run_dir)
    cfg = load_preset("cpu" if device != "cuda" else "gpu")
    cfg.scene_box = box
    cfg.steps = 100000  # time-limited
    apply_overrides(cfg, overrides or [])
    t0 = time.perf_counter()
    summary = train(ds, run_dir, cfg, device=device, max_minutes=minutes, show_progress=False)
    wall = time.perf_counter() - t0
    run = load_run(run_dir, device=device)
    t1 = time.perf_counter()
    res = evaluate(run, CaptureTruth(cap, run.views), max_frames=eval_frames, scale=EVAL_SCALE,
                   novel=NOVEL if novel is None else novel, progress=False)
    curve = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    curve = [(r["elapsed_s"] / 60, r["psnr"]) for r in curve if r.get("type") == "eval"]
    return {"minutes": round(summary["elapsed_s"] / 60, 2), "wall_minutes": round(wall / 60, 2),
            "eval_minutes": round((time.perf_counter() - t1) / 60, 2), "steps": summary["steps"],
            **{k: res.get(k) for k in EVAL_KEYS}, "state_mae_max": res.get("state_mae_max"), "params": summary["params"],
            "reject_threshold": res["reject_threshold"], "eval_scale": EVAL_SCALE, "eval_frames": res["held_out_frames"],
            "curve": curve}


def part_of(variant: str) -> str:
    return variant.split(" ")[0]


def charts(path: Path, runs: list[dict]) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(11, 8), dpi=100)
    ax = axes[0, 0]
    for r in runs:
        if r.get("curve") and r["variant"] in ("main", "reject s=0", "reject s=0.5", "reject s=0.5 bg k=0"):
            xs, ys = zip(*r["curve"])
            ax.plot(xs, ys, "-o", ms=3, label=f"{r['variant']} (quick eval, 160 px)")
            if r.get("psnr") is not None:
                ax.scatter([r["minutes"]], [r["psnr"]], marker="*", s=120, label=f"{r['variant']} full held-out")
    ax.axhline(28, ls="--", c="gray", lw=0.8)
    ax.set(xlabel="training minutes (2 shared CPU cores)", ylabel="held-out PSNR (dB)", title="PSNR against wall time")
    ax.legend(fontsize=7)
    ax = axes[0, 1]
    lab = sorted([r for r in runs if r["variant"].startswith("labels")], key=lambda r: r["label_fraction"])
    if lab:
        ax.plot([100 * r["label_fraction"] for r in lab], [r["state_mae"] for r in lab], "-o")
        ax.axhline(0.05, ls="--", c="gray", lw=0.8)
        ax.set_xscale("log")
    ax.set(xlabel="labelled frames (%)", ylabel="state MAE, unlabelled frames", title="State error against labels")
    ax = axes[1, 0]
    cap = sorted([r for r in runs if r["variant"].startswith("capacity")], key=lambda r: r["params"])
    if cap:
        ax.plot([r["params"] for r in cap], [r["psnr"] for r in cap], "-o")
        for r in cap:
            ax.annotate(r["variant"].replace("capacity ", "") + (" (auto)" if r.get("auto") else ""),
                        (r["params"], r["psnr"]), fontsize=8, xytext=(3, 3), textcoords="offset points")
        auto = [r for r in cap if r.get("auto")]
        if auto:
            ax.scatter([auto[0]["params"]], [auto[0]["psnr"]], s=150, facecolors="none", edgecolors="r")
        ax.set_xscale("log")
    ax.set(xlabel="parameters", ylabel="held-out PSNR (dB)", title="Capacity sweep (equal time)")
    ax = axes[1, 1]
    obj = sorted([r for r in runs if r["variant"].startswith("objects")], key=lambda r: r["objects"])
    if obj:
        ax.plot([r["objects"] for r in obj], [r["params"] / 1e6 for r in obj], "-o")
    ax.set(xlabel="interactive objects", ylabel="parameters (M)", title="Parameters against object count")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def main() -> int:
    args = bench_args("train", __doc__.splitlines()[0], extra_args)
    from livescene.device import configure_threads, reexec_with_jemalloc, select_device

    reexec_with_jemalloc()

    threads = configure_threads(args.threads)

    device = str(select_device(args.device).type)
    quick = args.quick
    minutes = args.minutes or (2.0 if quick else 15.0)
    sweep_minutes = args.sweep_minutes or (1.0 if quick else 4.0)
    eval_frames = args.eval_frames if args.eval_frames is not None else (4 if quick else 0)
    only = set(args.only.split(","))
    global EVAL_SCALE, NOVEL
    EVAL_SCALE = args.eval_scale or (1.0 if device == "cuda" else 0.5)
    NOVEL = args.novel if args.novel is not None else 3
    cap = args.data or make_capture(args.out, quick)
    ds = make_dataset(cap, args.out, args.source)
    box = depth_box(cap) if args.source == "truth" else []  # own: the trainer takes it from sparse_pc.ply
    from interreal.dataset import load_dataset

    base = load_dataset(ds)
    label_fraction = sum(1 for _ in base.labels) / len(base.frames)
    results_path = args.out / "train.json"
    runs: list[dict] = []
    if results_path.exists():  # keep the parts not re-run now (so parts can run in separate sessions)
        runs = [r for r in json.loads(results_path.read_text()).get("runs", []) if part_of(r["variant"]) not in only]

    def record(variant: str, rec: dict, **extra) -> None:
        runs.append({"data": f"synth-{args.source} 320x240", "variant": variant, "label_fraction": round(label_fraction, 3),
                     **rec, **extra})
        write_results(args.out, "train", runs, quick=quick, device=device, box=box, threads=threads)
        charts(args.out / "train.png", runs)

    if "main-eval" in only:  # re-evaluate an existing main run (e.g. after changing the evaluation)
        from interreal.synth.evaltruth import CaptureTruth
        from livescene.evaluate import evaluate
        from livescene.trainer import load_run

        old = [r for r in json.loads(results_path.read_text())["runs"] if r["variant"] == "main"] if results_path.exists() else []
        run = load_run(args.out / "runs" / "main", device=device)
        res = evaluate(run, CaptureTruth(cap, run.views), max_frames=eval_frames, scale=EVAL_SCALE, novel=NOVEL,
                       progress=False)
        runs = [r for r in runs if r["variant"] != "main"]
        rec = {**(old[0] if old else {}), **{k: res.get(k) for k in EVAL_KEYS}}
        rec.pop("variant", None)
        rec.pop("data", None)
        rec.pop("label_fraction", None)
        record("main", rec)
    if "main" in only:
        record("main", train_and_eval(ds, cap, args.out / "runs" / "main", minutes, box, device, eval_frames),
               motions=motion_errors(ds, cap))
    if "motion" in only:  # the paper's k-axis alone, and rigid parts with the simulator's true motions
        record("motion k-axis", train_and_eval(ds, cap, args.out / "runs" / "motion_k", minutes, box, device,
                                               eval_frames, ["model.motion=none"]))
        record("motion truth", train_and_eval(oracle(ds, cap, args.out), cap, args.out / "runs" / "motion_truth",
                                              minutes, box, device, eval_frames))
    if "reject" in only:
        for s, bg in ((0.0, "slice"), (0.5, "slice"), (0.5, "zero")):
            name = f"reject s={s:g}" + (" bg k=0" if bg == "zero" else "")
            record(name, train_and_eval(ds, cap, args.out / "runs" / name.replace(" ", "_").replace("=", ""),
                                        sweep_minutes * 1.5, box, device, min(eval_frames or 4, 4),
                                        [*args.sweep_set, f"model.reject_threshold={s}", f"model.background_k={bg}"]))
    if "labels" in only:
        for frac in (0.01, 0.02, 0.05, 0.10, 0.25):
            dsl = relabel(ds, cap, frac, args.out)
            rec = train_and_eval(dsl, cap, args.out / "runs" / f"labels_{frac:g}", sweep_minutes, box, device,
                                 1, args.sweep_set, novel=0)
            record(f"labels {frac:.0%}", rec, label_fraction=frac)
    if "capacity" in only:
        for c in (0.25, 0.5, 1.0, 2.0):
            rec = train_and_eval(ds, cap, args.out / "runs" / f"capacity_{c:g}", sweep_minutes, box, device,
                                 min(eval_frames or 2, 2), [*args.sweep_set, f"model.capacity={c}"], novel=0)
            record(f"capacity x{c:g}", rec, auto=c == 1.0)
    if "objects" in only:
        from livescene.config import load_preset
        from livescene.data import load_views
        from livescene.field import LiveSceneModel
        from livescene.trainer import build_model

        cfg = load_preset("cpu")
        cfg.scene_box = box
        views = load_views(ds, cfg)
        rcfg, _ = build_model(cfg, views)
        for n in range(1, 7):
            record(f"objects {n}", {"params": LiveSceneModel(rcfg.model, n).param_count()}, objects=n)
    print_table(runs, COLUMNS, title=f"livescene train ({'quick' if quick else 'full'}, {device})")
    print(f"-> {results_path}, {args.out / 'train.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
