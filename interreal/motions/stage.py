"""`interreal motions DS`: how each object moves with its state, measured from the video -> DS/articulation.json.

A rigid part's pose in the world at every frame, whether it was still or moving, comes from its own pixels (its
masks, eroded, with the transient layer's hands and people taken out) by one of two routes (a third, for a part too
plain for both, needs no pose: see the end):
- its own SfM (default first): the part's pixels alone reconstructed with pycolmap, as if it were a scene of its
  own; every frame that reconstruction registers gives the camera relative to the part, and with the camera's pose
  in the world (transforms.json), the part's pose;
- known-camera PnP (`motions.pnp`, the fallback, or first with `--route pnp`): the part triangulated once
  where it rests, with the known cameras, and located in every frame by PnP (seconds, but it needs a stretch where
  the part rests while the camera moves; its reference is the window that triangulates most points, which can be
  one where the part moved slowly).
When neither gives an accepted motion, the part's silhouettes against the known cameras (`motions.silhouette`:
its flat front triangulated from its masks' corners, then the hinge or slide whose predicted silhouettes fit the
masks) measure every frame's displacement directly, and for a plain door cut by the image border, the one straight
edge of its outline that stays put is its hinge (`motions.edge`); for a plain drawer, its front at rest on one
of those edges, pulled out along its normal, each frame's pull from its mask (`motions.prism`).
`motions.fit` turns those poses into a hinge or a slide decided by the geometry (does the part turn about
one axis, or translate along one line?), measures every registered frame's state from its displacement, and uses
the labels only to fix the ends and the direction; labels that disagree with the geometry are named as likely
mistakes. Time is bounded: at most `max_frames` frames of a part are used, and another mapper seed is tried only
when the first model is refused and time is left (`budget_s`).
The trainer (`livescene`, `model.motion`) then reads each part's samples in its rest frame (its pose at state 0).
Conventions of the file: `interreal.conventions` / `interreal.dataset.Articulation`.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from tqdm import tqdm

from .. import provenance
from ..conventions import ARTICULATION_FILE
from ..dataset import Articulation, known_states, load_dataset, write_articulation
from ..errors import InputError, StageError
from ..options import add_flags, config_from, values_from_args
from ..report import StageReport, finished_with, fingerprint, read_report, warning_lines
from ..sfm import colmap
from .edge import rival_words
from .fit import FLAG_TOL, LABELS_LINE, UNLABELLED_END, PartViews, fit_motion
from .part import (DRAW_WHY, ROUTES, MotionConfig, ObjectResult, measure_object, measure_object_at, measure_part,
                   part_dir, saved_result)

__all__ = ["PartViews", "fit_motion", "estimate_motions", "measure_part", "MotionConfig"]


# ----------------------------------------------------------------------------------------------------------------
# Measuring a part
# ----------------------------------------------------------------------------------------------------------------
def disagreement_text(check: list[list], fids: list[str], most: int = 5) -> str:
    """'measured states -0.05..1.12; labels that disagree most: 00042 (label 1.00, measured 0.62), ...'"""
    if not check:
        return "no labelled frame was measured"
    measured = [m for _, _, m in check]
    worst = sorted(check, key=lambda r: -abs(r[2] - r[1]))
    off = [r for r in worst if abs(r[2] - r[1]) > FLAG_TOL][:most]
    return (f"measured states {min(measured):.2f} to {max(measured):.2f} on {len(check)} labelled frames; "
            + ("labels off by more than " + f"{FLAG_TOL} (likely mistakes): " + ", ".join(
                f"{fids[f]} (label {lab:.2f}, measured {m:.2f})" for f, lab, m in off) if off
               else "no single label is off by more than " + f"{FLAG_TOL}"))


def routes_text(fig: dict[str, Any]) -> str:
    """'; the other routes: pnp: <why not>; ...' for the routes tried besides the one whose motion is reported."""
    used = fig.get("route")
    said = [f"{r}: {v.get('reason') or ('refused' if v.get('kind') else 'no motion')}"
            for r, v in fig.get("routes", {}).items() if r != used]
    return f"; the other routes: {'; '.join(said)}" if said else ""


def ends_warnings(name: str, fig: dict[str, Any], fids: list[str] | None = None) -> list[tuple[str, str]]:
    """(text, cause) for each end of a used motion whose state the geometry alone did not give: an end with no
    label near it (taken as 0 or 1), and an end the labels' line placed short of it, where no route measured the
    part further: its range is then the labels' guess, so the person hears which frames to draw (`draw_frames`, by
    their ids in `fids`) and which labels to check."""
    ends = fig.get("ends_from", "")
    out = []
    if UNLABELLED_END in ends:
        out.append((f"'{name}': {ends}: label a frame at each end to be sure", "ends-from-geometry"))
    if LABELS_LINE in ends:
        masks = f"; its masks past there: {fig['reach_reason']}" if fig.get("reach_reason") else ""
        ask, _ = draw_ask(fig, fids)
        out.append((f"'{name}': no route measured it further than the frames labelled there, so its range comes from "
                    f"the labels ({ends}{masks}): {ask + ', and ' if ask else ''}check the labels near that end, or "
                    f"film the part at its ends where it can be seen", "ends-from-labels"))
    return out


def contested_text(name: str, measured_by: str, fig: dict[str, Any], fids: list[str]) -> str:
    """The warning for a hinge used although a slide of the part's front explains its masks nearly as well."""
    return (f"'{name}': the hinge measured by {measured_by} is used, but a slide of its front explains the masks of "
            f"the frames it turned in nearly as well ({rival_words(fig)}): {draw_ask(fig, fids)[0]}")


def draw_ask(fig: dict[str, Any], fids: list[str] | None) -> tuple[str, list[str]]:
    """(words, frame ids) asking a person to draw the part on `fig`'s `draw_frames` (where an end of its motion is
    the labels' guess and the masks lost it), or ('', [])."""
    draw = [fids[f] if fids else str(f) for f in fig.get("draw_frames") or []]
    if not draw:
        return "", []
    return (f"draw its mask on frame{'s' if len(draw) > 1 else ''} {', '.join(draw)} ({draw_why(fig)}; "
            f"`interreal annotate` lists them), run `interreal masks` and `interreal motions` again"), draw


def draw_why(fig: dict[str, Any]) -> str:
    """Why `fig`'s `draw_frames` are asked for, in words (an end the labels' guess scales, unless it says)."""
    return str(fig.get("draw_why") or DRAW_WHY["end"])


def draw_fields(fig: dict[str, Any], fids: list[str]) -> dict[str, Any]:
    """The warning's fields naming the frames to draw and why (`frames_asked` reads them), or none."""
    draw = draw_ask(fig, fids)[1]
    return {"draw": draw, "draw_why": draw_why(fig)} if draw else {}


def frames_asked(root: str | Path) -> list[dict[str, Any]]:
    """The frames the last `interreal motions` run asks a person to draw a part's mask on (where an end of its
    motion is the labels' guess, or where a drawn mask decides between two models): [{fid, object, why}] (what the
    annotate app lists beside its suggested frames)."""
    out = []
    for w in (read_report(root, "motions") or {}).get("warnings", []):
        if isinstance(w, dict) and isinstance(w.get("draw"), list):
            out += [{"fid": str(f), "object": str(w.get("object", "")), "why": draw_why(w)} for f in w["draw"]]
    return out


def frame_state_rows(fig: dict[str, Any], fids: list[str], labels: np.ndarray, given: np.ndarray) -> list[list]:
    """[[frame id, measured state, label or None, likely mistake], ...] over the registered frames: each frame's
    measured state next to its label, for the report and the annotate app."""
    flagged = {f for f, _, _ in fig.get("flagged_labels", [])}
    return [[fids[f], m, round(float(labels[f]), 3) if given[f] else None, f in flagged]
            for f, m in fig.get("frame_states", [])]


def _flag_rows(fig: dict[str, Any], fids: list[str]) -> list[list]:
    """[[frame id, label, measured state], ...] of the labels the fit named as likely mistakes."""
    return [[fids[f], lab, m] for f, lab, m in fig.get("flagged_labels", [])]


def flagged_labels(root: str | Path) -> list[dict[str, Any]]:
    """The labels the last `interreal motions` run named as likely mistakes: [{fid, object, label, measured}]
    (what the annotate app lists next to its suggested frames; [] without a report)."""
    out = []
    for w in (read_report(root, "motions") or {}).get("warnings", []):
        if isinstance(w, dict) and isinstance(w.get("flagged"), list):
            for row in w["flagged"]:
                if isinstance(row, list) and len(row) == 3:
                    out.append({"fid": str(row[0]), "object": str(w.get("object", "")), "label": row[1],
                                "measured": row[2]})
    return out


# ----------------------------------------------------------------------------------------------------------------
# The stage
# ----------------------------------------------------------------------------------------------------------------
def worker_count(cfg: MotionConfig, parts: int) -> int:
    """How many parts are measured at once: `cfg.workers`, or one per CPU core this process may use (no more than
    the CPU budget `interreal batch` gives each capture, OMP_NUM_THREADS, as COLMAP's threads keep to it)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    budget = colmap.threads(-1)
    return max(1, min(parts, cfg.workers or (min(cores, budget) if budget > 0 else cores)))


def follow_parent(parent: int) -> None:
    """A part's process ends soon after the command that started it is gone (killed, SIGKILL included): left
    waiting, it would hold that command's terminal and pipes open for ever. Ctrl-C is the command's to answer (one
    line; it ends its parts' processes), and so is SIGTERM (COLMAP's handler would dump each one's stack)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    # its progress bar's lock a thread's, not a semaphore: killed, it would leave one the parent's tracker warns of
    tqdm.set_lock(threading.RLock())

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="follow-parent", daemon=True).start()


def measured_objects(ds, cfg: MotionConfig, states: np.ndarray, known: np.ndarray, given: np.ndarray,
                     key: str | None = None, reuse: bool = True) -> Iterator[tuple[int, ObjectResult]]:
    """(object, its measurement) in the objects' order. With several parts and cores each part is measured in a
    process of its own (spawned: no thread of COLMAP's or OpenCV's is forked mid-work): the routes are mostly
    single-threaded Python, so two doors take the time of the slower one. A part's answer does not depend on which
    process measures it. Each finished part is saved under the resume `key`, and a run the stage did not finish
    (Ctrl-C, another part's failure) is resumed from the parts it saved when `reuse`."""
    n = ds.n_objects
    saved = {o: r for o in range(n) if key is not None and reuse
             and (r := saved_result(part_dir(ds.root, o), key, ds.object_names[o])) is not None}
    todo = [o for o in range(n) if o not in saved]
    workers = worker_count(cfg, len(todo))
    if workers <= 1:
        for o in range(n):
            yield o, saved.get(o) or measure_object(ds, o, cfg, states[:, o], known[:, o], given[:, o], key=key)
        return
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=follow_parent,
                               initargs=(os.getpid(),))
    done = False
    try:
        futures = {o: pool.submit(measure_object_at, ds.root, o, cfg, states[:, o], known[:, o], given[:, o],
                                  position, key) for position, o in enumerate(todo)}
        for o in range(n):
            if o in saved:
                yield o, saved[o]
                continue
            try:
                result = futures[o].result()
            except BrokenProcessPool as exc:
                raise StageError(f"the process measuring '{ds.object_names[o]}' died ({exc}): run `interreal motions "
                                 f"{ds.root} --workers 1` to measure the parts one after another and see why") from exc
            yield o, result
        done = True
    finally:
        if not done:  # Ctrl-C, an error: the parts still being measured are not waited for (killed: COLMAP's
            for proc in list((getattr(pool, "_processes", None) or {}).values()):  # handler dumps a stack on SIGTERM)
                proc.kill()
        pool.shutdown(wait=done, cancel_futures=True)


def estimate_motions(ds_path: str | Path, force: bool = False, **opts: Any) -> dict[str, Any]:
    """Measure every object's motion and write DS/articulation.json and reports/motions.json; returns the figures.
    A finished run from the same masks, poses, labels and settings is reused unless `force`.

    An object the reconstruction cannot follow (too few registered frames, or too few of them with a known state)
    gets no motion and a warning: the trainer then moves it with the k-axis alone, as the paper does."""
    ds_path = Path(ds_path)
    cfg = config_from(MotionConfig, opts, "motion")
    if cfg.route not in ROUTES:
        raise InputError(f"--route {cfg.route!r} is not one of {', '.join(ROUTES)}")
    fps = provenance.fingerprints(ds_path, provenance.MOTION_INPUTS)  # before anything is read
    ds = load_dataset(ds_path)
    if not ds.n_objects:
        raise InputError(f"{ds_path} has no objects (mapping.yaml): nothing moves")
    if not ds.has_masks():
        raise InputError(f"{ds_path} has no masks for every frame: run `interreal masks {ds_path} --keyframes DIR`")
    if ds.intrinsics is None:
        raise InputError(f"{ds_path}: transforms.json has no shared intrinsics (per-frame cameras are not supported)")
    labels, given = ds.label_matrix()
    if not given.any():
        raise InputError(f"{ds_path} has no state labels: label a few frames first (`interreal label`)")
    times = np.array([f.index for f in ds.frames], float)
    states, known = known_states(times, labels, given)
    colmap.load_pycolmap(cfg.verbose)  # its absence said before any part is measured
    inputs = {"frames": len(ds.frames), "objects": ds.object_names, "fingerprints": fps}
    # by content: a re-run of an earlier stage that rewrote the same bytes does not measure everything again
    # (how many parts at once changes no answer)
    key = fingerprint({k: v for k, v in asdict(cfg).items() if k != "workers"},
                      {k: v["content"] for k, v in sorted(fps.items())})
    done = finished_with(ds_path, "motions", key)
    if done is not None and (ds_path / ARTICULATION_FILE).exists() and not force:
        return dict(done["figures"], reused=True)
    motions: dict[str, Articulation] = {}
    parts: dict[str, dict[str, Any]] = {}
    with StageReport(ds_path, "motions", inputs=inputs, settings=asdict(cfg), resume_key=key) as rep:
        for o, (matched, shown, motion, fig, reused) in measured_objects(ds, cfg, states, known, given, key,
                                                                         reuse=not force):
            name = ds.object_names[o]
            with rep.step(f"object {o}") as st:
                st["frames_shown"], st["frames_matched"] = shown, matched
                if reused:
                    st["reused"] = True  # measured by an earlier run of these inputs and settings that did not finish
                if fig is None:
                    rep.warn(f"'{name}' shows in only {matched} frames: no motion measured (the k-axis alone "
                             f"will move it)", cause="motion-unseen", object=name)
                    continue
                fids = [f.fid for f in ds.frames]
                st.update({k: v if not isinstance(v, float) or np.isfinite(v) else None for k, v in fig.items()})
                if motion is None:
                    ask = draw_ask(fig, fids)[0]
                    rep.warn(f"'{name}': no route measured a motion in the {shown} frames it shows in: "
                             + "; ".join(f"{r}: {v['reason']}" for r, v in fig.get("routes", {}).items())
                             + (f"; {ask}" if ask else "; label more frames where it moves, or film it with more "
                                                       "texture in view"),
                             cause="motion-unregistered", object=name, **draw_fields(fig, fids))
                    continue
                st["kind"] = motion.kind
                st["frame_states"] = frame_state_rows(fig, fids, labels[:, o], given[:, o])
                motion.extra = {k: v for k, v in fig.items() if k != "frame_states"}
                # every registered frame's measured state, by frame id: what training fits the states to
                # (`Articulation.measured_states`), eyeballed labels being coarser than the geometry
                motion.extra["frame_states"] = {fids[f]: m for f, m in fig.get("frame_states", [])}
                measured_by = f"{fig.get('route', '?')} ({fig['registered']} of the {shown} frames it shows in)"
                if not fig["accepted"]:
                    ask = draw_ask(fig, fids)[0]
                    rep.warn(f"'{name}': the {motion.kind} measured by {measured_by} is not used: {fig['reason']}; "
                             f"{disagreement_text(fig.get('label_check', []), fids)}{routes_text(fig)}; "
                             + (f"{ask}; " if ask else "") + "check "
                             + ("those labels and " if cfg.trust_labels else "") + "the part's masks",
                             cause="motion-inconsistent", object=name, flagged=_flag_rows(fig, fids),
                             **draw_fields(fig, fids))
                    continue
                for text, cause in ends_warnings(name, fig, fids):
                    rep.warn(text, cause=cause, object=name,
                             **(draw_fields(fig, fids) if cause == "ends-from-labels" else {}))
                if fig.get("draw_why") == DRAW_WHY["confirm"]:
                    rep.warn(contested_text(name, measured_by, fig, fids), cause="motion-contested", object=name,
                             **draw_fields(fig, fids))
                if fig["flagged_labels"]:
                    rep.warn(f"'{name}': {len(fig['flagged_labels'])} of {len(fig['label_check'])} labels disagree "
                             f"with the {motion.kind} measured by {measured_by}, which is used"
                             + ("" if cfg.trust_labels else " (the labels only orient it; --trust-labels lets them "
                                "decide)") + f": {disagreement_text(fig['label_check'], fids)}; the annotate app "
                             f"offers the measured states as the fix", cause="label-disagrees", object=name,
                             flagged=_flag_rows(fig, fids))
                motions[name] = motion
                parts[name] = part_summary(motion, fig, shown)
        write_articulation(ds_path, motions, {"source": "interreal motions"})
        rep.figures.update(objects={n: m.kind for n, m in motions.items()}, measured=len(motions),
                           total=ds.n_objects, parts=parts)
        figures = dict(rep.figures)
    return figures


def part_summary(motion: Articulation, fig: dict[str, Any], shown: int) -> dict[str, Any]:
    """What a user needs to trust a used motion, in one record: kind, size, route, frames, the states' span, the
    labels flagged (the report's step holds every frame's state and why the other routes gave nothing)."""
    states = [m for _, m in fig.get("frame_states", [])]
    size = round(float(np.degrees(motion.range)), 1) if motion.kind == "hinge" else round(float(motion.range), 4)
    return {"kind": motion.kind, "range": size, "unit": "deg" if motion.kind == "hinge" else "world units",
            "route": fig.get("route"), "poses": fig.get("poses_from"), "measured_frames": len(states),
            "shown_frames": shown,
            "states": [round(min(states), 2), round(max(states), 2)] if states else None,
            "flagged_labels": len(fig.get("flagged_labels", [])), "ends_from": fig.get("ends_from", ""),
            "read_by_masks": 0 if fig.get("reach_reason") else int(fig.get("reach_beyond") or 0)}


def part_line(name: str, p: dict[str, Any]) -> str:
    """One line per used motion, e.g. 'door': hinge of 53.6 deg by sfm posed by the known cameras, 64 of 64 frames,
    states -0.01 to 1.02."""
    how = p["route"] + (" posed by the known cameras" if p.get("poses") == "known cameras" else "")
    return (f"'{name}': {p['kind']} of {p['range']:g} {p['unit']} by {how}, {p['measured_frames']} of "
            f"{p['shown_frames']} frames" + (f" ({p['read_by_masks']} past its measured angles read by their masks)"
                                             if p.get("read_by_masks") else "")
            + (f", states {p['states'][0]:g} to {p['states'][1]:g}" if p["states"] else "")
            + (f"; {p['flagged_labels']} label(s) flagged" if p["flagged_labels"] else ""))


def add_arguments(p) -> None:
    p.add_argument("dataset", type=Path, help="dataset folder with images, masks, transforms.json and labels")
    add_flags(p, MotionConfig)  # one flag per `option` field
    p.add_argument("--force", action="store_true", help="measure again even when a finished run matches")
    p.epilog = ("examples:\n  interreal motions out/ds\n  interreal motions out/ds --erode 4\n"
                "  interreal motions out/ds --route edge      # a plain door filmed from close by, tried first\n"
                "  interreal motions out/ds --route prism     # a plain drawer, tried first\n"
                "  interreal motions out/ds --workers 1       # the parts one after another (each holds its masks)\n"
                f"writes DS/{ARTICULATION_FILE} (read by `livescene train`) and DS/reports/motions.json")


def main(args) -> int:
    fig = estimate_motions(args.dataset, force=args.force, **values_from_args(MotionConfig, args))
    for line in warning_lines(args.dataset, ["motions"]):
        print(line)
    steps = (read_report(args.dataset, "motions") or {}).get("steps") or {}
    resumed = sum(bool(st.get("reused")) for st in steps.values() if isinstance(st, dict))
    print(measured_line(fig, " (reused: same inputs and settings)" if fig.get("reused") else
                        f" ({resumed} part(s) read back from the run that was stopped)" if resumed else ""))
    return 0


def measured_line(fig: dict[str, Any], note: str = "") -> str:
    """The stage's summary from its figures: how many objects got a motion (`note` after that), each one's kind,
    then a line per part (`part_line`); what `interreal motions` and `process` print."""
    objs = fig.get("objects") or {}
    return (f"motions: {fig.get('measured', 0)} of {fig.get('total', '?')} objects measured{note}"
            + (": " + ", ".join(f"{n} ({k})" for n, k in objs.items()) if objs else "")
            + "".join(f"\n  {part_line(n, p)}" for n, p in (fig.get("parts") or {}).items()))
