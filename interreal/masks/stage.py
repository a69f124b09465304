"""The `masks` stage: keyframe annotations + DS/images -> DS/masks/*.npy, DS/sfm_masks/, previews, report."""

from __future__ import annotations

import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from .. import atomic, provenance
from ..conventions import (IMAGES_DIR, FRAME_PREFIX, frame_id, frame_index, index_to_onehot, mask_file,
                           onehot_to_index)
from ..dataset import list_images, read_image_rgb, read_mapping, write_mapping, write_mask
from ..errors import InputError
from ..layout import MASKS_CACHE_DIR, PREVIEWS_DIR, SFM_MASKS_DIR, TRANSIENTS_CACHE_FILE
from ..report import StageReport, files_fingerprint, finished_with, fingerprint, tree_fingerprint
from ..options import config_from
from .carry import SETTINGS as CARRY_SETTINGS, carry_layer
from .config import PREVIEW_KINDS, MasksConfig
from .confidence import reach_suggestion
from . import health as H
from .keyframes import load_keyframes
from ..video import VideoWriter
from .preview import contact_sheet, second_line, thumb
from .redetect import Event
from .soft import disk
from .reuse import Reuse
from .track import FrameResult, Propagator, TrackConfig
from .verdict import MAX_REACH, Cues, RunHealth, assess_run, fine_shares, key_refs
from ..transients import (IGNORE, clear_transients, read_transient, split_labels, track_labels, transient_file,
                          write_transient)
from ..transients.auto import AutoLayer, layer_key, load_layer, propose, save_layer
from ..transients.hands import model_problem, shares



def make_config(**opts: Any) -> TrackConfig:
    """A TrackConfig from the user-facing options (`MasksConfig` fields; None = the default)."""
    return config_from(MasksConfig, opts, "masks").track_config()


def dataset_frames(ds: Path) -> list[Path]:
    images = [p for p in list_images(ds / IMAGES_DIR) if p.stem.startswith(FRAME_PREFIX) and frame_id(p).isdigit()]
    if not images:
        raise InputError(f"{ds / IMAGES_DIR} has no frame_NNNNN images: run `interreal frames VIDEO {ds}` first")
    return sorted(images, key=frame_index)


def propagate(ds: str | Path, keyframes_dir: str | Path, *, progress: bool = True, config: TrackConfig | None = None,
              **opts: Any) -> dict[str, Any]:
    """Propagate keyframe masks to every frame of DS; returns the report's figures.

    `opts`: the `MasksConfig` fields (work_long_side, flow, preset, appearance, rigid, fusion, refine, suggest,
    preview, sfm_dilate, transients; None = the default). `config` (a TrackConfig) overrides the propagation ones
    (benchmarks use it for the baseline).

    Everything the user gave is checked first (InputError, nothing written); then the report is opened
    ("running"), so a crash half-way leaves it "failed" and `interreal validate` refuses the dataset. A finished
    run from the same images, keyframes and settings is reused (the poses stage downstream then reuses its
    features too).
    """
    ds = Path(ds)
    opt = config_from(MasksConfig, opts, "masks")
    if opt.preview not in PREVIEW_KINDS:
        raise InputError(f"--preview {opt.preview!r}: choose one of {PREVIEW_KINDS}")
    # the hand model checked once, first: a run made without it is made again once it is installed
    no_model = model_problem() if opt.transients == "auto" else None
    auto = opt.transients == "auto" and no_model is None
    cfg = config or opt.track_config()
    images = dataset_frames(ds)
    # the mapping file is left out of the key: the first run writes it, which would make every second run look changed
    keys_fp = tree_fingerprint(Path(keyframes_dir))
    key = None if keys_fp is None else fingerprint("masks", str(ds.resolve()), files_fingerprint(images), keys_fp,
                                                    asdict(cfg), opt.suggest, opt.preview, opt.sfm_dilate, auto)
    done = _reusable(ds, images, key)
    if done is not None:
        if progress:
            print(f"masks: {len(images)} frames' masks are up to date (same frames, keyframes and settings)")
        return done
    fingerprints = provenance.fingerprints(ds, ["images", "capture"], keyframes=keyframes_dir)  # before any read
    job = _Job.open(ds, images, Path(keyframes_dir))
    inputs = {"keyframes_dir": str(keyframes_dir), "keyframes": job.kf.sources, "frames": len(job.fids),
              "size": list(job.size), "objects": job.kf.names, "fingerprints": fingerprints}
    settings = {**asdict(cfg), "suggest": opt.suggest, "preview": opt.preview, "transients": opt.transients}
    with StageReport(ds, "masks", inputs=inputs, settings=settings, resume_key=key) as rep:
        rep.steps["keyframes"] = {"wall_s": round(job.keyframes_s, 4)}
        if not job.ds_mapping:
            write_mapping(ds, dict(enumerate(job.kf.names)))
        layer = _auto_layer(rep, job, auto, no_model, progress, opt.reuse)
        dil = opt.sfm_dilate if opt.sfm_dilate is not None else max(2, round(0.006 * float(np.hypot(*job.size))))
        out = _run_chains(rep, job, cfg, layer, opt.preview, dil, progress, opt.reuse)
        hl, health = assess_run(ds, job.fids, job.anchors, job.n_obj, out.cues, out.ref, out.prop,
                                out.grey is not None, opt.suggest)
        with rep.step("left_view"):
            _blank_left_view(job, out, health.blank, opt.preview, dil)
        with rep.step("previews"):
            _write_previews(ds, out, hl, job.n_obj)
        _report(rep, job, out, hl, health, dil)
        rep.figures["transients"]["auto"] = auto_figures(layer, job.fids, opt.transients, no_model)
        _warn(rep, job, out, hl, health, layer)
        return dict(rep.figures)


def _reusable(ds: Path, images: list[Path], key: str | None) -> dict[str, Any] | None:
    """The figures of a finished run with this key whose files are all still there, else None."""
    done = finished_with(ds, "masks", key) if key is not None else None
    if done is None:
        return None
    fids = [frame_id(p) for p in images]
    transients = (done["figures"].get("transients") or {}).get("share", {})
    if all(mask_file(ds, f).exists() for f in fids) \
            and all((ds / SFM_MASKS_DIR / f"{p.name}.png").exists() for p in images) \
            and all(transient_file(ds, f).exists() for f in transients):
        return done["figures"]
    return None


@dataclass
class _Job:
    """One masks run's inputs, checked: the frames (their ids, size, how to read one) and the keyframes."""

    ds: Path
    images: list[Path]
    fids: list[str]
    size: tuple[int, int]  # (w, h)
    ds_mapping: dict[int, str]
    kf: Any = None  # `keyframes.Keyframes`
    keyframes_s: float = 0.0

    @classmethod
    def open(cls, ds: Path, images: list[Path], keyframes_dir: Path) -> "_Job":
        first = read_image_rgb(images[0])
        job = cls(ds, images, [frame_id(p) for p in images], (first.shape[1], first.shape[0]), read_mapping(ds))
        _refuse_duplicate_names(ds / "mapping.yaml", list(job.ds_mapping.values()))
        t0 = time.perf_counter()
        job.kf = load_keyframes(keyframes_dir, job.fids, job.size, job.ds_mapping,
                                image_of=lambda fid: job.load(job.pos_of[fid]))
        job.keyframes_s = time.perf_counter() - t0
        _refuse_duplicate_names(keyframes_dir, list(job.kf.names))
        return job

    @cached_property
    def pos_of(self) -> dict[str, int]:
        return {f: i for i, f in enumerate(self.fids)}

    @property
    def n_obj(self) -> int:
        return len(self.kf.names)

    @property
    def n_track(self) -> int:
        """Objects the chains track: the painted ignore class (people, hands) is one more, then written to
        DS/transients/."""
        return self.n_obj + int(self.kf.has_ignore)

    @cached_property
    def anchors(self) -> dict[int, np.ndarray]:
        return {self.pos_of[f]: track_labels(m, self.n_obj) for f, m in self.kf.masks.items()}

    @cached_property
    def painted(self) -> set[int]:
        """Keyframe positions that paint the ignore class: what is transient there is what they say."""
        return {self.pos_of[f] for f, m in self.kf.masks.items() if (m == IGNORE).any()}

    def load(self, pos: int) -> np.ndarray:
        img = read_image_rgb(self.images[pos])
        if (img.shape[1], img.shape[0]) != self.size:
            raise InputError(f"{self.images[pos]} is {img.shape[1]}x{img.shape[0]}, other frames are "
                             f"{self.size[0]}x{self.size[1]}; re-run `interreal frames`")
        return img


def _auto_layer(rep: StageReport, job: _Job, auto: bool, no_model: str | None, progress: bool,
                reuse: bool = True) -> AutoLayer | None:
    """`--transients auto`'s layer (the last run's when the frames are the same: it depends on no keyframe), or
    the one line on why there is none."""
    if auto:
        key, cache = fingerprint(layer_key(job.images), "carried", CARRY_SETTINGS), job.ds / TRANSIENTS_CACHE_FILE
        layer = load_layer(cache, key) if reuse else None
        if layer is not None:
            rep.steps["transients_auto"] = {**layer.seconds, "reused": True}
            return layer
        with rep.step("transients_auto") as st:
            layer = carry_layer(propose(job.load, len(job.fids), job.size, progress=progress), job.load,
                                len(job.fids))
            st.update(layer.seconds)
        if reuse:
            try:
                save_layer(cache, key, layer)
            except OSError as exc:  # a convenience for the next run: this one goes on
                rep.warn(f"the transient layer was not kept for the next run ({exc})", cause="cache-not-kept")
        return layer
    if no_model:
        rep.warn(f"no automatic transient layer: {no_model}; or paint the hand / person as `ignore` on the "
                 f"keyframes", cause="no-hand-model")
        if progress:
            print(f"masks: no automatic transient layer: {no_model}")
    return None


@dataclass
class _Chains:
    """What the propagation pass leaves: the tracker, the per-frame cues and transient shares, the preview tiles, the
    fine-part shares of the keyframes and the pass's speed."""

    prop: Propagator
    cues: Cues
    transient_share: np.ndarray
    grey: int | None  # the ignore class's index in the tracked labels when there is a transient layer (drawn grey)
    ref: dict[int, np.ndarray]  # keyframe position -> each tracked class's area share there
    fine_r: int
    tiles: dict[int, np.ndarray] = field(default_factory=dict)
    video: dict[int, np.ndarray] = field(default_factory=dict)
    fine: np.ndarray | None = None
    fine_key: list | None = None
    info: dict[str, Any] = field(default_factory=dict)


def _run_chains(rep: StageReport, job: _Job, cfg: TrackConfig, layer: AutoLayer | None, preview: str, dil: int,
                progress: bool, reuse: bool = True) -> _Chains:
    """Every frame's labels from the chains (or, for the stretches no keyframe change touched, from the last run:
    `reuse`), written (masks, transients, SfM masks) on a thread of their own while the chains run, with the cues
    health needs and the preview tiles."""
    n_obj, fids = job.n_obj, job.fids
    prop = Propagator(job.load, len(fids), job.size, job.n_track, cfg)
    out = _Chains(prop, Cues(len(fids), job.n_track), np.zeros(len(fids)),
                  n_obj + 1 if job.n_track > n_obj or (layer is not None and layer.masks) else None,
                  {p: np.array([(m == k + 1).mean() for k in range(job.n_track)]) for p, m in job.anchors.items()},
                  H.fine_radius(job.size[0], prop.wsize[0]))
    clear_transients(job.ds)  # this run's ignore class (or none) replaces any earlier transient layer
    kept = Reuse(job.ds / MASKS_CACHE_DIR, job.images, job.anchors, (asdict(cfg), job.n_track)) if reuse else None
    sheet_pos = set(np.linspace(0, len(fids) - 1, min(len(fids), 24)).round().astype(int).tolist())
    vid_w = min(480, job.size[0])
    t_write = 0.0
    with rep.step("propagate") as info:
        t_start, c_start, c_write = time.perf_counter(), time.process_time(), 0.0
        bar = tqdm(total=len(fids), desc="masks", unit="frame", disable=not progress)
        # files are written on a thread of their own: encoding and syncing them overlaps the chains
        with ThreadPoolExecutor(1, thread_name_prefix="write") as writer:
            # what health compares each frame with, made on the writer (first in its queue, so ready for every
            # frame's cues) while the chains start: a decode and a colour fit per keyframe, off their path
            refs = writer.submit(key_refs, job.anchors, job.load, prop.wsize, job.n_track)
            fine = writer.submit(fine_shares, job.anchors, n_obj, out.fine_r)
            pending: deque[Future] = deque()

            def emit(res: FrameResult, row: dict[str, np.ndarray] | None) -> None:
                # a keyframe that paints the ignore class says what is transient there: no proposal over it
                labels = with_auto(res.labels, None if res.pos in job.painted else layer, res.pos, n_obj)
                out.transient_share[res.pos] = (labels == n_obj + 1).mean() if out.grey is not None else 0.0
                pending.append(writer.submit(_write_frame, job.ds, fids[res.pos], job.images[res.pos].name,
                                             labels, n_obj, dil))
                while pending and pending[0].done():
                    pending.popleft().result()  # a failed write stops the stage here, not at the end
                # the cues and the preview tiles go to the writer too: the chains' thread is the one the
                # others wait for (first frame only: 10 % of its time was these)
                work = None if res.keyframe or row is not None else prop.cache.work(res.pos)
                if row is not None:
                    out.cues.put(res.pos, row)
                else:
                    pending.append(writer.submit(out.cues.add, res, work, refs))
                if kept is not None and row is None and not res.keyframe:
                    pending.append(writer.submit(kept.save_frame, res.pos, res.labels))
                if preview != "none":
                    full = prop.cache.peek(res.pos)
                    cap = f"{fids[res.pos]}{' key' if res.keyframe else ''}"
                    if preview in ("sheet", "both") and res.pos in sheet_pos:
                        pending.append(writer.submit(_tile, out.tiles, res.pos, full, job.load, labels, 240, cap,
                                                     out.grey))
                    if preview in ("video", "both"):
                        # the work image is the video's size (WORK_LONG_SIDE = vid_w): no resize of the full one
                        src = work if work is not None and work.shape[1] == vid_w else full
                        pending.append(writer.submit(_tile, out.video, res.pos, src, job.load, labels, vid_w, cap,
                                                     out.grey))
                bar.update(1)

            for res in prop.run(job.anchors, kept.found if kept is not None else ()):
                tw, cw = time.perf_counter(), time.process_time()
                emit(res, None)
                t_write += time.perf_counter() - tw
                c_write += time.process_time() - cw
            for pos, labels, row in (kept.replay() if kept is not None else ()):
                emit(FrameResult(pos, labels), row)
            bar.close()
            tw = time.perf_counter()
            for done in pending:
                done.result()
            out.fine, out.fine_key = fine.result()
            if kept is not None:
                kept.finish(out.cues, prop)
                if kept.failed:
                    rep.warn(f"this run's masks were not kept for the next ({kept.failed}): the next run makes every "
                             f"frame again", cause="cache-not-kept")
            t_write += time.perf_counter() - tw
        compute = time.perf_counter() - t_start - t_write
        cpu = time.process_time() - c_start - c_write
        # fps: wall clock (slowed by whatever else runs); cpu_fps: frames per CPU-second over all threads,
        # i.e. what one dedicated core would do, a contention-free floor for the 2-core figure
        info.update(frames=len(fids), flow_pairs=prop.flow_pairs, compute_s=round(compute, 3),
                    write_s=round(t_write, 3), fps=round(len(fids) / max(compute, 1e-9), 2),
                    cpu_s=round(cpu, 3), cpu_fps=round(len(fids) / max(cpu, 1e-9), 2),
                    reused_frames=kept.reused_frames if kept is not None else 0)
        out.info = dict(info)
    return out


def _blank_left_view(job: _Job, out: _Chains, blank: dict[int, list[int]], preview: str, dil: int) -> None:
    """No mask for an object where it is out of the view (`verdict.left_view`: per object, the frames): whatever
    the chains left there (a remnant, a look-alike they moved to) is taken out of its mask file, its SfM mask, its
    preview tiles and its area cue."""
    n_obj = job.n_obj
    for pos in sorted({i for frames in blank.values() for i in frames}):
        objs = [k for k, frames in blank.items() if pos in frames]
        fid = job.fids[pos]
        out.cues.area[pos, objs] = 0.0
        onehot = np.load(mask_file(job.ds, fid))
        if not onehot[..., objs].any():
            continue
        gone = onehot[..., objs].any(-1)
        onehot[..., objs] = False
        onehot[..., n_obj] |= gone
        write_mask(job.ds, fid, onehot)
        labels = onehot_to_index(onehot)
        transient = read_transient(job.ds, fid, labels.shape)
        if transient is not None:
            labels[transient & (labels == 0)] = n_obj + 1
        _write_sfm_mask(job.ds, job.images[pos].name, labels, dil)
        for group, width in ((out.tiles, 240), (out.video, min(480, job.size[0]))):
            if pos in group and preview != "none":
                _tile(group, pos, None, job.load, labels, width, fid, out.grey)


def _write_previews(ds: Path, out: _Chains, hl: H.Health, n_obj: int) -> None:
    """The contact sheet and the overlay video, each tile captioned with its confidence and worst state."""
    conf = hl.predicted  # the honest confidence: a predicted J, calibrated on real footage
    for group in (out.tiles, out.video):
        for p, tile in group.items():
            worst = int(hl.state[p, :n_obj].max()) if n_obj else 0
            text = f"c={conf[p, :n_obj].min():.2f}" + (f" {H.STATES[worst]}" if worst else "") if n_obj else ""
            second_line(tile, text, alert=worst > 0)
    prev_dir = ds / PREVIEWS_DIR
    if out.tiles:
        contact_sheet(prev_dir / "masks_sheet.png", [out.tiles[p] for p in sorted(out.tiles)])
    if out.video:
        first_v = out.video[min(out.video)]
        with VideoWriter(prev_dir / "masks_overlay.mp4", first_v.shape[1], first_v.shape[0], fps=15, crf=28) as vw:
            for p in sorted(out.video):
                vw.write(out.video[p])


def _report(rep: StageReport, job: _Job, out: _Chains, hl: H.Health, h: RunHealth, dil: int) -> None:
    """The report's figures (see docs/interfaces.md, Masks)."""
    fids, names, cues, conf = job.fids, job.kf.names, out.cues, hl.predicted
    n = len(fids)
    rep.figures.update({
        "frames": n, "keyframes": sorted(job.kf.masks), "objects": names,
        "fps": out.info["fps"], "cpu_fps": out.info["cpu_fps"],
        "reused_frames": out.info.get("reused_frames", 0),  # kept from the last run (`reuse`)
        "confidence": {nm: {fids[i]: round(float(conf[i, k]), 4) for i in range(n)} for k, nm in enumerate(names)},
        "area_fraction": {nm: {fids[i]: round(float(cues.area[i, k]), 5) for i in range(n)}
                          for k, nm in enumerate(names)},
        "confidence_mean": {nm: round(float(h.mean_pred[k]), 4) for k, nm in enumerate(names)},
        "confidence_min": {nm: round(float(conf[:, k].min()), 4) for k, nm in enumerate(names)},
        "suggested_frames": [fids[i] for i in h.picks],
        "sfm_dilate_px": dil,
        # per object: predicted J over the propagated frames and the stretches in each state (frame ranges)
        "health": {nm: {"predicted_j": round(float(h.mean_pred[k]), 4),
                        **{st: _stretch_text(fids, runs[k]) for st, runs in hl.stretches.items()}}
                   for k, nm in enumerate(names)},
        "states": {nm: {fids[i]: H.STATES[hl.state[i, k]] for i in range(n) if hl.state[i, k]}
                   for k, nm in enumerate(names)},
        # the cues behind the predicted J, per object and frame (recipes/bench_masks.py calibrates on them)
        "cues": {nm: {**{f: [round(float(v), 4) for v in h.feats[:, k, j]] for j, f in enumerate(H.FEATURES)},
                      "area_share": [round(float(v), 6) for v in cues.area[:, k]],
                      "ref_share": [round(float(v), 6) for v in h.ref_area[:, k]],
                      "expected": [bool(v) for v in h.expected[:, k]]} for k, nm in enumerate(names)},
    })
    share = out.transient_share
    rep.figures["transients"] = {
        "ignore_keyframes": sorted(f for f, m in job.kf.masks.items() if (m == IGNORE).any()),
        "frames": int((share > 0).sum()), "mean_share": round(float(share.mean()), 5),
        "max_share": round(float(share.max(initial=0.0)), 5),
        "share": {fids[i]: round(float(v), 5) for i, v in enumerate(share) if v > 0},
        "occluded": {names[k]: _stretch_text(fids, runs) for k, runs in h.occluded.items()}}
    # per object: lost stretches that are the object out of the view (it left over the image border)
    rep.figures["left_view"] = {names[k]: _stretch_text(fids, runs) for k, runs in h.left.items()}
    # frames where a chain found a collapsed object again from its keyframe's appearance (`redetect`)
    rep.figures["redetected"] = _event_frames(out.prop.redetections, fids, names)
    # ... and where a region of its colours was not taken for it: it moved with the background, the object not
    rep.figures["redetect_refused"] = _event_frames(out.prop.refusals, fids, names)
    # per object: the share of its keyframe masks in parts too fine for propagation to carry (`health.fine_share`)
    # and the keyframe with most of them (where the annotate app shows the warning)
    rep.figures["fine_parts"] = {"width_px": 2 * out.fine_r + 1,
                                 "share": {nm: round(float(out.fine[k]), 4) for k, nm in enumerate(names)},
                                 "keyframe": {nm: fids[out.fine_key[k]] for k, nm in enumerate(names)
                                              if out.fine_key[k] is not None}}
    rep.figures["keyframe_reach"] = [{"first": fids[a], "last": fids[b], "reach": round(r, 4)} for a, b, r in h.reach]
    rep.figures["max_keyframe_reach"] = round(max((r for _, _, r in h.reach), default=0.0), 4)


def _warn(rep: StageReport, job: _Job, out: _Chains, hl: H.Health, h: RunHealth, layer: AutoLayer | None) -> None:
    """The stage's warnings: a leaking auto layer, and per object lost stretches, fine parts, unreliable masks."""
    fids = job.fids
    if layer is not None and layer.leaked:
        leaked = [fids[p] for p in layer.leaked]
        rep.warn(f"transients auto: at frames {', '.join(leaked[:8])}{' ...' if len(leaked) > 8 else ''} the "
                 f"found hand grew over half the frame (a wall of the skin's colour?); only the hand itself was "
                 f"kept there: check them in `interreal annotate` and paint the arm as ignore where it matters",
                 cause="transient-leak", frames=leaked)
    keys = sorted(job.anchors)
    fine, fine_r = out.fine, out.fine_r
    for k, n in enumerate(job.kf.names):
        lost = hl.stretches["lost"][k]
        if lost:
            where = _stretch_text(fids, lost)
            rep.warn(f"'{n}': object lost at frames {where}: its mask vanished or collapsed where the keyframes "
                     f"show it; add a keyframe at {', '.join(fids[a] for a, _ in lost[:5])}",
                     cause="object-lost", object=n, frames=[fids[i] for a, b in lost for i in range(a, b + 1)])
        fine_note = (f"{100 * fine[k]:.0f} % of its keyframe masks are parts narrower than {2 * fine_r + 1} px "
                     f"(lines, cables, thin rods), which propagation leaves out between keyframes"
                     if fine[k] >= H.FINE_WARN else "")
        if fine_note:
            rep.warn(f"'{n}': {fine_note}: its masks there can reach J {1 - fine[k]:.2f} at most. Leave such parts "
                     f"out of its keyframes if the object need not include them; a finer --work-size keeps a "
                     f"little more of them", cause="masks-fine-parts", object=n)
        if h.mean_pred[k] >= H.WARN_J:
            continue
        why = [f"{st} at frames {_stretch_text(fids, hl.stretches[st][k])}"
               for st in ("lost", "jumped", "drifting") if hl.stretches[st][k]]
        if rep.figures["redetected"][n]:
            why.append(f"its mask collapsed and the object was found again by its keyframe's appearance at frames "
                       f"{_ranges(rep.figures['redetected'][n])}")
        if rep.figures["redetect_refused"][n]:
            why.append(f"its mask collapsed and a region of its colours that moved with the background was not "
                       f"taken for it at frames {_ranges(rep.figures['redetect_refused'][n])}")
        if fine_note:
            why.append(fine_note)
        if h.far:
            why.append("the view moves up to " + ", ".join(f"{100 * r:.0f} %" for _, _, r in h.far[:1])
                       + f" of its width from the nearest keyframe (propagation holds to about {100 * MAX_REACH:.0f} %)")
        add = sorted({fids[i] for i in h.picks[:8]}
                     or {fids[reach_suggestion(h.motion, a, b, keys)] for a, b, _ in h.far[:3]})
        rep.warn(f"'{n}': masks are unreliable (predicted J {h.mean_pred[k]:.2f}, under {H.WARN_J}): "
                 f"{'; '.join(why) or 'low confidence throughout'}; add keyframes at {', '.join(add[:8])}",
                 cause="masks-unreliable", object=n)


def _tile(into: dict[int, np.ndarray], pos: int, image: np.ndarray | None, load, labels: np.ndarray, width: int,
          caption: str, grey: int | None) -> None:
    """A preview tile of frame `pos` into `into` (the writer thread); `image` None: the frame left the cache."""
    into[pos] = thumb(load(pos) if image is None else image, labels, width, caption, ignore=grey)


def _event_frames(events: list[Event], fids: list[str], names: list[str]) -> dict[str, list[str]]:
    """Per object name, the sorted frame ids of its re-detection events (`redetect.Event`)."""
    return {n: sorted({fids[e.pos] for e in events if e.obj == k}) for k, n in enumerate(names)}


def _stretch_text(fids: list[str], runs: list[tuple[int, int]]) -> str:
    """[(first, last)] positions -> '16-24, 30' in frame numbers ('' when none)."""
    return _ranges([fids[i] for a, b in runs for i in range(a, b + 1)]) if runs else ""


def _refuse_duplicate_names(where: Path, names: list[str]) -> None:
    """Two objects with one name cannot be told apart by labels, prompts or motions."""
    dups = sorted({n for n in names if names.count(n) > 1})
    if dups:
        raise InputError(f"{where}: object name(s) {dups} are used for more than one object; give every object its "
                         "own name (mapping.yaml) and run `interreal masks` again")


def with_auto(labels: np.ndarray, layer: AutoLayer | None, pos: int, n_obj: int) -> np.ndarray:
    """A tracked index map with the auto layer of frame `pos` added as the ignore class (n_obj + 1) where no object
    is: a part in motion is not a transient."""
    extra = layer.full(pos, (labels.shape[1], labels.shape[0])) if layer is not None else None
    if extra is None:
        return labels
    out = labels.copy()
    out[extra & (labels == 0)] = n_obj + 1
    return out


def auto_figures(layer: AutoLayer | None, fids: list[str], mode: str, no_model: str | None) -> dict[str, Any]:
    """The report's account of the auto layer: how the hands were found, where, and what each cue cost."""
    if layer is None:
        return {"mode": mode, "ran": False, **({"why_not": no_model} if no_model else {})}
    return {"mode": mode, "ran": True, "hands_found": round(layer.track.found_share(), 4),
            "found_by": shares(layer.track), "frames": len(layer.masks), "carried": len(layer.carried),
            "leaked": [fids[p] for p in layer.leaked], "seconds": layer.seconds}


def transient_line(figures: dict[str, Any]) -> str | None:
    """One line on the transient layer a masks run wrote (painted and automatic), None when it wrote none and
    tried nothing."""
    tr = figures.get("transients") or {}
    auto = tr.get("auto") or {}
    if not tr.get("frames") and not auto.get("ran"):
        return None
    how = []
    if tr.get("ignore_keyframes"):
        how.append(f"painted on {len(tr['ignore_keyframes'])} keyframes")
    if auto.get("ran"):
        carried = f", carried by the flow to {auto['carried']} more" if auto.get("carried") else ""
        how.append(f"auto: a hand found on {100 * auto['hands_found']:.0f} % of the frames{carried}")
    return (f"transients: {tr.get('frames', 0)} frames, {100 * tr.get('mean_share', 0.0):.1f} % of the pixels on "
            f"average (at most {100 * tr.get('max_share', 0.0):.0f} %)" + (f" ({'; '.join(how)})" if how else ""))


def left_view_lines(figures: dict[str, Any]) -> list[str]:
    """One line per object that left the view over the image border (its masks blank there, not lost)."""
    return [f"{name}: out of the view at frames {frames} (it left over the image border; not lost)"
            for name, frames in (figures.get("left_view") or {}).items() if frames]


def _write_frame(ds: Path, fid: str, image_name: str, labels: np.ndarray, n_obj: int, dilate: int) -> None:
    """One frame's files: its mask, its transient layer (when any) and its SfM mask."""
    objects, transient = split_labels(labels, n_obj)
    write_mask(ds, fid, index_to_onehot(objects, n_obj))
    if transient.any():
        write_transient(ds, fid, transient)
    _write_sfm_mask(ds, image_name, labels, dilate)  # transients left out like objects


def _write_sfm_mask(ds: Path, image_name: str, labels: np.ndarray, dilate: int) -> None:
    """COLMAP mask `sfm_masks/<image name>.png`: 255 = use the pixel for SfM, 0 = object (moves), ignore."""
    obj = (labels > 0).astype(np.uint8)
    if dilate > 0 and obj.any():
        obj = cv2.dilate(obj, disk(dilate))
    atomic.write_image(ds / SFM_MASKS_DIR / f"{image_name}.png", np.where(obj > 0, 0, 255).astype(np.uint8))


def _ranges(fids: list[str]) -> str:
    nums = sorted(int(f) for f in fids)
    out, start, prev = [], nums[0], nums[0]
    for n in nums[1:] + [None]:
        if n is not None and n == prev + 1:
            prev = n
            continue
        out.append(f"{start}" if start == prev else f"{start}-{prev}")
        if n is not None:
            start = prev = n
    return ", ".join(out[:8]) + (" ..." if len(out) > 8 else "")
