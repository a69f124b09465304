"""Part motions: each route of `interreal motions` alone, and the stage, against the simulator's true motions.

Simulated captures (seeds; 150 frames 480x360 by default) go through `interreal process` without motions; then,
per part, each route is run on its own (sfm: the part's own reconstruction; pnp: known-camera PnP; silhouette: the
part's masks against the known cameras; edge: the static edge of its keyframes' outlines as a hinge) and the whole stage (routes in order until one is accepted). Per part and
route: the kind, the axis and range error against the truth, the state RMSE over the frames it measured (against the
simulator's states), accepted or the reason it was not, seconds. The drawers of seeds 4 and 6 are the plain parts
SfM and PnP cannot follow.

    python recipes/bench_motions.py --out bench/                 # seeds 1-6
    python recipes/bench_motions.py --quick --out bench/         # seeds 4 and 6, 90 frames
    python recipes/bench_motions.py --quick --hard --seeds 1,2,3,4,5,6,7,8,9,10 --out bench/  # plain parts, drift
    python recipes/bench_motions.py --quick --hard --true-masks --routes edge,stage --out bench/  # routes' ceiling

`--eyeballed 0.5` moves every label between the ends by up to 0.5, as a person eyeballing the part would (the issue's
bar: such labels never stop a measured motion).

`--true-masks` gives every route the simulator's own masks in place of the propagated ones: what the motion routes
can do with perfect masks, apart from what propagation loses. `--follow N` annotates the frames the masks stage asks
for next (with the truth) until the capture has N keyframes, as a user who follows its advice would; `--draw-asked`
annotates the frames the motions stage asks for where an end of a motion is the labels' guess, then measures again.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from benchlib import bench_args, print_table, write_results

ROUTE_NAMES = ("sfm", "pnp", "silhouette", "edge", "prism", "stage")


HARD = {"furniture": "plain", "exposure_drift": 0.2, "noise": 3.0, "occluder": 0.3, "arm": True}  # --hard: as real captures are


def make_dataset(root: Path, seed: int, frames: int, size: tuple[int, int], **synth) -> tuple[Path, Path]:
    """Capture -> processed dataset (frames, masks from the capture's keyframes, poses, labels), once; `synth`:
    more `SynthConfig` settings (they name the work folder)."""
    from interreal.process import process
    from interreal.synth import SynthConfig, write_capture

    tag = "-".join(f"{k}={v}" for k, v in sorted(synth.items()))
    cap, ds = root / f"s{seed}{'-' + tag if tag else ''}" / "cap", root / f"s{seed}{'-' + tag if tag else ''}" / "ds"
    if not (cap / "video.mp4").exists():
        write_capture(SynthConfig(frames=frames, width=size[0], height=size[1], seed=seed, **synth), cap,
                      progress=False)
    if not (ds / "transforms.json").exists():
        process(cap / "video.mp4", ds, keyframes=cap / "annotations" / "keyframes",
                labels=cap / "annotations" / "states.yaml", motions=False)
    return cap, ds


def follow_suggestions(cap: Path, ds: Path, keyframes: int, paint: bool) -> tuple[Path, list[str]]:
    """A copy of the dataset whose masks come from the capture's keyframes plus the frames the masks stage asks for
    next, annotated with the simulator's truth as a careful person would (the arm and person as background, or
    painted with `paint`), one at a time until there are `keyframes`; each round re-runs `interreal masks` (only the
    gaps the new keyframe touches). The poses are the dataset's. Returns the copy and the frames added."""
    import shutil

    import cv2

    from interreal import atomic
    from interreal.masks import propagate
    from interreal.synth.capture import annotation_index

    out, kdir = ds.parent / f"ds_follow{keyframes}", ds.parent / f"keys_follow{keyframes}"
    if not out.exists():
        shutil.copytree(ds, out)
    if not kdir.exists():
        shutil.copytree(cap / "annotations" / "keyframes", kdir)
    added: list[str] = []
    while True:
        fig = propagate(out, kdir, progress=False, preview="none")
        have = {p.stem for p in kdir.glob("*.png")}
        picks = [f for f in fig.get("suggested_frames", []) if f not in have]
        if len(have) >= keyframes or not picks:
            return out, added
        inst = cv2.imread(str(cap / "gt" / "instance" / f"{int(picks[0]):05d}.png"), cv2.IMREAD_UNCHANGED)
        atomic.write_image(kdir / f"{picks[0]}.png", annotation_index(inst, paint_occluders=paint))
        added.append(picks[0])


def draw_asked(cap: Path, ds: Path, fids: list[str]) -> Path:
    """A copy of the dataset whose masks come from the capture's keyframes plus the frames `interreal motions` asked
    a person to draw (where an end of a motion was the labels' guess), annotated with the simulator's truth as a
    careful person would; `interreal masks` re-run on it, the poses kept."""
    import shutil

    import cv2

    from interreal import atomic
    from interreal.masks import propagate
    from interreal.synth.capture import annotation_index

    out, kdir = ds.parent / "ds_drawn", ds.parent / "keys_drawn"
    for d in (out, kdir):
        if d.exists():
            shutil.rmtree(d)
    shutil.copytree(ds, out)
    shutil.copytree(cap / "annotations" / "keyframes", kdir)
    for fid in fids:
        inst = cv2.imread(str(cap / "gt" / "instance" / f"{int(fid):05d}.png"), cv2.IMREAD_UNCHANGED)
        atomic.write_image(kdir / f"{fid}.png", annotation_index(inst))
    propagate(out, kdir, progress=False, preview="none")
    return out


def score(motion, fig: dict[str, Any], truth, true_states: np.ndarray) -> dict[str, Any]:
    """The motion against the truth (None: what the route said)."""
    if motion is None:
        return {"kind": None, "accepted": False, "reason": fig.get("silhouette_reason") or fig.get("reason")}
    rows = np.array(fig.get("frame_states") or np.zeros((0, 2)))
    rmse = float(np.sqrt(np.mean((rows[:, 1] - true_states[rows[:, 0].astype(int)]) ** 2))) if len(rows) else None
    return {"kind": motion.kind, "axis_deg": round(float(np.degrees(np.arccos(min(1.0, abs(motion.axis @ truth.axis))))), 2),
            "range_error": round(abs(motion.range - truth.range) / truth.range, 4) if motion.kind == truth.kind else None,
            "state_rmse": None if rmse is None else round(rmse, 3), "measured_frames": len(rows),
            "accepted": bool(fig.get("accepted")), "reason": fig.get("reason") or None}


def true_masks(ds, cap: Path) -> None:
    """The dataset's masks replaced, in memory, by the simulator's instance maps (object k = instance k + 1), all
    trusted, and its transient layer by the simulator's occluders (the person and the arm, instance 255)."""
    import cv2
    from interreal.conventions import frame_index
    from interreal.motions import part, silhouette

    def occluders(root, fid: str, hw: tuple[int, int]) -> np.ndarray:
        inst = cv2.imread(str(cap / "gt" / "instance" / f"{frame_index(fid):05d}.png"), cv2.IMREAD_UNCHANGED)
        return cv2.resize((inst == 255).astype(np.uint8), hw[::-1], interpolation=cv2.INTER_NEAREST) > 0

    silhouette.has_transients = lambda root: True
    silhouette.read_transient = occluders
    part.mask_confidence = lambda ds, obj: None  # the propagated masks' confidence says nothing of the truth
    own = ds.load_mask

    def load(f):
        inst = cv2.imread(str(cap / "gt" / "instance" / f"{f.index:05d}.png"), cv2.IMREAD_UNCHANGED)
        m = own(f).copy()
        for k in range(m.shape[-1]):
            m[..., k] = cv2.resize((inst == k + 1).astype(np.uint8), m.shape[1::-1], interpolation=cv2.INTER_NEAREST) > 0
        return m

    ds.load_mask = load


def mask_j(ds_path: Path, cap: Path, keyframes: set[int]) -> list[float]:
    """Per object, the mean J of the dataset's masks against the simulator's instance maps over the frames that are
    not keyframes (where the object is in either): what the routes measure from."""
    import cv2
    from interreal.conventions import mask_file
    from interreal.dataset import load_dataset

    ds = load_dataset(ds_path)
    vals: list[list[float]] = [[] for _ in ds.object_names]
    for f in ds.frames:
        if f.index in keyframes:
            continue
        inst = cv2.imread(str(cap / "gt" / "instance" / f"{f.index:05d}.png"), cv2.IMREAD_UNCHANGED)
        masks = np.load(mask_file(ds_path, f.fid))
        for k in range(len(vals)):
            truth = cv2.resize((inst == k + 1).astype(np.uint8), masks.shape[1::-1], interpolation=cv2.INTER_NEAREST) > 0
            union = (truth | masks[..., k]).sum()
            if union:
                vals[k].append(float((truth & masks[..., k]).sum() / union))
    return [round(float(np.mean(v)), 3) if v else float("nan") for v in vals]


def eyeball(labels: np.ndarray, given: np.ndarray, seed: int, spread: float) -> np.ndarray:
    """The labels as a person eyeballing the part would give them: the ends (closed 0, fully open 1) right, every
    state between moved by up to `spread` (uniform, seeded), kept strictly between the ends. Why: a real capture's
    labels are guesses (a half-open drawer called 0.85 where it measured 0.38); the geometry must not follow them."""
    rng = np.random.default_rng(seed)
    out = labels.copy()
    inner = given & (labels > 0.02) & (labels < 0.98)
    out[inner] = np.clip(labels[inner] + rng.uniform(-spread, spread, int(inner.sum())), 0.05, 0.95)
    return out


def run_part(ds_path: Path, cap: Path, o: int, route: str, truth_masks: bool = False,
             eyeballed: float = 0.0, seed: int = 0) -> dict[str, Any]:
    from interreal.motions import part as motions
    from interreal.dataset import known_states, load_dataset
    from interreal.sfm import colmap
    from interreal.synth.truth import truth_articulation

    ds = load_dataset(ds_path)
    if truth_masks:
        true_masks(ds, cap)
    name = ds.object_names[o]
    labels, given = ds.label_matrix()
    if eyeballed:
        labels = eyeball(labels, given, seed, eyeballed)
    times = np.array([f.index for f in ds.frames], float)
    states, known = known_states(times, labels, given)
    gt = json.loads((cap / "gt" / "states.json").read_text())
    true_states = np.array(gt["values"])[:, gt["objects"].index(name)][times.astype(int)]
    truth = truth_articulation(cap, ds_path)[name]
    part = ds_path / "motions" / f"object_{o}"
    cfg = motions.MotionConfig()
    names = motions.part_masks(ds, o, part / "masks", cfg, keep=set(np.flatnonzero(given[:, o]).tolist())).names
    t0 = time.perf_counter()
    motion, fig = motions.measure_part(colmap.load_pycolmap(False), ds, names, part, states[:, o], known[:, o], cfg,
                                       labelled=given[:, o], obj=o, routes=None if route == "stage" else (route,))
    said = [v.get("reason") for v in fig.get("routes", {}).values() if v.get("reason")]
    if motion is None and said:
        fig = dict(fig, reason="; ".join(said))
    out = {"part": name, "true_kind": truth.kind, "route": route, **score(motion, fig, truth, true_states),
           "seconds": round(time.perf_counter() - t0, 1)}
    if route == "stage":
        out["route_used"] = next((r for r, v in fig.get("routes", {}).items() if v["accepted"]), None)
        out["draw_asked"] = [ds.frames[i].fid for i in fig.get("draw_frames") or []]
    return out


def main() -> int:
    def extra(p):
        p.add_argument("--seeds", default=None, help="simulator seeds (comma-separated; default 1-6, quick 4 and 6)")
        p.add_argument("--routes", default=",".join(ROUTE_NAMES), help="routes to run alone, and 'stage'")
        p.add_argument("--hard", action="store_true", help="captures as hard as real ones: plain painted furniture "
                                                            "and parts, exposure drift, sensor noise, a person "
                                                            f"walking across ({HARD})")
        p.add_argument("--true-masks", action="store_true", help="the simulator's own masks in place of the "
                                                                  "propagated ones (the routes' ceiling)")
        p.add_argument("--paint-occluders", action="store_true", help="the keyframes paint the person and the arm "
                                                                       "as the ignore class (the transient layer)")
        p.add_argument("--follow", type=int, default=0, metavar="N",
                       help="the masks stage's suggested frames annotated (with the truth) until N keyframes, as a user "
                            "who follows its advice would (the masks re-made, the poses kept)")
        p.add_argument("--draw-asked", action="store_true",
                       help="the frames `interreal motions` asks a person to draw (where an end of a motion is the "
                            "labels' guess) annotated with the truth, the masks re-made, the motions measured again")
        p.add_argument("--eyeballed", type=float, default=0.0, metavar="SPREAD",
                       help="labels as a person eyeballs them: the ends right, every state between moved by up to "
                            "SPREAD (e.g. 0.5; seeded); the truth still scores")

    args = bench_args("motions", __doc__.splitlines()[0], extra)
    seeds = [int(s) for s in args.seeds.split(",")] if args.seeds else [4, 6] if args.quick else [1, 2, 3, 4, 5, 6]
    frames, size = (90, (480, 360)) if args.quick else (150, (480, 360))
    routes = [r for r in args.routes.split(",") if r]
    synth = dict(HARD if args.hard else {}, **({"paint_occluders": True} if args.paint_occluders else {}))
    runs = []
    for seed in seeds:
        cap, ds = make_dataset(args.out / "_motions_work", seed, frames, size, **synth)
        kdir = cap / "annotations" / "keyframes"
        if args.follow:
            ds, added = follow_suggestions(cap, ds, args.follow, args.paint_occluders)
            kdir = ds.parent / f"keys_follow{args.follow}"
            print(f"seed {seed}: keyframes added where the masks stage asked: {added or 'none (already there)'}")
        if args.draw_asked:  # the frames the stage asks for, drawn (with the truth), then the masks and motions again
            firsts = [run_part(ds, cap, o, "stage", args.true_masks, args.eyeballed, seed) for o in range(2)]
            runs += [{"seed": seed, **r, "route": "before drawing"} for r in firsts]  # the same table, before and after
            asked = sorted({f for r in firsts for f in r["draw_asked"]})
            print(f"seed {seed}: frames the motions stage asked to draw: {asked or 'none'}")
            if asked:
                ds, kdir = draw_asked(cap, ds, asked), ds.parent / "keys_drawn"
        js = mask_j(ds, cap, {int(p.stem) for p in kdir.glob("*.png")})
        print(f"seed {seed}: the masks' J over the frames between keyframes: {js}")
        for o in range(2):
            for route in routes:
                r = {"seed": seed, **run_part(ds, cap, o, route, args.true_masks, args.eyeballed, seed), "mask_j": js[o]}
                runs.append(r)
                print(f"seed {seed} {r['part']} {route}: {r['kind']} accepted={r['accepted']} axis {r.get('axis_deg')} "
                      f"range {r.get('range_error')} states {r.get('state_rmse')} {r.get('reason') or ''}", flush=True)
    print_table(runs, ["seed", "part", "true_kind", "route", "mask_j", "kind", "axis_deg", "range_error", "state_rmse",
                       "accepted", "route_used", "seconds", "reason"], "part motions against the simulator")
    summary = summarise(runs)
    print_table(summary, ["route", "part", "measured_right", "seeds", "worst_axis_deg", "worst_range_error",
                          "worst_state_rmse", "mask_j_worst_first"], f"measured right (the kind, axis <= {RIGHT_AXIS_DEG} deg, range within "
                                               f"{RIGHT_RANGE:.0%}), worst first")
    name = "motions" + ("_hard" if args.hard else "") + ("_true_masks" if args.true_masks else "") + \
        (f"_follow{args.follow}" if args.follow else "") + ("_drawn" if args.draw_asked else "") + \
        (f"_eyeballed{args.eyeballed:g}" if args.eyeballed else "")
    write_results(args.out, name, runs, frames=frames, size=list(size), seeds=seeds, synth=synth, summary=summary,
                  follow=args.follow, eyeballed=args.eyeballed, draw_asked=args.draw_asked)
    return 0


RIGHT_AXIS_DEG, RIGHT_RANGE = 3.0, 0.05  # the bar for a measured motion


def summarise(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per route and part: in how many seeds the used motion was right, and the worst figures over the seeds."""
    out = []
    for route in dict.fromkeys(r["route"] for r in runs):
        for part in dict.fromkeys(r["part"] for r in runs):
            rs = [r for r in runs if r["route"] == route and r["part"] == part]
            right = [r for r in rs if r["accepted"] and r["kind"] == r["true_kind"]
                     and r["axis_deg"] <= RIGHT_AXIS_DEG and (r["range_error"] or 0) <= RIGHT_RANGE]
            used = [r for r in rs if r["accepted"]]
            worst = lambda k: max((r[k] for r in used if r.get(k) is not None), default=None)  # noqa: E731
            out.append({"route": route, "part": part, "measured_right": len(right), "seeds": len(rs),
                        "mask_j_worst_first": sorted(r["mask_j"] for r in rs if r.get("mask_j") is not None),
                        "worst_axis_deg": worst("axis_deg"), "worst_range_error": worst("range_error"),
                        "worst_state_rmse": worst("state_rmse")})
    return sorted(out, key=lambda r: (r["route"] != "stage", r["measured_right"] / max(r["seeds"], 1)))


if __name__ == "__main__":
    raise SystemExit(main())
