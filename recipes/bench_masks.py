"""Mask propagation benchmark: J against truth, the time of the whole `interreal masks` command, and whether
the stage's warning predicts the sequences that fail.

Data: every sequence in ../shared/data/davis2016 (images/*.jpg, masks/*.png), and the default simulated capture
(`interreal synth`, its keyframes: every 60 frames + first + last). Every run is the real command
(`python -m interreal masks DS --keyframes K --quiet`, previews included) in a subprocess, timed from start-up
to exit. Settings:
- protocol `first`: the first frame's mask only; protocol `every10`: a truth keyframe every 10 frames;
- the annotation-effort curve: 1, 2, 5, 10, 20 keyframes per 100 frames; after the first frame, keyframes go
  where the stage's own `suggested_frames` (from the run one level below) say;
- the simulated capture (keyframe every 60).
Per run: j_mean (Jaccard, mean over the frames that were not given, per object, then over objects), j_worst_object,
s_per_frame and fps of the whole command, warned (a `masks-unreliable` warning in DS/reports/masks.json),
lost_warned (an `object-lost` warning), predicted_j (the stage's own estimate), redetected (frames where the stage
found a collapsed object again from its keyframe's appearance), fine_share (the stage's share of the keyframe masks
in parts too fine to propagate) and j_ceiling_fine (the J left if exactly those parts of the truth are lost).
Warning quality over the DAVIS runs of both protocols: precision / recall of "warned" for "J < 0.7", with the
shipped weights (in-sample) and leave-one-sequence-out (the health model refit without the held-out sequence), for
the default setting and, with `--variants`, for every setting run. `--fit` prints weights refit on every run (to
paste into interreal/masks/health.py; they were fit with `--variants ours,ours-fast,baseline`).

    python recipes/bench_masks.py --quick --out bench/
    python recipes/bench_masks.py --out bench/

`--clicks`: the annotation effort in clicks instead (`recipes/bench_clicks.py`: a simulated user, NoC@85 / NoC@90 on
every 10th DAVIS frame and the laptop fixtures; `--video-rounds N`: the clicks to a whole video) -> masks_clicks.json.

    python recipes/bench_masks.py --clicks --video-rounds 8 --out bench/
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from bench_clicks import main_clicks
from benchlib import REPO, bench_args, print_table, scatter_chart, write_results

from interreal import atomic
from interreal.conventions import fid_of_index, frame_name
from interreal.masks import health as H
from interreal.paths import require_shared

THREADS = 2
BAD_J = 0.7                      # a sequence under this mean J is one the warning must catch
EFFORT = (1, 2, 5, 10, 20)       # keyframes per 100 frames
VARIANTS = {                     # extra command-line settings (speed / accuracy trade-offs)
    "ours": [],
    "ours-fast": ["--preset", "ultrafast", "--work-size", "320", "--cut", "0"],
    "ours-full": ["--preset", "medium", "--work-size", "0"],
    "baseline": ["--flow", "farneback", "--appearance", "0", "--rigid", "0", "--cut", "0", "--no-fusion", "--no-refine",
                 "--work-size", "0"],
}


def davis_sequences(quick: bool) -> list[str]:
    """Every sequence folder present (with images/ and masks/); --quick: the first two."""
    root = require_shared("davis2016")
    seqs = sorted(p.name for p in root.iterdir() if (p / "images").is_dir() and (p / "masks").is_dir())
    return seqs[:2] if quick else seqs


def davis_dataset(seq: str, root: Path, limit: int | None) -> tuple[Path, list[np.ndarray], list[str]]:
    """images/frame_%05d.png from the JPEGs (once), plus the truth as index maps."""
    src = require_shared("davis2016", seq)
    jpgs = sorted((src / "images").glob("*.jpg"))[:limit]
    pngs = sorted((src / "masks").glob("*.png"))[:limit]
    ds = root / f"davis-{seq}-{len(jpgs)}"
    if not (ds / "images").is_dir() or len(list((ds / "images").iterdir())) != len(jpgs):
        shutil.rmtree(ds, ignore_errors=True)
        for i, j in enumerate(jpgs):
            atomic.write_bytes(ds / "images" / f"{frame_name(i)}.png", cv2.imencode(".png", cv2.imread(str(j)))[1].tobytes())
    gts = [(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 127).astype(np.uint8) for p in pngs]
    return ds, gts, [seq]


def synth_dataset(root: Path, quick: bool) -> tuple[Path, list[np.ndarray], list[str], list[int]]:
    """The default simulated capture (smaller with --quick), decoded frame by frame from its H.264 video."""
    import av

    from interreal.synth import Capture, SynthConfig, write_capture

    cfg = SynthConfig(frames=90, width=320, height=240) if quick else SynthConfig()
    cap_dir = root / f"synth-{cfg.frames}-{cfg.width}"
    if not (cap_dir / "video.mp4").exists():
        write_capture(cfg, cap_dir, progress=True)
    cap = Capture.open(cap_dir)
    ds = root / f"synth-ds-{cfg.frames}-{cfg.width}"
    if not (ds / "images").is_dir() or len(list((ds / "images").iterdir())) != cfg.frames:
        shutil.rmtree(ds, ignore_errors=True)
        with av.open(str(cap_dir / "video.mp4")) as c:
            for i, fr in enumerate(c.decode(video=0)):
                atomic.write_image(ds / "images" / f"{frame_name(i)}.png", fr.to_ndarray(format="rgb24"))
    gts = [cv2.imread(str(cap_dir / "gt" / "instance" / f"{fid_of_index(i)}.png"), cv2.IMREAD_GRAYSCALE)
           for i in range(cfg.frames)]
    return ds, gts, list(cap.names), list(cap.keyframes)


def write_keyframes(folder: Path, gts: list[np.ndarray], keys: list[int], names: list[str]) -> None:
    shutil.rmtree(folder, ignore_errors=True)
    for k in keys:
        m = gts[k].copy()
        m[m == 255] = 0  # an occluder is background to the annotator
        atomic.write_image(folder / f"{fid_of_index(k)}.png", m)
    atomic.write_yaml(folder / "mapping.yaml", dict(enumerate(names)))


def frame_j(ds: Path, gts: list[np.ndarray], n_obj: int) -> np.ndarray:
    """(frames, objects) Jaccard of the written masks (both empty counts as 1; 255 in the truth is ignored)."""
    out = np.ones((len(gts), n_obj))
    for i, gt in enumerate(gts):
        pred = np.load(ds / "masks" / f"{fid_of_index(i)}.npy")
        valid = gt != 255
        for k in range(n_obj):
            p, g = pred[..., k] & valid, gt == k + 1
            u = (p | g).sum()
            out[i, k] = (p & g).sum() / u if u else 1.0
    return out


def run_command(ds: Path, kdir: Path, extra: list[str], suggest: int, reuse: bool = False) -> float:
    """The whole `interreal masks` command in a fresh process; returns its wall time (start-up to exit). `reuse`:
    keep what the last run left for the next (DS/cache: the stretches no keyframe change touched, the transient
    layer), as a user's next round does; otherwise every run starts from nothing."""
    if not reuse:
        shutil.rmtree(ds / "cache", ignore_errors=True)
    shutil.rmtree(ds / "masks", ignore_errors=True)
    shutil.rmtree(ds / "reports", ignore_errors=True)
    (ds / "mapping.yaml").unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "interreal", "masks", str(ds), "--keyframes", str(kdir), "--quiet",
           "--suggest", str(suggest), *extra]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stdout}\n{proc.stderr}")
    return wall


def run_one(data: str, ds: Path, gts, names, keys: list[int], setting: str, variant: str, work: Path,
            suggest: int = 5) -> dict:
    kdir = work / f"keys-{data}"
    write_keyframes(kdir, gts, keys, names)
    wall = run_command(ds, kdir, VARIANTS[variant], suggest)
    rep = json.loads((ds / "reports" / "masks.json").read_text())
    fig = rep["figures"]
    j = frame_j(ds, gts, len(names))
    free = np.ones(len(gts), bool)
    free[keys] = False
    per_obj = j[free].mean(0) if free.any() else np.ones(len(names))
    causes = {w.get("cause") for w in rep.get("warnings", [])}
    worst = {n: [(int(i), round(float(j[i, k]), 3)) for i in np.argsort(j[:, k]) if free[i]][:5]
             for k, n in enumerate(names)}
    fine = fig["fine_parts"]
    return {"data": data, "setting": setting, "variant": variant, "keyframes": len(keys),
            "keyframes_per_100": round(100 * len(keys) / len(gts), 2), "frames": len(gts), "objects": len(names),
            "j_mean": round(float(per_obj.mean()), 4), "j_worst_object": round(float(per_obj.min()), 4),
            "wall_s": round(wall, 2), "s_per_frame": round(wall / len(gts), 4), "fps": round(len(gts) / wall, 2),
            "stage_fps": fig["fps"], "width": int(gts[0].shape[1]), "height": int(gts[0].shape[0]),
            "warned": "masks-unreliable" in causes, "lost_warned": "object-lost" in causes,
            "predicted_j": round(float(min(fig["confidence_mean"].values())), 4),  # worst object, as warned
            "lost": {n: fig["health"][n]["lost"] for n in names},
            # frames where the stage found a collapsed object again (interreal/masks/redetect.py)
            "redetected": {n: (fig.get("redetected") or {}).get(n, []) for n in names},
            "suggested": fig["suggested_frames"],
            # the stage's share of each keyframe mask too fine to propagate, and the J the truth's own fine parts
            # leave at most (every propagated frame's truth without them, the rest perfect)
            "fine_share": round(max(fine["share"].values()), 4),
            "j_ceiling_fine": round(fine_ceiling(gts, free, len(names), (fine["width_px"] - 1) // 2), 4),
            "per_object": "; ".join(f"{n}={v:.3f}" for n, v in zip(names, per_obj)),
            "worst_frames": worst,
            # per frame, for the leave-one-sequence-out check of the warning
            "_frames": {"j": j.round(4).tolist(), "key": (~free).tolist(),
                        "cues": {n: fig["cues"][n] for n in names}}}


def fine_ceiling(gts: list[np.ndarray], free: np.ndarray, n_obj: int, radius: int) -> float:
    """Mean J over the propagated frames (per object, then over objects) of masks that are perfect except for the
    parts of the truth narrower than 2 radius + 1 px (`health.fine_share`), which propagation loses."""
    per_obj = [np.mean([1.0 - H.fine_share(gts[i] == k + 1, radius) for i in np.nonzero(free)[0]]) if free.any() else 1.0
               for k in range(n_obj)]
    return float(np.mean(per_obj))


def effort_curve(seq: str, ds: Path, gts, names, work: Path, first: dict, every10: dict | None) -> list[dict]:
    """Mean J against keyframes per 100 frames; keyframes after the first go where the stage suggests."""
    n = len(gts)
    out, keys, last = [], [0], first
    for level in EFFORT:
        target = max(1, min(n, round(level * n / 100)))
        if target > len(keys):
            for fid in last["suggested"]:
                if len(keys) < target and int(fid) not in keys:
                    keys.append(int(fid))
            while len(keys) < target:  # fewer suggestions than needed: split the widest gap
                ks = sorted(keys)
                a, b = max(zip(ks, ks[1:] + [n]), key=lambda g: g[1] - g[0])
                keys.append((a + b) // 2)
            keys = sorted(set(keys))
            last = run_one(seq, ds, gts, names, keys, f"effort{level}", "ours", work,
                           suggest=max(1, round(EFFORT[-1] * n / 100) - len(keys)))
        out.append({**last, "setting": f"effort{level}", "effort_level": level})
    return out


def loo_warning(runs: list[dict]) -> dict:
    """Precision / recall of the warning for 'mean J < BAD_J' over the DAVIS protocol runs: as the stage shipped
    it, and with the health model refit leave-one-sequence-out (on the protocol runs of the other sequences, every
    variant run, the set the shipped weights were fit on: `--variants ours,ours-fast,baseline --fit`). Figures for
    the default setting ("ours") and, where other variants ran, for every setting together."""
    davis = [r for r in runs if r["data"] != "synth" and r["setting"] in ("first", "every10")]
    train = davis

    def inputs(r):
        """Per object: (features (n, F), area, ref area, expected, keyframe, J per frame)."""
        key = np.array(r["_frames"]["key"])
        j = np.array(r["_frames"]["j"])
        for k, c in enumerate(r["_frames"]["cues"].values()):
            f = np.stack([np.array(c[name], float) for name in H.FEATURES], -1)
            yield f, np.array(c["area_share"]), np.array(c["ref_share"]), np.array(c["expected"], bool), key, j[:, k]

    def means(rs):
        xs, ys = [], []
        for r in rs:
            for f, *_, key, j in inputs(r):
                xs.append(f[~key].mean(0))
                ys.append(j[~key].mean())
        return np.array(xs), np.array(ys)

    def predicted(r, w):
        return min(float(H.assess(f[:, None], a[:, None], ref[:, None], e[:, None], key, w).mean_predicted(key)[0])
                   for f, a, ref, e, key, _ in inputs(r))

    def pr(pred: list[bool], truth: list[bool]) -> dict:
        tp = sum(p and t for p, t in zip(pred, truth))
        return {"precision": round(tp / sum(pred), 3) if sum(pred) else None,
                "recall": round(tp / sum(truth), 3) if sum(truth) else None,
                "warned": sum(pred), "bad": sum(truth), "runs": len(truth)}

    truth = [r["j_worst_object"] < BAD_J for r in davis]
    ours = [r["variant"] == "ours" for r in davis]

    def both(pred: list[bool]) -> dict:
        """pr over the default setting's runs, and over every setting's where others ran."""
        out = pr([p for p, o in zip(pred, ours) if o], [t for t, o in zip(truth, ours) if o])
        return out if all(ours) else {**out, "all_settings": pr(pred, truth)}

    out = {"shipped": both([r["warned"] for r in davis]),
           "shipped_any_warning": both([r["warned"] or r["lost_warned"] for r in davis])}
    loo_pred, detail = [], []
    for r in davis:
        w = H.fit(*means([x for x in train if x["data"] != r["data"]]))
        p = predicted(r, w)
        loo_pred.append(p < H.WARN_J)
        detail.append({"data": r["data"], "setting": r["setting"], "variant": r["variant"], "j": r["j_mean"],
                       "predicted_loo": round(p, 3), "predicted_shipped": r["predicted_j"]})
    out["leave_one_out"] = both(loo_pred)
    out["leave_one_out_runs"] = detail
    out["weights_all"] = [round(float(v), 3) for v in H.fit(*means(train))]
    return out


def main() -> int:
    def extra(p):
        p.add_argument("--no-synth", action="store_true", help="DAVIS only")
        p.add_argument("--no-effort", action="store_true", help="skip the annotation-effort curve")
        p.add_argument("--variants", default="ours", help=f"comma-separated settings of the command to compare "
                       f"on the two protocols (default ours; all: {','.join(VARIANTS)})")
        p.add_argument("--only", default="", help="comma-separated DAVIS sequences (default: every one present)")
        p.add_argument("--fit", action="store_true", help="print the health model's weights refit on every run")
        p.add_argument("--clicks", action="store_true", help="the annotation effort in clicks (bench_clicks.py)")
        p.add_argument("--video-rounds", type=int, default=0, metavar="N",
                       help="with --clicks: clicks to a whole video, at most N keyframes a sequence (0: skip)")
        p.add_argument("--video-budget", type=int, default=200, help="with --clicks: at most this many clicks a video")
    args = bench_args("masks", __doc__.splitlines()[0], extra)
    cv2.setNumThreads(THREADS)
    if args.clicks:
        return main_clicks(args, davis_sequences, davis_dataset, run_command, frame_j, REPO / "tests" / "fixtures" /
                           "laptop" / "keyframes")
    work = args.out / "_masks_work"
    limit = 20 if args.quick else None
    vs = list(VARIANTS) if args.variants == "all" else args.variants.split(",")
    unknown = set(vs) - set(VARIANTS)
    if unknown:
        raise SystemExit(f"unknown variant(s) {sorted(unknown)}; choose from {sorted(VARIANTS)}")
    seqs = args.only.split(",") if args.only else davis_sequences(args.quick)
    runs: list[dict] = []
    curves: dict[str, list[dict]] = {}
    for seq in seqs:
        ds, gts, names = davis_dataset(seq, work, limit)
        for vname in vs:
            first = run_one(seq, ds, gts, names, [0], "first", vname, work,
                            suggest=max(1, round(EFFORT[-1] * len(gts) / 100) - 1))
            every = run_one(seq, ds, gts, names, list(range(0, len(gts), 10)), "every10", vname, work)
            runs += [first, every]
            print(f"  {seq} {vname}: J first {first['j_mean']:.3f} (warned {first['warned']}, predicted "
                  f"{first['predicted_j']:.2f}), every10 {every['j_mean']:.3f} (warned {every['warned']}, predicted "
                  f"{every['predicted_j']:.2f}), {first['fps']:.1f} / {every['fps']:.1f} frames/s", file=sys.stderr)
            if vname == "ours" and not args.no_effort:
                curve = curves[seq] = effort_curve(seq, ds, gts, names, work, first, every)
                runs += [r for r in curve if r["keyframes"] > 1]  # one keyframe: the `first` run itself
                print(f"  {seq} effort: " + ", ".join(f"{r['effort_level']}/100 -> {r['j_mean']:.3f}" for r in curve),
                      file=sys.stderr)
    if not args.no_synth:
        ds, gts, names, keys = synth_dataset(work, args.quick)
        runs.append(run_one("synth", ds, gts, names, keys, "synth60", "ours", work))
        print(f"  synth: J {runs[-1]['j_mean']:.3f} ({runs[-1]['per_object']})", file=sys.stderr)
    # the per-frame figures first: an hour of runs is kept whatever the summary below does
    atomic.write_json(args.out / "masks_frames.json",
                      [{"data": r["data"], "setting": r["setting"], "variant": r["variant"], **r["_frames"]} for r in runs])
    summary = summarise(runs, seqs, curves)
    warning = loo_warning(runs) if len({r["data"] for r in runs if r["data"] != "synth"}) > 1 else {}
    summary["warning"] = {k: v for k, v in warning.items() if k != "leave_one_out_runs"}
    if args.fit:
        print("weights refit on every run:", warning.get("weights_all"))
    targets = {"davis first frame only j_mean": 0.75, "davis keyframe every 10 j_mean": 0.92,
               "whole command fps": 15, "synth keyframes every 60, each object": 0.93,
               "warning precision and recall (J < 0.7)": 0.9}
    for r in runs:
        r.pop("_frames")
    write_results(args.out, "masks", runs, quick=args.quick, threads=THREADS, targets=targets, summary=summary,
                  warning_runs=warning.get("leave_one_out_runs", []),
                  note="every run is the whole `interreal masks` command (start-up, previews, writing) on a shared "
                       "2-core machine: times are pessimistic")
    scatter_chart(args.out / "masks.png", chart_points(runs, summary), "s_per_frame", "j_mean",
                  label=lambda r: r["label"],
                  xlabel="seconds per frame, whole `interreal masks` command",
                  ylabel="J (mean over sequences)", title="interreal masks: accuracy vs time, every setting")
    print_table(runs, ["data", "setting", "variant", "keyframes", "j_mean", "j_ceiling_fine", "predicted_j", "warned",
                       "lost_warned", "fps", "s_per_frame", "per_object"], title="masks")
    print(json.dumps(summary, indent=1))
    return 0


def chart_points(runs: list[dict], summary: dict) -> list[dict]:
    """One point per setting: mean J and mean seconds per frame over the sequences (the effort curve joined)."""
    pts = []
    for (setting, variant) in sorted({(r["setting"], r["variant"]) for r in runs if not r["setting"].startswith("effort")}):
        rs = [r for r in runs if r["setting"] == setting and r["variant"] == variant]
        pts.append({"label": setting + ("" if variant == "ours" else f" {variant}"), "group": "protocols",
                    "j_mean": float(np.mean([r["j_mean"] for r in rs])),
                    "s_per_frame": float(np.mean([r["s_per_frame"] for r in rs]))})
    for c in summary.get("effort_curve", []):
        pts.append({"label": f"{c['keyframes_per_100_asked']}/100", "group": "effort (suggested keyframes)",
                    "j_mean": c["j_mean"], "s_per_frame": c["s_per_frame"]})
    return pts


def summarise(runs: list[dict], seqs: list[str], curves: dict[str, list[dict]]) -> dict:
    """Means per setting over DAVIS, the effort curve, keyframes each sequence needs for J >= 0.9, the synth."""
    out: dict = {"sequences": seqs}
    ours = [r for r in runs if r["variant"] == "ours"]
    if curves:
        out["effort_curve"] = [{"keyframes_per_100_asked": level,
                                "keyframes_per_100": round(float(np.mean([c[i]["keyframes_per_100"] for c in curves.values()])), 2),
                                "j_mean": round(float(np.mean([c[i]["j_mean"] for c in curves.values()])), 4),
                                "s_per_frame": round(float(np.mean([c[i]["s_per_frame"] for c in curves.values()])), 4)}
                               for i, level in enumerate(EFFORT)]
    for s in ("first", "every10", "synth60"):
        rs = [r for r in ours if r["setting"] == s]
        if not rs:
            continue
        out[s] = {"j_mean": round(float(np.mean([r["j_mean"] for r in rs])), 4),
                  "keyframes_per_100": round(float(np.mean([r["keyframes_per_100"] for r in rs])), 2),
                  "fps_whole_command": round(sum(r["frames"] for r in rs) / sum(r["wall_s"] for r in rs), 2),
                  "j_ceiling_fine": round(float(np.mean([r["j_ceiling_fine"] for r in rs])), 4),
                  "sequences": len(rs)}
    need = {}
    for seq in seqs:
        ok = sorted((r["keyframes_per_100"], r["keyframes"]) for r in ours if r["data"] == seq and r["j_mean"] >= 0.9)
        need[seq] = ok[0][1] if ok else None
    out["keyframes_for_j_0.9"] = need
    synth = [r for r in ours if r["data"] == "synth"]
    if synth:
        out["synth60"]["per_object"] = synth[0]["per_object"]
    return out


if __name__ == "__main__":
    sys.exit(main())
