"""`livescene eval`: held-out PSNR / SSIM, depth L1, state MAE on unlabelled frames, mask IoU of the
probability field, and novel-state PSNR against a simulator that can render any (camera, states) pair (with,
per novel-state view, the mask IoU there - who owns the space at the new states - and how training saw its parts).

Held-out frames are the trainer's split (every 8th frame, never trained on). Truth comes from a simulated
capture (`--gt DIR`: gt/states.json, gt/depth, gt/instance, and its scene for novel states), whose world frame
must be the dataset's (true for `interreal.synth.truth_dataset`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

import numpy as np

from interreal import atomic
from interreal.dataset import Intrinsics

from .data import load_frame, nearest_views
from .errors import LiveSceneError, writing
from .losses import psnr
from .render import RenderMeter, learned_frame_states, render_view


class Truth(Protocol):
    """What evaluation can compare against (all optional except `states`)."""

    states: np.ndarray  # (N, M) true states, dataset frame order

    metres_per_unit: float  # dataset world units -> metres (1 for a truth dataset, the SfM scale otherwise)

    def render(self, i: int, states: np.ndarray, intr: Intrinsics) -> np.ndarray: ...  # rgb uint8, frame i's true camera

    def depth(self, i: int, intr: Intrinsics) -> np.ndarray | None: ...  # z-depth metres, 0 = none

    def instance(self, i: int, intr: Intrinsics) -> np.ndarray | None: ...  # 0 bg, k obj k-1, 255 ignore

    # optional: frame i's true camera at any states, as `instance` (scores who owns what at a novel state)
    def state_instance(self, i: int, states: np.ndarray, intr: Intrinsics) -> np.ndarray | None: ...


class CaptureTruth:
    """Truth of an `interreal synth` capture, indexed by the dataset's frames (matched by source frame index)."""

    def __init__(self, gt_dir: str | Path, views):
        from interreal.synth import Capture

        self.dir = Path(gt_dir)
        if not (self.dir / "gt" / "states.json").exists():
            raise LiveSceneError(f"{self.dir}/gt/states.json not found: --gt must be an `interreal synth` capture folder")
        self.cap = Capture.open(self.dir)
        check_same_capture(self.cap, views, self.dir)
        cols = []
        for n in views.names:
            if n not in self.cap.names:
                raise LiveSceneError(f"object {n!r} of the dataset is not in the capture's {self.cap.names}")
            cols.append(self.cap.names.index(n))
        self.frames = list(views.dataset.frames)
        self.names = list(views.names)
        self.states = self.cap.states[[f.index for f in self.frames]][:, cols]
        self._renders: dict = {}
        # the dataset's cameras may live in an SfM frame (centred, scaled): truth renders use the capture's own
        # camera for each frame, and depth compares in metres through a similarity fit of the camera centres
        from interreal.scoring import umeyama

        est = np.asarray(views.c2w_gl)[:, :3, 3]
        ref = self.cap.poses[[f.index for f in self.frames]][:, :3, 3]
        self.metres_per_unit = float(umeyama(est, ref)[0]) if len(est) >= 3 else 1.0

    def render(self, i, states, intr):
        """Supersampled at the capture's resolution, then area-averaged: the way the dataset's images were made
        (one ray per pixel at a small size aliases, which alone costs about 30 dB)."""
        import cv2

        f = max(1, min(4, int(round(self.cap.intrinsics.w / intr.w))))
        rgb = self._scene_render(i, states, self.cap.intrinsics.scaled(intr.w * f, intr.h * f)).rgb
        return rgb if f == 1 else cv2.resize(rgb, (intr.w, intr.h), interpolation=cv2.INTER_AREA)

    def _scene_render(self, i: int, states, cap_intr: Intrinsics):
        """The simulator's render (rgb, z-depth, instance) of frame i's own camera at `states` with cap_intr."""
        values = {n: float(v) for n, v in zip(self.names, np.asarray(states).ravel())}
        return self.cap.scene().render(self.cap.poses[self.frames[i].index], values, cap_intr)

    def _clean(self, i: int, states, intr: Intrinsics, cache: bool = False):
        """The simulator's clean render (rgb, z-depth, instance) of frame i's camera at `states`, at the capture's
        own intrinsics scaled to intr's size; `cache` keeps it (part_support reads every training frame once per
        novel view)."""
        key = (i, intr.w, intr.h, tuple(np.round(np.asarray(states, float).ravel(), 6)))
        if cache and key in self._renders:
            return self._renders[key]
        out = self._scene_render(i, states, self.cap.intrinsics.scaled(intr.w, intr.h))
        if cache:
            self._renders[key] = out
        return out

    def part_support(self, i: int, states, intr: Intrinsics, train: list[int], comparable: float = 1.5) -> dict:
        """How training saw the moving parts that camera i shows at `states`.

        Each part pixel's surface point is taken into its part's own frame (so a training frame at any state
        can have seen it), carried to each training frame at that frame's states, and counted as seen where it
        lands unoccluded on the same part (2 cm + 1 % of depth). `seen`: share of the part pixels some training
        frame saw; `seen_comparable`: share seen from no more than `comparable` times this view's distance -
        a surface seen only from three times farther (or at a grazing angle: the footprint of a pixel on the
        surface, distance / cos(incidence), is compared) has a third of the detail this view asks for, and no
        model can render what it never saw. `part_share`: share of the image the parts cover."""
        from interreal.synth.consistency import project, unproject

        parts = [next(p for p in self.cap.scene().parts if p.name == n) for n in self.names]
        states = np.asarray(states, float).ravel()
        cap_intr = self.cap.intrinsics.scaled(intr.w, intr.h)
        centre = self.cap.poses[self.frames[i].index][:3, 3]
        cam = self._clean(i, states, intr)
        world = unproject(self.cap.poses[self.frames[i].index], cam.depth, cap_intr)
        n_px = int(np.isin(cam.instance, np.arange(1, len(parts) + 1)).sum())
        if n_px == 0:
            return {"part_share": 0.0, "seen": None, "seen_comparable": None}
        normal = np.cross(np.gradient(world, axis=1), np.gradient(world, axis=0))
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True).clip(1e-12)
        seen_all, close_all = 0, 0
        for o, part in enumerate(parts):
            sel = cam.instance == o + 1
            if not sel.any():
                continue
            rot, trans = part.pose(float(states[o]))
            local = (world[sel] - trans) @ rot  # the part's rest frame
            n_local = normal[sel] @ rot
            here = _footprint(world[sel], normal[sel], centre)
            best = np.full(local.shape[0], np.inf)
            for f in train:
                ref = self._clean(f, self.states[f], intr, cache=True)
                rf, tf = part.pose(float(self.states[f][o]))
                pts = local @ rf.T + tf
                pose = self.cap.poses[self.frames[f].index]
                px, z = project(pose, pts, cap_intr)
                u, v = np.round(px[:, 0]).astype(int), np.round(px[:, 1]).astype(int)
                ok = (z > 0) & (u >= 0) & (u < intr.w) & (v >= 0) & (v < intr.h)
                idx = np.nonzero(ok)[0]
                zf = ref.depth[v[idx], u[idx]]
                hit = (np.abs(zf - z[idx]) < 0.02 + 0.01 * z[idx]) & (ref.instance[v[idx], u[idx]] == o + 1)
                idx = idx[hit]
                there = _footprint(pts[idx], n_local[idx] @ rf.T, pose[:3, 3])
                best[idx] = np.minimum(best[idx], there / here[idx])
            seen_all += int(np.isfinite(best).sum())
            close_all += int((best <= comparable).sum())
        return {"part_share": n_px / cam.depth.size, "seen": seen_all / n_px, "seen_comparable": close_all / n_px}

    def state_instance(self, i, states, intr):
        return self._clean(i, states, intr).instance

    @staticmethod
    def _fit(img: np.ndarray, intr: Intrinsics) -> np.ndarray:
        import cv2

        if img.shape[:2] == (intr.h, intr.w):
            return img
        return cv2.resize(img, (intr.w, intr.h), interpolation=cv2.INTER_NEAREST)

    def depth(self, i, intr):
        try:
            return self._fit(self.cap.depth(self.frames[i].index), intr)
        except Exception:  # noqa: BLE001 - no depth for this frame: no depth figure
            return None

    def instance(self, i, intr):
        try:
            return self._fit(self.cap.instance(self.frames[i].index), intr)
        except Exception:  # noqa: BLE001
            return None


MAX_CENTRE_ERR_PCT = 5.0  # SfM cameras of the capture itself agree within a fraction of this (0.1-1 %)
MAX_ROT_ERR_DEG = 5.0


def check_same_capture(cap, views, gt_dir: Path) -> None:
    """--gt must be the capture the run's dataset was made from, or every figure compares unrelated pictures:
    its frames hold the dataset's frame indices, its image has the dataset's aspect ratio, and its cameras match
    the dataset's up to a similarity (SfM's frame). LiveSceneError naming the mismatch otherwise."""
    idx = [f.index for f in views.dataset.frames]
    if max(idx) >= len(cap):
        raise LiveSceneError(f"--gt {gt_dir} has {len(cap)} frames but the run's dataset has frame index {max(idx)}: "
                             f"it is not the capture this dataset was made from")
    intr = views.intrinsics[0]
    ours, theirs = intr.w / intr.h, cap.intrinsics.w / cap.intrinsics.h
    if abs(ours / theirs - 1) > 0.02:
        raise LiveSceneError(f"--gt {gt_dir}: its images are {cap.intrinsics.w}x{cap.intrinsics.h}, the dataset's "
                             f"{intr.w}x{intr.h} (another aspect ratio): it is not the capture this dataset was made from")
    if len(idx) < 3:
        return
    from interreal.scoring import compare_poses

    est = np.asarray(views.c2w_gl, dtype=np.float64)
    ref = cap.poses[idx]
    err = compare_poses(est, ref)
    if not (err["center_err_pct_median"] <= MAX_CENTRE_ERR_PCT and err["rot_err_deg_median"] <= MAX_ROT_ERR_DEG):
        raise LiveSceneError(f"--gt {gt_dir}: its cameras do not match the run's dataset (median centre error "
                             f"{err['center_err_pct_median']:.1f} % of the path, rotation {err['rot_err_deg_median']:.1f} "
                             f"deg after the best similarity): it is not the capture this dataset was made from")


def _footprint(points: np.ndarray, normals: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Size of a pixel on the surface, up to the focal length: distance / cos(incidence) (N,)."""
    ray = points - centre
    dist = np.linalg.norm(ray, axis=-1)
    cos = np.abs((ray * normals).sum(-1)) / dist.clip(1e-12)
    return dist / cos.clip(0.05)


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    from skimage.metrics import structural_similarity

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
    import time

    t_start = time.perf_counter()
    meter = RenderMeter()
    from tqdm import tqdm

    views = run.views
    m = run.model.n_objects
    held = pick_frames(views.held_out, max_frames)
    if not held:
        raise LiveSceneError("the run has no held-out frames (holdout_every <= 1)")
    per_frame = []
    for i in tqdm(held, desc="eval held-out", disable=not progress):
        intr = view_intrinsics(views, i, scale)
        rgb, mask = load_frame(views, i)
        import cv2

        if (rgb.shape[1], rgb.shape[0]) != (intr.w, intr.h):
            rgb = cv2.resize(rgb, (intr.w, intr.h), interpolation=cv2.INTER_AREA)
            mask = None if mask is None else cv2.resize(mask, (intr.w, intr.h), interpolation=cv2.INTER_NEAREST)
        out = meter.add(render_view(run, views.c2w_gl[i], intr, None, time=float(views.times[i]), fast=fast))
        gt = rgb.astype(np.float32) / 255.0
        rec: dict[str, Any] = {"frame": views.dataset.frames[i].fid, "psnr": psnr(np.mean((out["rgb"] - gt) ** 2)),
                               "ssim": ssim(out["rgb"], gt)}
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
                              "params": run.model.param_count()}
    # states on frames without labels
    learned = learned_frame_states(run)
    labels, given = views.dataset.label_matrix()
    result.update(labelled_state_errors(learned, labels, given, views))
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
    result["speed"] = {**meter.report(), "eval_s": round(time.perf_counter() - t_start, 3)}
    return result


def add_arguments(p) -> None:
    p.add_argument("run", type=Path, help="run folder of `livescene train`")
    p.add_argument("--gt", type=Path, default=None, help="`interreal synth` capture folder with the truth")
    p.add_argument("--out", type=Path, required=True, help="JSON file for the figures")
    p.add_argument("--max-frames", type=int, default=0, help="evaluate this many held-out frames, evenly spread (0 = all)")
    p.add_argument("--scale", type=float, default=1.0, help="render scale (e.g. 0.5 for a quicker estimate)")
    p.add_argument("--novel", type=int, default=4, help="held-out cameras rendered at novel states (needs --gt)")
    p.add_argument("--device", default="auto")
    p.add_argument("--dataset", type=Path, default=None, help="the run's dataset where it is now, when it was moved")
    p.add_argument("--exact", action="store_true",
                   help="render with the exact renderer (every sample read; slower) instead of the fast one")
    p.epilog = ("examples:\n"
                "  livescene eval out/run --out out/eval.json\n"
                "  livescene eval out/run --gt out/cap --out out/eval.json --max-frames 8")


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


def main(args) -> int:
    from .trainer import load_run

    from .device import configure_threads

    configure_threads(0)
    if not (np.isfinite(args.scale) and 0 < args.scale <= 4) or args.max_frames < 0 or args.novel < 0:
        raise LiveSceneError("--scale must be in (0, 4], --max-frames and --novel at least 0")
    if args.gt is not None and not args.gt.is_dir():
        raise LiveSceneError(f"--gt {args.gt} is not a folder: give the `interreal synth` capture folder")
    run = load_run(args.run, device=args.device, dataset=args.dataset)
    truth = CaptureTruth(args.gt, run.views) if args.gt else None
    res = evaluate(run, truth, max_frames=args.max_frames, scale=args.scale, novel=args.novel, fast=not args.exact)
    with writing(args.out):
        atomic.write_json(args.out, res)
    keys = ["psnr", "ssim", "mask_iou", "depth_l1", "state_mae", "state_mae_labelled_train",
            "state_mae_labelled_held_out", "novel_state_psnr", "composition_psnr"]
    print("livescene eval: " + ", ".join(f"{k} {res[k]:.4g}" for k in keys if res.get(k) is not None)
          + f" ({res['speed']['renderer']} renderer, {res['speed']['seconds_per_frame'] or 0:.2f} s a frame, "
            f"{res['speed']['rays_per_s'] or 0:,} rays/s) -> {args.out}")
    return 0
