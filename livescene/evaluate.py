"""Evaluation of a run (`livescene eval` is `commands/eval.py`): held-out PSNR / SSIM, depth L1, state MAE on
unlabelled frames, mask IoU of the probability field, and novel-state PSNR against a truth that can render any
(camera, states) pair (with, per novel-state view, the mask IoU there - who owns the space at the new states - and
how training saw its parts).

Held-out frames are the trainer's split (every 8th frame, never trained on). With per-frame appearance
(`model.appearance`) `psnr` / `ssim` are neutral (identity, as new views render) and `psnr_interpolated` /
`ssim_interpolated` give each held-out frame the appearance interpolated from the training frames around it.

Truth is anything with the `Truth` protocol; `--gt DIR` opens one through an installed truth reader
(`open_truth`): for an `interreal synth` capture, `interreal.synth.evaltruth` (gt/states.json, gt/depth,
gt/instance, and its scene for novel states).
"""

from __future__ import annotations

import time
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np
from skimage.metrics import structural_similarity
from tqdm import tqdm

from interreal.dataset import Intrinsics
from interreal.errors import InterRealError

from .appearance import apply_to_image, interpolate_codes
from .data import load_frame, measured_matrix, nearest_views, scored_mse, transient_at
from .errors import LiveSceneError
from .losses import psnr
from .render import RenderMeter, learned_frame_states, render_view
from .unseen import sweep_frames, unsupported_pairs


class Truth(Protocol):
    """What evaluation can compare against (all optional except `states`)."""

    states: np.ndarray  # (N, M) true states, dataset frame order

    metres_per_unit: float  # dataset world units -> metres (1 for a truth dataset, the SfM scale otherwise)

    def render(self, i: int, states: np.ndarray, intr: Intrinsics) -> np.ndarray: ...  # rgb uint8, frame i's true camera

    def depth(self, i: int, intr: Intrinsics) -> np.ndarray | None: ...  # z-depth metres, 0 = none

    def instance(self, i: int, intr: Intrinsics) -> np.ndarray | None: ...  # 0 bg, k obj k-1, 255 ignore

    # optional: frame i's true camera at any states, as `instance` (scores who owns what at a novel state)
    def state_instance(self, i: int, states: np.ndarray, intr: Intrinsics) -> np.ndarray | None: ...

    # optional: how training saw the moving parts camera i shows at `states` (reported per novel-state view)
    def part_support(self, i: int, states: np.ndarray, intr: Intrinsics, train: list[int]) -> dict: ...


TRUTH_READERS = "livescene.truth"  # the entry-point group of the truth readers `open_truth` knows


def open_truth(gt_dir: str | Path, views) -> Truth:
    """The truth in `gt_dir` for the run's views, read by an installed truth reader: a callable
    `(gt_dir, views) -> Truth` registered under the entry-point group `livescene.truth` (interreal registers
    `interreal.synth.evaltruth:open_truth` for its simulated captures). Readers are tried in name order; the first
    that reads the folder wins, and when none does, the first one's refusal (it names what is wrong) is raised.

    livescene imports no simulator: the truth reaches it through this protocol only (docs/architecture.md)."""
    readers = sorted(entry_points(group=TRUTH_READERS), key=lambda ep: ep.name)
    if not readers:
        raise LiveSceneError(f"--gt {gt_dir}: no truth reader is installed (entry points {TRUTH_READERS!r}); "
                             f"reinstall the package (bash .ci/setup, or pip install -e .)")
    errors: list[Exception] = []
    for ep in readers:
        try:
            return ep.load()(Path(gt_dir), views)
        except InterRealError as exc:
            errors.append(exc)
    raise errors[0]


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    return float(structural_similarity(a, b, channel_axis=2, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                       use_sample_covariance=False))


def mask_iou(probs: np.ndarray, index: np.ndarray, n_objects: int) -> float | None:
    """Mean IoU over objects present in the truth (index map 0 = bg, k = object k-1, 255 ignored)."""
    pred = probs.argmax(-1)  # objects 0..M-1, background M
    pred = np.where(pred == n_objects, 0, pred + 1)
    valid = index != 255
    ious = []
    for k in range(1, n_objects + 1):
        t, p = (index == k) & valid, (pred == k) & valid
        if t.sum() == 0:
            continue
        ious.append((t & p).sum() / max((t | p).sum(), 1))
    return float(np.mean(ious)) if ious else None


def pick_frames(frames: list[int], n: int) -> list[int]:
    if n <= 0 or n >= len(frames):
        return list(frames)
    return [frames[i] for i in np.linspace(0, len(frames) - 1, n).round().astype(int)]


def view_intrinsics(views, i: int, scale: float) -> Intrinsics:
    """Frame i's intrinsics at the evaluation's render scale."""
    intr = views.intrinsics[i]
    if scale == 1.0:
        return intr
    return intr.scaled(max(1, round(intr.w * scale)), max(1, round(intr.h * scale)))


def state_scores(run, truth: Truth, i: int, states: np.ndarray, intr: Intrinsics, fast: bool = True,
                 meter: RenderMeter | None = None) -> dict[str, float | None]:
    """The run against the simulator, frame i's camera, both at the given states: `psnr`, and `mask_iou` of the
    probability field against the simulator's instances there (None when the truth has none) - a novel-state view
    can fail by drawing a part badly or by giving its space to another owner (the background), and only this
    tells them apart."""
    ref = truth.render(i, states, intr).astype(np.float32) / 255.0
    views = run.views
    out = render_view(run, views.c2w_gl[i], intr, np.asarray(states, np.float32), time=float(views.times[i]),
                      fast=fast)
    if meter is not None:
        meter.add(out)
    inst = truth.state_instance(i, states, intr) if hasattr(truth, "state_instance") else None
    return {"psnr": psnr(np.mean((out["rgb"] - ref) ** 2)),
            "mask_iou": None if inst is None else mask_iou(out["probs"], inst, run.model.n_objects)}


def novel_states(train_states: np.ndarray, rng: np.random.Generator, tries: int = 200) -> tuple[np.ndarray, float]:
    """A state vector far (L-inf) from every training frame's states: (states, distance)."""
    m = train_states.shape[1]
    best, best_d = None, -1.0
    for _ in range(tries):
        cand = rng.choice([0.0, 0.25, 0.5, 0.75, 1.0], size=m) if m > 1 else rng.uniform(0, 1, 1)
        d = float(np.abs(train_states - cand).max(1).min()) if len(train_states) else 1.0
        if d > best_d:
            best, best_d = cand, d
    return np.asarray(best, dtype=np.float64), best_d


def composition_states(states: np.ndarray, centres: np.ndarray, train: list[int], i: int, near: int = 0,
                       levels: int = 5) -> tuple[np.ndarray, float] | None:
    """For camera i: a combination of states, each object's state seen from near this camera in training, that is
    far (L-inf) from every training frame's combination; None when the nearby states allow no new combination.

    Separates composing parts (the model's claim) from rendering a part at a state it was never seen in from
    this side (an extrapolation no data supports). states (N, M); centres (N, 3) camera centres."""
    m = states.shape[1]
    tr = np.asarray(train)
    close = nearest_views(centres, train, centres[i], near)
    options = []
    for o in range(m):
        seen = np.unique(np.round(states[close, o] * 20) / 20)
        options.append(seen[np.linspace(0, len(seen) - 1, min(levels, len(seen))).round().astype(int)])
    grids = np.stack(np.meshgrid(*options, indexing="ij"), -1).reshape(-1, m)
    dist = np.abs(states[tr][None] - grids[:, None]).max(-1).min(1)
    best = int(np.argmax(dist))
    return (grids[best], float(dist[best])) if dist[best] >= 0.1 else None


def evaluate(run, truth: Truth | None = None, *, max_frames: int = 0, scale: float = 1.0, novel: int = 4,
             seed: int = 0, progress: bool = True, fast: bool = True) -> dict[str, Any]:
    """The figures (module doc), and `speed`: how fast the run rendered here (`RenderMeter.report`) and the whole
    evaluation's wall time. fast=False renders with the exact renderer (`render_view`)."""
    t_start = time.perf_counter()
    meter = RenderMeter()
    views = run.views
    m = run.model.n_objects
    held = pick_frames(views.held_out, max_frames)
    if not held:
        raise LiveSceneError("the run has no held-out frames (holdout_every <= 1)")
    per_frame = []
    codes = held_out_codes(run)
    for i in tqdm(held, desc="eval held-out", disable=not progress):
        intr = view_intrinsics(views, i, scale)
        rgb, mask = load_frame(views, i)
        if (rgb.shape[1], rgb.shape[0]) != (intr.w, intr.h):
            rgb = cv2.resize(rgb, (intr.w, intr.h), interpolation=cv2.INTER_AREA)
            mask = None if mask is None else cv2.resize(mask, (intr.w, intr.h), interpolation=cv2.INTER_NEAREST)
        out = meter.add(render_view(run, views.c2w_gl[i], intr, None, time=float(views.times[i]), fast=fast))
        recorded = rgb.astype(np.float32) / 255.0
        tr = transient_at(views, i, intr.w, intr.h)  # a person / hand: not part of the scene, not scored
        if tr is not None:
            mask = None if mask is None else np.where(tr, 255, mask).astype(np.uint8)
        rec: dict[str, Any] = {"frame": views.dataset.frames[i].fid, **image_scores(out["rgb"], recorded, tr)}
        if codes is not None:  # the same render as this frame's camera would have recorded it (module doc)
            look = apply_to_image(out["rgb"], codes[i], run.model.appearance.mode)
            rec.update({f"{k}_interpolated": v for k, v in image_scores(look, recorded, tr).items()})
        if tr is not None:
            rec["transient_share"] = round(float(tr.mean()), 4)
        inst = truth.instance(i, intr) if truth is not None and hasattr(truth, "instance") else None
        if inst is None and mask is not None:
            inst = mask
        if inst is not None and m:
            rec["mask_iou"] = mask_iou(out["probs"], inst, m)
        depth = truth.depth(i, intr) if truth is not None and hasattr(truth, "depth") else None
        if depth is not None:
            ok = depth > 0
            mpu = float(getattr(truth, "metres_per_unit", 1.0))
            rec["depth_l1"] = float(np.abs(out["depth"][ok] * mpu - depth[ok]).mean()) if ok.any() else None  # metres
        per_frame.append(rec)

    def mean(key: str) -> float | None:
        vals = [r[key] for r in per_frame if r.get(key) is not None]
        return float(np.mean(vals)) if vals else None

    result: dict[str, Any] = {"run": str(run.run_dir), "step": run.step, "held_out_frames": len(held),
                              "psnr": mean("psnr"), "ssim": mean("ssim"), "mask_iou": mean("mask_iou"),
                              "depth_l1": mean("depth_l1"), "reject_threshold": run.model.cfg.reject_threshold,
                              "params": run.model.param_count(), "appearance": appearance_note(run)}
    if codes is not None:
        result.update(psnr_interpolated=mean("psnr_interpolated"), ssim_interpolated=mean("ssim_interpolated"))
    # states on frames without labels
    learned = learned_frame_states(run)
    labels, given = views.dataset.label_matrix()
    result.update(labelled_state_errors(learned, labels, given, views))
    result.update(measured_state_errors(learned, views))
    if truth is not None and m:
        free = ~given
        result["state_mae"] = float(np.abs(learned - truth.states)[free].mean()) if free.any() else None
        result["state_mae_max"] = float(np.abs(learned - truth.states)[free].max()) if free.any() else None
    # novel states
    if truth is not None and hasattr(truth, "render") and novel > 0 and m:
        rng = np.random.default_rng(seed)
        train_states = truth.states[views.train]
        records, dists = [], []
        novel_cams = pick_frames(views.held_out, novel)
        for i in tqdm(novel_cams, desc="eval novel states", disable=not progress):
            intr = view_intrinsics(views, i, scale)
            st, d = novel_states(train_states, rng)
            dists.append(d)
            sc = state_scores(run, truth, i, st, intr, fast, meter)
            # the same camera at the frame's true states, against the same renderer: separates "new state"
            # from "simulator render vs recorded frame"
            b = state_scores(run, truth, i, truth.states[i], intr, fast, meter)
            rec = {"frame": views.dataset.frames[i].fid, "states": [round(float(v), 3) for v in st],
                   "psnr": sc["psnr"], "true_state_psnr": b["psnr"], "mask_iou": sc["mask_iou"],
                   "true_state_mask_iou": b["mask_iou"]}
            if hasattr(truth, "part_support"):  # how training saw the parts this view shows
                rec["parts"] = truth.part_support(i, st, intr, views.train)
            records.append(rec)
        result["novel_state_psnr"] = float(np.mean([r["psnr"] for r in records]))
        result["true_state_sim_psnr"] = float(np.mean([r["true_state_psnr"] for r in records]))
        ious = [r["mask_iou"] for r in records if r["mask_iou"] is not None]
        result["novel_state_mask_iou"] = float(np.mean(ious)) if ious else None
        result["novel_state_distance"] = float(np.mean(dists))
        result["novel_frames"] = records
        # composition: new combinations of states each seen from near the camera
        centres = np.asarray(views.c2w_gl)[:, :3, 3]
        comp = []
        for i in novel_cams:
            pick = composition_states(truth.states, centres, views.train, i)
            if pick is None:
                continue
            intr = view_intrinsics(views, i, scale)
            st, d = pick
            comp.append({"frame": views.dataset.frames[i].fid, "states": [round(float(v), 3) for v in st],
                         "distance": round(d, 3), "psnr": state_scores(run, truth, i, st, intr, fast, meter)["psnr"]})
        result["composition_frames"] = comp
        result["composition_psnr"] = float(np.mean([c["psnr"] for c in comp])) if comp else None
    result["frames"] = per_frame
    # parts without a measured motion: the (camera, state) pairs no training view supports (`livescene.unseen`)
    result["unsupported"] = unsupported_pairs(run, sweep_frames(views)) if m else []
    result["speed"] = {**meter.report(), "eval_s": round(time.perf_counter() - t_start, 3)}
    return result


def image_scores(rendered: np.ndarray, recorded: np.ndarray, transient: np.ndarray | None) -> dict[str, float]:
    """PSNR and SSIM of a render against the recorded frame; transient pixels (a hand) are left out of the PSNR and
    given the render's colour for the SSIM (its window needs whole images)."""
    if transient is not None:
        recorded = recorded.copy()
        recorded[transient] = rendered[transient]
    return {"psnr": psnr(scored_mse(rendered, recorded, transient)), "ssim": ssim(rendered, recorded)}


def held_out_codes(run) -> np.ndarray | None:
    """(N, D) an appearance code per frame, the held-out ones interpolated in time from the training frames'
    (`livescene.appearance.interpolate_codes`); None when the run has no per-frame appearance."""
    app = run.model.appearance
    if app is None:
        return None
    codes = app.centred().detach().cpu().numpy()
    trained = np.flatnonzero(app.trained.cpu().numpy()).tolist()
    return interpolate_codes(codes, run.views.times, trained)


def appearance_note(run) -> dict[str, Any]:
    """What `psnr` / `ssim` and `*_interpolated` mean for this run's appearance setting."""
    app = run.model.appearance
    if app is None:
        return {"mode": "off"}
    return {"mode": app.mode, "psnr": "neutral: rendered with the identity appearance, as new views are",
            "psnr_interpolated": "each held-out frame's appearance interpolated in time from the nearest training "
                                 "frames' codes (no held-out pixel is used)"}


def labelled_state_errors(learned: np.ndarray, labels: np.ndarray, given: np.ndarray, views) -> dict[str, Any]:
    """State MAE on the labelled training frames (fitted: how well Lvar held them) and on the labelled held-out
    frames (never trained on: what to expect on unlabelled frames), apart, with how many labels each is over."""
    out: dict[str, Any] = {}
    for key, frames in (("train", views.train), ("held_out", views.held_out)):
        mask = np.zeros_like(given)
        mask[list(frames)] = given[list(frames)]
        n = int(mask.sum())
        out[f"state_mae_labelled_{key}"] = float(np.abs(learned - labels)[mask].mean()) if n else None
        out[f"state_labels_{key}"] = n
    return out


def measured_state_errors(learned: np.ndarray, views) -> dict[str, Any]:
    """State MAE against the states `interreal motions` measured from each part's displacement, on held-out frames
    (never trained on): on a real capture, where no truth exists, the closest thing to a state error on every
    frame; {} when no part has measured states."""
    measured = measured_matrix(views.dataset)[views.held_out]
    ok = np.isfinite(measured)
    if not ok.any():
        return {}
    errs = np.abs(learned[views.held_out][:, : measured.shape[1]] - measured)[ok]
    return {"state_mae_measured_held_out": float(errs.mean()), "state_measured_held_out": int(ok.sum())}
