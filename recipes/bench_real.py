"""Real-capture benchmark: the shared laptop video (a lid moved by a hand while the camera walks around it).

Data: ../shared/data/laptop/laptop_orbit.mp4 (240 frames, 1072x608, 10 fps) and our own annotations, committed as
small fixtures: tests/fixtures/laptop/keyframes/ (LabelMe polygons of the lid, and of the hand / person as the
"ignore" class, on 5 frames) and tests/fixtures/laptop/labels.yaml (eyeballed lid states on 5 frames; 0 = the
most closed the lid gets, 1 = the most open). Steps, each timed:
1. `interreal process VIDEO DS --keyframes K --labels L --no-motions` (frames, masks, poses, labels); the frames
   are a subsample (`--every`), the annotated ones always kept;
2. `interreal motions DS --route R` for each R of `--routes` (sfm: the lid's own reconstruction first; pnp: the lid
   triangulated at rest with the known cameras and located by PnP first) -> a hinge or a slide from the geometry;
   the two routes' axes and per-frame states are compared (`route_agreement`).
Per run: stage seconds, frames, registered frames, the lid's motion (kind, axis, angle range in degrees, frames
its reconstruction registered), the lid's state RMSE against our labels, labels flagged as likely mistakes, the
measured state of every registered frame (in the JSON), and the axis's angle to the scene's up (the hinge of a lid
is horizontal: about 90 degrees).

The eyeballed labels are off by up to 0.4 themselves, so the states are also checked against a careful reference
made without `interreal motions` (`recipes/hinge_reference.py`: the lid's top corners marked in every frame,
tests/fixtures/laptop/lid_corners.json, and one bundle adjustment of a hinged pair of points on this dataset's
cameras): `ref_rmse` over every frame both measured, `ref_rmse_labelled` on the labelled ones, `ref_max`, and the
reference's own figures (its range, reprojection error, `point_spread`: the RMS difference between the states
each corner gives alone). On synthetic marks with 0.5 px noise the reference's states are within 0.015 RMS
(tests/test_hinge_reference.py).

    python recipes/bench_real.py --quick --out bench/      # every 4th frame at 800 px: a few minutes on 2 cores
    python recipes/bench_real.py --out bench/              # every 2nd frame at full size (1072 px)

`--train-minutes N` then trains (cpu preset, N minutes) with the first route's motion and adds held-out PSNR / SSIM
(`livescene eval`, 8 frames) and, per held-out camera, the share of the lid's pixels whose rendered colour changes
between states 0 and 1, and whether the hand shows (`hand_shows`: PSNR against the captured frames inside the
transient layer's pixels and elsewhere; a scene that baked the hand in reproduces it there).

`--transients auto` runs it with nothing painted but the lid (the keyframes' hand and person shapes dropped) and the
transient layer from `--transients auto`; `--transients none` with neither.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from benchlib import REPO, bench_args, print_table, write_results

from interreal.conventions import frame_index
from interreal.paths import require_shared

FIXTURES = REPO / "tests" / "fixtures" / "laptop"
PART = "laptop lid"


def _extra(p) -> None:
    p.add_argument("--every", type=int, default=None, help="one frame per EVERY source frames (default 2, quick 4)")
    p.add_argument("--long-side", type=int, default=None, help="image long side (default 1072, quick 800)")
    p.add_argument("--threads", type=int, default=2, help="COLMAP threads (default 2)")
    p.add_argument("--train-threads", type=int, default=0, help="`livescene train --threads` (default 0: the trainer "
                   "measures; a fixed 2 on a busy machine trained 2.5x slower than 1)")
    p.add_argument("--reuse", action="store_true", help="keep an existing OUT/real_ds (re-measure motions only)")
    p.add_argument("--train-minutes", type=float, default=0.0, help="then train this long (cpu preset) and measure "
                   "held-out PSNR / SSIM and the lid's pixel change between states 0 and 1 (default 0: skip)")
    p.add_argument("--transients", default="painted", choices=("painted", "auto", "none"),
                   help="the hand and the person: painted on the fixture keyframes (default), found by "
                        "`--transients auto` with nothing painted, or neither (the baseline that bakes them in)")
    p.add_argument("--routes", default="sfm,pnp", help="`interreal motions --route` values to run (the route tried "
                   "first: sfm, the part's own SfM; pnp, known-camera PnP); default sfm,pnp")


def objects_only(keyframes: Path, out: Path) -> Path:
    """A copy of LabelMe keyframes without their ignore-class shapes (hand, person): nothing painted but objects."""
    from interreal.transients import is_ignore_label

    out.mkdir(parents=True, exist_ok=True)
    for src in sorted(keyframes.glob("*.json")):
        doc = json.loads(src.read_text())
        doc["shapes"] = [s for s in doc["shapes"] if not is_ignore_label(s["label"], [PART])]
        (out / src.name).write_text(json.dumps(doc))
    return out


def run_process(video: Path, ds: Path, every: int, long_side: int, transients: str = "painted") -> dict:
    """Frames, masks, poses and labels; per-stage seconds from reports/process.json. transients: painted (the
    fixture keyframes as they are, no auto layer), auto (their objects only, `--transients auto`) or none."""
    from interreal.process import process

    keys = FIXTURES / "keyframes" if transients == "painted" else objects_only(FIXTURES / "keyframes",
                                                                               ds.parent / "keyframes_objects")
    t0 = time.perf_counter()
    fig = process(video, ds, keyframes=keys, labels=FIXTURES / "labels.yaml", every=every,
                  long_side=long_side, motions=False, transients="auto" if transients == "auto" else "off")
    steps = json.loads((ds / "reports" / "process.json").read_text()).get("steps", {})
    return {"process_s": round(time.perf_counter() - t0, 1), "registered": fig.get("registered"),
            "frames": fig.get("total"), **{f"{k}_s": round(v.get("wall_s", 0.0), 1) for k, v in steps.items()}}


def up_angle_deg(axis: list[float]) -> float:
    """Angle between the axis and the scene's up (+Z: `interreal poses` orients the world so, "vertical"): a
    laptop's hinge lies flat, about 90."""
    return round(float(np.degrees(np.arccos(min(1.0, abs(float(axis[2])) / float(np.linalg.norm(axis)))))), 1)


def run_motions(ds: Path, threads: int, route: str) -> dict:
    """`estimate_motions` timed; the lid's figures from reports/motions.json and articulation.json."""
    from interreal.motions import estimate_motions

    t0 = time.perf_counter()
    fig = estimate_motions(ds, force=True, num_threads=threads, route=route)
    wall = round(time.perf_counter() - t0, 1)
    rep = json.loads((ds / "reports" / "motions.json").read_text())
    st = rep["steps"].get("object 0", {})
    arts = ds / "articulation.json"
    art = json.loads(arts.read_text())["objects"].get(PART) if arts.exists() else None
    kind = st.get("kind")
    out = {"route": st.get("route"), "motions_s": wall, "part_frames": st.get("frames_shown"),
           "part_registered": st.get("registered"), "kind": kind, "used": art is not None, "reason": st.get("reason"),
           "turn_deg": st.get("turn_deg"), "rot_noise_deg": st.get("rot_noise_deg"),
           "state_rmse": st.get("state_rmse_from_pose"), "flagged": len(st.get("flagged_labels") or []),
           "attempts": st.get("attempts"), "warnings": [w.get("message") for w in rep.get("warnings", [])]}
    if art is not None:
        out.update(axis=[round(v, 3) for v in art["axis"]], axis_to_up_deg=up_angle_deg(art["axis"]),
                   range=round(art["range"], 4),
                   range_deg=round(float(np.degrees(art["range"])), 1) if kind == "hinge" else None)
    out.update(end_states=st.get("end_states"), label_check=st.get("label_check"),
               frame_states=st.get("frame_states"), measured=fig.get("measured"))
    return out


def run_training(ds: Path, out: Path, minutes: float, threads: int) -> dict:
    """`livescene train` for `minutes` (cpu preset, the measured motion in articulation.json), `livescene eval` on
    8 held-out frames, and from each held-out camera the share of the lid's pixels (its mask there) whose colour
    changes between the state-0 and state-1 renders (a part that really moves changes most of its pixels)."""
    import subprocess
    import sys

    import shutil

    run = out / "real_run"
    shutil.rmtree(run, ignore_errors=True)  # a fresh run each time (train refuses an existing run folder)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "livescene", "train", str(ds), "--out", str(run), "--preset", "cpu",
                    "--max-minutes", str(minutes), "--steps", "1000000",  # the time binds, not the preset's steps
                    "--threads", str(threads), "--no-progress"], check=True)
    train_s = round(time.perf_counter() - t0, 1)
    subprocess.run([sys.executable, "-m", "livescene", "eval", str(run), "--out", str(out / "real_eval.json"),
                    "--max-frames", "8"], check=True)
    ev = json.loads((out / "real_eval.json").read_text())
    flat = {k: v for k, v in ev.items() if isinstance(v, (int, float))}
    return {"train_s": train_s, "steps": ev.get("step"),
            **{k: flat[k] for k in sorted(flat) if "psnr" in k or "ssim" in k or "state_mae" in k or k == "mask_iou"},
            "part_moves": part_change(run), **hand_shows(run)}


def hand_shows(run_dir: Path, most: int = 6, scale: float = 0.25, hands: Path | None = None) -> dict:
    """Does the trained scene draw the hand? On the training frames where the transient layer covers most, each
    rendered at its own learned states: PSNR against the captured frame inside the hand's pixels and elsewhere. A
    scene that baked the hand in reproduces it (as close as elsewhere); one that left it out draws what is behind
    it, far from the captured hand. There is no truth of what is behind, so this says whether the hand shows, not
    how well the scene behind it is drawn. hands: a dataset of the same frames whose transient layer marks the
    hand (default the run's own; for a run trained without the layer, the one with it)."""
    import cv2

    from interreal.transients import read_transient
    from livescene.losses import psnr
    from livescene.render import learned_frame_states, render_view
    from livescene.run import load_run

    run = load_run(run_dir, device="cpu")
    v = run.views
    ds = v.dataset
    hands = hands or ds.root
    layer = {i: read_transient(hands, ds.frames[i].fid) for i in v.train}
    layer = {i: m for i, m in layer.items() if m is not None and m.any()}
    if not layer:
        return {"hand_frames": 0}
    states = learned_frame_states(run)
    inside, outside = [], []
    for i in sorted(layer, key=lambda j: -float(layer[j].mean()))[:most]:
        w, h = _scaled_size(v.intrinsics[i], scale)
        out = render_view(run, v.c2w_gl[i], v.intrinsics[i].scaled(w, h), states[i], time=float(v.times[i]))["rgb"]
        img = cv2.resize(ds.load_image(ds.frames[i]), (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
        hand = cv2.resize(layer[i].astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
        err = ((out - img) ** 2).mean(-1)
        inside.append(float(err[hand].mean()))
        outside.append(float(err[~hand].mean()))
    return {"hand_frames": len(inside), "psnr_at_hand": round(psnr(np.mean(inside)), 2),
            "psnr_elsewhere": round(psnr(np.mean(outside)), 2)}


def _scaled_size(intr, scale: float) -> tuple[int, int]:
    """(w, h) of a camera's image `scale` times its size (at least 8 pixels a side)."""
    return max(8, int(intr.w * scale)), max(8, int(intr.h * scale))


def part_change(run_dir: Path, scale: float = 0.25, tol: float = 0.1) -> list[float]:
    """Per held-out camera (at most 6): the share of the lid's mask pixels whose rendered colour differs by more
    than `tol` (mean over channels) between states 0 and 1."""
    import cv2

    from livescene.render import render_view
    from livescene.run import load_run

    run = load_run(run_dir, device="cpu")
    v = run.views
    held = v.held_out[:: max(1, len(v.held_out) // 6)][:6]
    out = []
    for i in held:
        intr = v.intrinsics[i]
        w, h = _scaled_size(intr, scale)
        small = intr.scaled(w, h)
        a = render_view(run, v.c2w_gl[i], small, [0.0])["rgb"]
        b = render_view(run, v.c2w_gl[i], small, [1.0])["rgb"]
        mask = v.dataset.load_mask(v.dataset.frames[i])[..., 0].astype(np.uint8)
        mask = cv2.resize(mask, (w, h), interpolation=cv2.INTER_NEAREST) > 0
        if mask.sum() < 10:
            continue
        diff = np.abs(a - b).mean(-1) > tol
        out.append(round(float(diff[mask].mean()), 3))
    return out


def agreement(a: dict, b: dict) -> dict:
    """How two runs' motions agree: the angle between their axes and the RMS difference of the states they
    measured on the frames both registered (two independent routes agreeing is evidence neither drifted)."""
    out: dict = {}
    if a.get("axis") and b.get("axis"):
        cos = abs(float(np.dot(a["axis"], b["axis"]))) / (np.linalg.norm(a["axis"]) * np.linalg.norm(b["axis"]))
        out["axis_deg"] = round(float(np.degrees(np.arccos(min(1.0, cos)))), 2)
    sa = {row[0]: row[1] for row in a.get("frame_states") or []}
    sb = {row[0]: row[1] for row in b.get("frame_states") or []}
    common = sorted(set(sa) & set(sb))
    if common:
        diff = np.array([sa[f] - sb[f] for f in common])
        out.update(frames=len(common), state_rms_diff=round(float(np.sqrt(np.mean(diff ** 2))), 4))
    return out


def against_reference(r: dict, ref: dict[int, float]) -> dict:
    """A run's measured states against the careful reference (`hinge_reference`) on the frames both have: RMSE
    over all of them and over the labelled ones (the same frames the label RMSE uses)."""
    rows = [(frame_index(row[0]), row[1], row[2]) for row in r.get("frame_states") or []]
    both = [(ref[f], s, lab) for f, s, lab in rows if f in ref and s is not None]
    if not both:
        return {"ref_frames": 0}
    d = np.array([s - t for t, s, _ in both])
    dl = np.array([s - t for t, s, lab in both if lab is not None])
    return {"ref_frames": len(both), "ref_rmse": round(float(np.sqrt(np.mean(d ** 2))), 4),
            "ref_max": round(float(np.max(np.abs(d))), 4),
            "ref_rmse_labelled": round(float(np.sqrt(np.mean(dl ** 2))), 4) if len(dl) else None}


def careful_reference(ds: Path) -> tuple[dict, dict[int, float]]:
    """The reference's figures and per-frame states on this dataset's cameras (the marks: lid_corners.json)."""
    from hinge_reference import first_object_labels, from_files

    ref = from_files(ds, FIXTURES / "lid_corners.json", first_object_labels(ds))
    return ref.figures(), ref.state_of()


def main() -> None:
    args = bench_args("real", __doc__.splitlines()[0], _extra)
    every = args.every or (4 if args.quick else 2)
    long_side = args.long_side or (800 if args.quick else 1072)
    video = require_shared("laptop", "laptop_orbit.mp4")
    ds = args.out / "real_ds"
    run: dict = {"data": "laptop_orbit", "every": every, "long_side": long_side, "threads": args.threads,
                 "transients": args.transients}
    if not (args.reuse and (ds / "transforms.json").exists()):
        run.update(run_process(video, ds, every, long_side, args.transients))
    runs = []
    for route in args.routes.split(","):
        r = dict(run, **run_motions(ds, args.threads, route.strip()), variant=route.strip())
        r["total_s"] = round(r.get("process_s", 0.0) + r["motions_s"], 1)
        runs.append(r)
    if args.train_minutes > 0:  # with the motion of the first route in articulation.json (re-measured last)
        if len(runs) > 1:
            run_motions(ds, args.threads, runs[0]["variant"])
        runs[0].update(run_training(ds, args.out, args.train_minutes, args.train_threads))
    ref_fig, ref_states = careful_reference(ds)
    for r in runs:
        r.update(against_reference(r, ref_states))
    meta = {"annotations": str(FIXTURES.relative_to(REPO)), "reference": ref_fig}
    if len(runs) >= 2:
        meta["route_agreement"] = agreement(runs[0], runs[1])
    path = write_results(args.out, "real", runs, **meta)
    print_table(runs, ["variant", "frames", "registered", "process_s", "motions_s", "route", "part_registered",
                       "kind", "range_deg", "axis_to_up_deg", "state_rmse", "ref_rmse", "ref_rmse_labelled",
                       "ref_max", "flagged", "used"])
    print(f"  careful reference (hinge_reference, {ref_fig['frames']} marked frames): {ref_fig}")
    for r in runs:
        if "part_moves" in r:
            print(f"  {r['variant']}: trained {r['train_s']} s; " + ", ".join(
                f"{k} {v:.3f}" for k, v in r.items()
                if "psnr" in k or "ssim" in k or "state_mae" in k or k == "mask_iou")
                + f"; lid pixels changing between states 0 and 1 per held-out camera: {r['part_moves']}")
    for r in runs:
        for name, measured, label, _ in [row for row in r.get("frame_states") or [] if row[2] is not None]:
            careful = ref_states.get(frame_index(name))
            print(f"  {r['variant']}: frame {name}: label {label:.2f}, careful "
                  f"{'-' if careful is None else f'{careful:.2f}'}, measured {measured:.2f}")
        for w in r["warnings"]:
            print(f"  {r['variant']} warning: {w}")
    if "route_agreement" in meta:
        print(f"  {runs[0]['variant']} vs {runs[1]['variant']}: {meta['route_agreement']}")
    print(f"-> {path}")


if __name__ == "__main__":
    main()
