"""Keyframe-to-keyframe propagation of soft object maps with dense flow.

Between two keyframes a and b each frame gets two predictions: one warped forward from a, one warped
backward from b. Each carries a trust map (the weakest forward-backward consistency along its chain, zero
where the source left the image). They are fused by trust and temporal distance; where the two disagree
over a whole region, a colour vote (the keyframes' colour models) picks the chain that fits. Then they are
refined on the full-size image with a guided filter, and turned into exclusive labels by argmax
(background last). Keyframes re-anchor every chain, so drift never spans more than one gap. Before the
first keyframe only the backward chain exists, after the last only the forward one; there the colour model is
the only anchor to the keyframe and weighs as much as it separated the labels on the keyframe itself, and at
every step mask pixels whose flow follows the background's motion rather than their object's are taken out of
the object (`TrackConfig.motion_one_sided`; `motion` between keyframes, off by default), pixels next to it that
move with it and have its colours join it (`grow`), and a GrabCut of the frame moves its boundary where the
keyframe's colours agree (`cut`); the colours a joining pixel must have are the keyframe's colours near it, carried
with the object (`local_colour`); between keyframes growth may take the pixels the chain does not know from its
keyframe (`grow_between`, off by default). These chains also watch each object's mask: when it collapses, the
object is searched for by its keyframe's appearance and put back where it is found (`redetect`), since no later
keyframe will bring a lost object back.

Soft maps (not binary) are warped: bilinear warping of a binary mask rounds every step and erodes thin
parts; warping probabilities keeps sub-pixel boundaries, and a per-step guided filter plus a mild
sharpening keeps them from blurring out over many steps.
"""

from __future__ import annotations

import threading
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, Collection, Iterable, Iterator

import cv2
import numpy as np

from ..conventions import UNANNOTATED
from ..images import at_size
from .appearance import AppearanceConfig, ColourModel, LocalColour, heldout_information, joint_log_table
from .flow import FlowConfig, FlowEngine, Step, make_step, sampling_grid
from .evidence import StepEvidence
from .redetect import Event, RedetectConfig, Redetector
from .reuse import Segment, chain_segments
from .soft import (anchor_soft, argmax_channels, argmax_labels, channels_to_labels, chsum, fill_untrusted,
                   filter_objects)
from .workframes import WORK_LONG_SIDE, FrameCache, work_size

__all__ = ["TrackConfig", "FrameResult", "Propagator", "median_motion", "FrameCache", "WORK_LONG_SIDE",
           "work_size", "anchor_soft", "filter_objects", "chsum"]


# frames between two keyframes over which a gap's stored chain is kept at half precision and only its forward
# Steps are made ahead (memory)
LONG_GAP = 100


@dataclass(frozen=True)
class TrackConfig:
    """Propagation settings (`interreal masks --help` lists the user-facing ones)."""

    flow: FlowConfig = field(default_factory=FlowConfig)
    appearance: AppearanceConfig = field(default_factory=AppearanceConfig)
    work_long_side: int = -1         # flow and propagation resolution (long side, px); 0 = full size, -1 = WORK_LONG_SIDE
    fill_radius: int = 7             # untrusted pixels take the trusted neighbourhood's value within this radius
    # between keyframes, plain pixels the flow carries their colour to keep its label and are not filled
    # (`FrameCache.flow_kept`): a plain door's inside is untrusted flow whose trusted neighbours are its rim and the
    # background, and the fill ate it step by step
    fill_plain: bool = True
    refine_radius: int = 3           # guided filter radius at work resolution (0 = no per-step refinement)
    refine_eps: float = 0.02         # guided filter regulariser (on [0, 1] intensities, squared)
    sharpen: float = 2.0             # per-step exponent on the soft map (1 = none); counters warping blur
    out_radius: int = 2              # guided filter radius at full size for the final labels (0 = off)
    rigid: float = 1.0               # blend of a per-object homography (fit to the flow inside the object) into the warp
    # exponent on the per-pixel motion evidence (object vs background homography) on the chains between two
    # keyframes; 0 = off: fusion and the colour vote already correct those chains (docs/measurements.md)
    motion: float = 0.0
    # the same on the chains before the first and after the last keyframe, where no second keyframe and no fusion
    # correct a mask that slid onto the background
    motion_one_sided: float = 0.5
    # on the same chains, pixels next to an object that move with it and have its colours join it (`_grow`): the
    # share of their probability moved to the object (0 = off)
    grow: float = 0.8
    # `_grow` on the chains between two keyframes too (0 = off), only into pixels the chain knows nothing of (a
    # surface that turns into view and is hidden again at the next keyframe); off: cars on long gaps lose
    grow_between: float = 0.0
    # `_grow`'s colour test by the keyframe's colours near each pixel (`appearance.LocalColour`, carried with the
    # object) rather than over the whole keyframe: a car's shadow is as dark as its underside, but not next to it
    local_colour: bool = True
    # on the same chains, the share of each object's probability set by a GrabCut of the frame itself (`_cut`;
    # 0 = off)
    cut: float = 0.5
    fusion: bool = True              # fuse forward and backward chains (False = forward only where possible)
    min_weight: float = 0.05         # weight floor so a fully untrusted chain still counts a little
    vote: float = 8.0                # colour vote of disagreeing chains: loser weight x exp(-vote * margin); 0 = off
    vote_margin: float = 1.0         # mean log-likelihood margin (nats per pixel) below which a region's vote abstains
    vote_min_px: int = 40            # smallest disagreement region (work-res pixels, after an opening) that votes
    prefetch: int = 12               # flow pairs decoded and computed ahead on a worker thread (0 = inline)
    # re-detection of an object whose mask collapsed, from its keyframe's appearance (`redetect`)
    redetect: RedetectConfig = field(default_factory=RedetectConfig)


@dataclass
class FrameResult:
    """What the driver yields per frame: exclusive labels at full size, plus what confidence needs."""

    pos: int
    labels: np.ndarray                      # (H, W) uint8 index map, 0 = background, k = object k-1
    keyframe: bool = False
    soft: np.ndarray | None = None          # (h, w, K+1) fused soft map at work resolution
    fwd: np.ndarray | None = None           # (h, w) uint8 labels of the forward chain alone (work res)
    bwd: np.ndarray | None = None           # (h, w) uint8 labels of the backward chain alone
    trust: np.ndarray | None = None         # (h, w) trust of the last step(s) into this frame
    dist: tuple[int | None, int | None] = (None, None)  # frames from the previous / next keyframe
    # (K,) on chains before the first / after the last keyframe: how much each object's area grew since the keyframe
    # by its own motion (product of its homographies' area scales; 1 where none was trusted)
    scale: np.ndarray | None = None


class Propagator(StepEvidence):
    """Runs the chains over a sequence. `load(pos)` returns the full-size RGB uint8 image of frame `pos`."""

    def __init__(self, load: Callable[[int], np.ndarray], n_frames: int, size: tuple[int, int],
                 n_objects: int, cfg: TrackConfig):
        self.n = n_frames
        self.size = size  # (W, H) full
        self.k = n_objects
        self.cfg = cfg
        self.wsize = work_size(size[0], size[1], WORK_LONG_SIDE if cfg.work_long_side < 0 else cfg.work_long_side)
        self.cache = FrameCache(load, self.wsize, cfg.appearance.bins)
        self.flow = FlowEngine(cfg.flow)
        self.grid = sampling_grid(self.wsize[1], self.wsize[0])
        self._flows: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.flow_pairs = 0
        # Decoding and flow run one step ahead on a worker thread (OpenCV releases the GIL), so the chain's own
        # work (warps, filters, fusion) overlaps them: the second core is otherwise idle most of the time.
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="flow") if cfg.prefetch > 0 else None
        # full-size labels of the chains with no second keyframe, one frame behind them (`_labels_later`)
        self._out = ThreadPoolExecutor(1, thread_name_prefix="labels") if cfg.prefetch > 0 else None
        self._lock = threading.Lock()  # the forward chain of the next gap asks for flows from its own thread
        self._plan: list[int] = []
        self._ahead: dict[int, Future] = {}  # planned or requested, not yet stored
        # per planned pair, the directions its chains step in ((t, t+1) forward, (t+1, t) backward): the worker
        # makes those Steps beside the flows, off the chains' thread (first frame only: 10 % of its time)
        self._dirs: dict[int, tuple[tuple[int, int], ...]] = {}
        self._steps: dict[tuple[int, int], Step] = {}  # made ahead, each taken once by `step`
        self._models: dict[int, Future] = {}  # keyframe -> its colour model (`_keyframe_model`)
        self._decoded: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # worker-only: the last decoded frame
        self.motion: dict[int, float] = {}  # pair t -> median flow t -> t+1, as a fraction of the work width
        self.redetections: list[Event] = []  # every chain's re-detections (positions, objects), for the report
        self.refusals: list[Event] = []  # ... and its refused colour finds
        self.exits: list[Event] = []  # ... and where an object left the view over the image border

    # -- flow -------------------------------------------------------------------------------------------
    def pair(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """(flow t -> t+1, flow t+1 -> t), computed once per pair (thread-safe)."""
        if self._pool is None:
            if t not in self._flows:
                self._store(t, *self._compute_pair(t))
            return self._flows[t]
        with self._lock:
            if t in self._flows:
                return self._flows[t]
            fut = self._ahead.get(t)
            if fut is None:
                fut = self._ahead[t] = self._pool.submit(self._compute_pair, t)
        flows, images, motion, steps = fut.result()
        with self._lock:
            if t not in self._flows:
                self._store(t, flows, images, motion, steps)
                self._ahead.pop(t, None)
                self._pump()
            return self._flows[t]

    def _store(self, t: int, flows, images, motion: float, steps: dict) -> None:
        self._flows[t] = flows
        self._steps.update(steps)
        self.motion[t] = motion
        for pos, (full, work) in images.items():
            self.cache.put(pos, full, work)
        self.flow_pairs += 1

    def release(self, pair: int | None = None, frame: int | None = None) -> None:
        """Forget a flow pair and / or a frame no chain will ask for again (memory stays one or two gaps)."""
        with self._lock:
            if pair is not None:
                self._flows.pop(pair, None)
                self._steps.pop((pair, pair + 1), None)
                self._steps.pop((pair + 1, pair), None)
            if frame is not None:
                self.cache.drop(frame)

    def plan(self, pairs: Iterable[int], dirs: dict[int, tuple[tuple[int, int], ...]] | None = None) -> None:
        """The flow pairs the next chain will ask for, in order: the worker computes them ahead, with the Steps
        of the directions `dirs` gives for a pair ((src, dst) each)."""
        if self._pool is None:
            return
        with self._lock:
            for fut in self._ahead.values():
                fut.cancel()
            self._ahead.clear()
            self._plan = list(pairs)[::-1]  # a stack: next pair last
            self._dirs = dict(dirs or {})
            self._pump()

    def _pump(self) -> None:  # called with the lock held
        while self._plan and len(self._ahead) < self.cfg.prefetch:
            t = self._plan.pop()
            if t not in self._flows and t not in self._ahead:
                self._ahead[t] = self._pool.submit(self._compute_pair, t)

    def _compute_pair(self, t: int):
        """Decode frames t and t+1 (the previous pair's frame is reused), then both flows; on the worker thread
        when prefetching, else inline."""
        images = {}
        for pos in (t, t + 1):
            if pos not in self._decoded:
                full = self.cache.load(pos)
                work = at_size(full, self.wsize)
                self._decoded = {k: v for k, v in self._decoded.items() if k in (t, t + 1)}
                self._decoded[pos] = (full, work)
            images[pos] = self._decoded[pos]
        a, b = images[t][1], images[t + 1][1]
        fwd = self.flow(a, b)
        bwd = self.flow(b, a)
        steps = {d: self._make_step(d[0], d[1], fwd, bwd) for d in self._dirs.get(t, ())}
        return (fwd, bwd), images, median_motion(fwd), steps  # motion: off the chains' path

    def close(self) -> None:
        if self._pool is not None:
            self.plan([])
            self._pool.shutdown(wait=True)
        if self._out is not None:
            self._out.shutdown(wait=True, cancel_futures=True)

    def step(self, src: int, dst: int) -> Step:
        """The Step from frame src to its neighbour dst: the one the worker made ahead, else made here."""
        f, b = self.pair(min(src, dst))
        with self._lock:
            st = self._steps.pop((src, dst), None)
        return st if st is not None else self._make_step(src, dst, f, b)

    def _make_step(self, src: int, dst: int, f: np.ndarray, b: np.ndarray) -> Step:
        """f, b: the pair's flows (min -> max, max -> min)."""
        if dst > src:   # forward in time: pull with flow (t+1 -> t), check with (t -> t+1)
            return make_step(b, f, self.grid, self.cfg.flow)
        return make_step(f, b, self.grid, self.cfg.flow)

    # -- one step of one chain ----------------------------------------------------------------------------
    def advance(self, soft: np.ndarray, acc: np.ndarray, src: int, dst: int, model: ColourModel | None,
                motion: float | None = None, grow: float = 0.0, local: LocalColour | None = None,
                one_sided: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Warp (soft, accumulated trust) from src to dst; untrusted pixels are filled from trusted neighbours.
        motion: the exponent of the motion evidence (`TrackConfig.motion` when None); grow: `_grow`'s strength.
        one_sided: the chain has no second keyframe (GrabCut may run, growth takes any pixel); False between
        keyframes, where growth takes only the pixels the chain does not know from its keyframe.
        Returns the soft map, the accumulated trust, this step's trust and each object's area scale (`_rigid`)."""
        st = self.step(src, dst)
        motion = self.cfg.motion if motion is None else motion
        grow = grow if model is not None else 0.0
        if motion > 0 or grow > 0:
            fits = self._plane_fits(soft, st)
            if fits[0] is not None:
                if motion > 0:
                    soft = self._motion_evidence(soft, st, fits, motion)
                if grow > 0:
                    known = None if one_sided else acc[..., 0] * acc[..., 1]
                    soft = self._grow(soft, st, fits, model, self.cache.bins(src), grow, local, self.cache.work(src),
                                      known)
        warped = st.warp(soft)
        trust = st.trust
        scale = np.ones(self.k)
        hs: list = [None] * self.k
        if self.cfg.rigid > 0:
            warped, trust, scale, hs = self._rigid(soft, st, warped, trust)
        if local is not None:
            local.warp(hs, st.map_x, st.map_y)
        # (weakest-link trust along the chain, 'seen': the chain started inside the anchor's annotation).
        # A minimum rather than a product: a product decays to nothing over a long gap even on perfect
        # tracking, and then the temporal weights alone decide the fusion.
        acc = st.warp(acc)
        acc[..., 0] = np.minimum(acc[..., 0], trust)
        if self.cfg.fill_radius > 0:
            keep = self.cache.flow_kept(src, dst, st.warp) if self.cfg.fill_plain and not one_sided else None
            warped = fill_untrusted(warped, trust, self.cfg.fill_radius, keep)
        outside = chsum(warped)[..., 0] < 1e-3
        warped[outside, -1] = 1.0  # nothing to pull from (left the image): background until a keyframe says otherwise
        image = self.cache.work(dst)
        if model is not None:
            warped = warped * model.ratio(self.cache.bins(dst))
            warped /= chsum(warped)
        soft = self.refine(warped, image)
        if one_sided and grow > 0 and self.cfg.cut > 0:
            soft = self._cut(soft, image, model, self.cache.bins(dst))
        return soft, acc, trust, scale

    def refine(self, soft: np.ndarray, image: np.ndarray) -> np.ndarray:
        cfg = self.cfg
        if cfg.refine_radius > 0:
            guide = image.astype(np.float32) / 255.0  # colour guide: grey loses edges between equally bright colours
            # a filter object built once, then applied: 40 % cheaper than the one-call form (measured, OpenCV 5)
            gf = cv2.ximgproc.createGuidedFilter(guide, cfg.refine_radius, cfg.refine_eps)
            soft = filter_objects(gf.filter, soft)
        soft = np.clip(soft, 1e-4, None)
        if cfg.sharpen != 1.0:
            soft = soft ** cfg.sharpen
        return (soft / chsum(soft)).astype(np.float32, copy=False)

    # -- output ------------------------------------------------------------------------------------------
    def labels_full(self, soft: np.ndarray, pos: int) -> np.ndarray:
        """Work-size soft map -> full-size exclusive labels, boundaries snapped to the full-size image."""
        return self._labels_of(soft, self.cache.full(pos))

    def _labels_later(self, soft: np.ndarray, pos: int) -> Future:
        """`labels_full` on the output thread (done at once without prefetching); the image is taken now, while
        the frame is still cached."""
        if self._out is None:
            done: Future = Future()
            done.set_result(self.labels_full(soft, pos))
            return done
        return self._out.submit(self._labels_of, soft, self.cache.full(pos))

    def _labels_of(self, soft: np.ndarray, full: np.ndarray) -> np.ndarray:
        w, h = self.size
        if (soft.shape[1], soft.shape[0]) != (w, h):
            soft = filter_objects(lambda x: cv2.resize(x, (w, h), interpolation=cv2.INTER_LINEAR), soft)
        r = self.cfg.out_radius
        if r > 0:
            grey = cv2.cvtColor(full, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
            scale = max(1, round(w / self.wsize[0]))
            sub = 0.5 if w >= 2 * self.wsize[0] else 1.0  # fast guided filter only when full size is much larger
            soft = filter_objects(lambda x: cv2.ximgproc.guidedFilter(grey, x, r * scale, self.cfg.refine_eps,
                                                                      dDepth=-1, scale=sub), soft)
        return argmax_labels(soft)

    # -- the whole sequence --------------------------------------------------------------------------------
    def run(self, anchors: dict[int, np.ndarray], skip: Collection[Segment] = ()) -> Iterator[FrameResult]:
        """A FrameResult for every frame (keyframes last) in chain order, but those `skip`'s stretches hold."""
        try:
            yield from self._run(anchors, set(skip))
        finally:
            self.close()

    def _run(self, anchors: dict[int, np.ndarray], skip: set[Segment]) -> Iterator[FrameResult]:
        keys = sorted(anchors)
        todo = [s for s in chain_segments(keys, self.n) if s not in skip]
        gaps, kinds = [(s.a, s.b) for s in todo if s.kind == "gap"], {s.kind for s in todo}
        # every flow pair in the order the chains below ask for it: the worker runs ahead across chains and gaps
        before = range(keys[0] - 1, -1, -1) if "before" in kinds else range(0)
        between = [t for a, b in gaps for t in range(a, b)]
        after = range(keys[-1], self.n - 1) if "after" in kinds else range(0)
        # a gap's backward Steps wait for its backward chain, made while the forward chain passes (1.5 MB each at
        # 480 px): on a long gap only the forward ones are made ahead, as the stored chain turns float16 there
        long_gap = {t for a, b in gaps if b - a > LONG_GAP for t in range(a, b)}
        dirs = {t: ((t + 1, t),) for t in before} | \
            {t: ((t, t + 1),) if t in long_gap else ((t, t + 1), (t + 1, t)) for t in between} | \
            {t: ((t, t + 1),) for t in after}
        self.plan([*before, *between, *after], dirs)
        soft0 = {k: anchor_soft(anchors[k], self.k, self.wsize) for k in keys}
        arrivals: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {k: [] for k in keys}
        # The forward chain of the next gap runs on its own thread while this gap's backward chain and fusion run
        # here: with flows on a third thread, both cores stay busy (keyframe every 10 frames: 1.5x faster).
        chains = ThreadPoolExecutor(1, thread_name_prefix="chain") if self._pool is not None and gaps else None

        def launch(g: int) -> Future:
            a, b = gaps[g]
            if chains is not None:
                return chains.submit(self._forward, a, b, soft0[a], soft0[b], arrivals)
            done: Future = Future()
            done.set_result(self._forward(a, b, soft0[a], soft0[b], arrivals))
            return done

        try:
            ahead = launch(0) if gaps else None
            # before the first keyframe: backward chain only
            yield from self._one_sided(keys[0], before, soft0[keys[0]], arrivals, nxt=True)
            for g, (a, b) in enumerate(gaps):
                fwd, model_a = ahead.result()
                ahead = launch(g + 1) if g + 1 < len(gaps) else None
                yield from self._backward(a, b, fwd, model_a, soft0[a], soft0[b], arrivals)
        finally:
            if chains is not None:
                chains.shutdown(wait=True, cancel_futures=True)
        yield from self._one_sided(keys[-1], range(keys[-1] + 1, self.n) if "after" in kinds else range(0),
                                   soft0[keys[-1]], arrivals, nxt=False)
        for k in keys:
            yield self._keyframe(k, anchors[k], arrivals[k])

    def _start(self, k: int, soft_known) -> tuple[np.ndarray, np.ndarray, ColourModel | None]:
        """A chain's start at keyframe k (soft_known: its anchor, `anchor_soft`): soft map, trust / seen, and the
        keyframe's colour model (None when appearance is off)."""
        soft, known = soft_known
        model = self._keyframe_model(k, soft, known) if self.cfg.appearance.weight > 0 else None
        known = known.astype(np.float32)
        return soft.copy(), np.stack([known, known], -1), model

    def _keyframe_model(self, k: int, soft: np.ndarray, known: np.ndarray) -> ColourModel:
        """Keyframe k's colour model, fit once: the chains that end a gap at k and start the next from it (on two
        threads, at the same time) share it (18 ms a fit at 480 px; a keyframe every 10 frames: 16 fits -> 8)."""
        with self._lock:
            fut = self._models.get(k)
            mine = fut is None
            if mine:
                fut = self._models[k] = Future()
        if mine:
            try:
                fut.set_result(ColourModel.fit(self.cache.work(k), soft, known, self.cfg.appearance))
            except BaseException as exc:
                fut.set_exception(exc)
        return fut.result()

    def _watch(self, k: int, soft_known, one_sided: bool) -> Redetector | None:
        """The re-detection memory of a chain that starts at keyframe k (None when re-detection is off for it)."""
        rd = self.cfg.redetect
        if not rd.enabled or not (one_sided or rd.between_keyframes):
            return None
        return Redetector(self.cache.work(k), soft_known[0], soft_known[1], self.cfg.redetect, self.cfg.appearance,
                          self.k)

    def _recheck(self, watch: Redetector | None, soft: np.ndarray, t: int, prev: int) -> np.ndarray:
        """A chain's soft map at frame t (reached from its neighbour prev) after its collapsed objects were searched
        for (`redetect`)."""
        if watch is None:
            return soft
        n, r, e = len(watch.events), len(watch.refusals), len(watch.exits)
        f, b = self.pair(min(prev, t))
        soft = watch.check(soft, self.cache.work(t), self.cache.bins(t), t,
                           lambda region, remnant: self._moves_apart(t, prev, region, remnant),
                           f if t > prev else b)
        self.refusals.extend(watch.refusals[r:])
        self.exits.extend(watch.exits[e:])
        if len(watch.events) > n:
            self.redetections.extend(watch.events[n:])
            soft = self.refine(soft, self.cache.work(t))
        return soft

    def _local(self, k: int, start, model, grow: float) -> LocalColour | None:
        """The keyframe's colours near each pixel for a chain from keyframe k that grows (`_grow`), else None."""
        if model is None or grow <= 0 or not self.cfg.local_colour:
            return None
        return LocalColour.fit(self.cache.work(k), start[0], start[1])

    def _one_sided(self, k: int, order: range, start, arrivals, nxt: bool) -> Iterator[FrameResult]:
        if not len(order):  # no frame on that side (or an earlier run's: `reuse`)
            return
        soft, acc, model = self._start(k, start)
        app = self.cfg.appearance
        if model is not None and app.adaptive:
            # no second keyframe will correct this chain: the colour model is its only anchor to the keyframe,
            # weighed by what it proved to tell apart there (never below the configured weight)
            info = heldout_information(self.cache.work(k), start[0], start[1], app)
            if info > app.weight:
                model = model.reweighted(info)
        watch = self._watch(k, start, one_sided=True)
        local = self._local(k, start, model, self.cfg.grow)
        prev, scale = k, np.ones(self.k)
        held: FrameResult | None = None  # the previous frame, its full-size labels still being made
        for i, t in enumerate(order):
            soft, acc, trust, step_scale = self.advance(soft, acc, prev, t, model, self.cfg.motion_one_sided,
                                                        self.cfg.grow, local)
            scale = scale * step_scale
            soft = self._recheck(watch, soft, t, prev)
            lab = argmax_labels(soft)
            dist = (None, i + 1) if nxt else (i + 1, None)
            # frame t's full-size labels are made on a thread of their own while this chain takes its next step
            res = FrameResult(t, self._labels_later(soft, t), soft=soft, fwd=None if nxt else lab,
                              bwd=lab if nxt else None, trust=trust, dist=dist, scale=scale)
            if held is not None:
                yield _resolved(held)
            held = res
            self.release(pair=min(prev, t), frame=prev if prev != k else None)
            prev = t
        if held is not None:
            yield _resolved(held)
        self.release(frame=prev if prev != k else None)

    def _forward(self, a: int, b: int, start_a, start_b, arrivals) -> tuple[dict, ColourModel | None]:
        """The forward chain over the gap (a, b), stored for the backward pass to fuse with."""
        fwd: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.pair(a)  # decodes frame a (the colour model's image) with its flow pair
        soft, acc, model = self._start(a, start_a)
        watch = self._watch(a, start_a, one_sided=False)
        local = self._local(a, start_a, model, self.cfg.grow_between)
        store = np.float32 if b - a <= LONG_GAP else np.float16  # long gaps: halve the memory of the stored chain
        for t in range(a + 1, b):
            soft, acc, trust, _ = self.advance(soft, acc, t - 1, t, model, None, self.cfg.grow_between, local, False)
            soft = self._recheck(watch, soft, t, t - 1)
            fwd[t] = (soft.astype(store), acc.astype(store), trust.astype(store))
        if b > a + 1 and (start_b[1] < 1).any():
            s, c, *_ = self.advance(soft, acc, b - 1, b, model)
            arrivals[b].append((s, c))
        else:
            self.pair(b - 1)  # the backward chain's first step: now, while frame b-1 is still decoded
        return fwd, model

    def _backward(self, a: int, b: int, fwd: dict, model_a: ColourModel | None, start_a, start_b,
                  arrivals) -> Iterator[FrameResult]:
        """The backward chain over the gap (a, b), fused frame by frame with the stored forward chain."""
        soft, acc, model = self._start(b, start_b)
        watch = self._watch(b, start_b, one_sided=False)
        local = self._local(b, start_b, model, self.cfg.grow_between)
        voting = self.cfg.vote > 0 and model is not None and model_a is not None
        table = joint_log_table([model_a, model]) if voting else None
        span = b - a
        for t in range(b - 1, a, -1):
            soft, acc, trust, _ = self.advance(soft, acc, t + 1, t, model, None, self.cfg.grow_between, local, False)
            soft = self._recheck(watch, soft, t, t + 1)
            sf, cf, tf = (x.astype(np.float32, copy=False) for x in fwd.pop(t))
            lf, lb = argmax_channels(sf), argmax_channels(soft)
            if self.cfg.fusion:
                # a chain whose pixel came from outside its keyframe's view (or an unannotated part) knows
                # nothing there: weight zero, whatever its distance
                wf = (b - t) / span * cf[..., 1] * (cf[..., 0] + self.cfg.min_weight)
                wb = (t - a) / span * acc[..., 1] * (acc[..., 0] + self.cfg.min_weight)
                none = (wf + wb) < 1e-6
                wf[none], wb[none] = (b - t) / span, (t - a) / span
                if table is not None:
                    wf, wb = self._vote(lf, lb, wf, wb, self.cache.bins(t), table)
                fused = (wf[..., None] * sf + wb[..., None] * soft) / (wf + wb)[..., None]
            else:
                fused = sf
            c = sf.shape[-1]
            yield FrameResult(t, self.labels_full(fused, t), soft=fused, fwd=channels_to_labels(lf, c),
                              bwd=channels_to_labels(lb, c), trust=0.5 * (tf + trust), dist=(t - a, b - t))
            self.release(pair=t, frame=t)  # the next gap's forward chain starts at b: it never needs t
        if b > a + 1 and (start_a[1] < 1).any():
            s, c, *_ = self.advance(soft, acc, a + 1, a, model)
            arrivals[a].append((s, c))
        self.release(pair=a, frame=a)

    def _vote(self, lf: np.ndarray, lb: np.ndarray, wf: np.ndarray, wb: np.ndarray, bins: np.ndarray,
              table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where the chains disagree over a region, the one whose labels fit the keyframes' colours wins it.

        lf, lb: (h, w) channel index of each chain's most likely label; bins: the frame's colour bins.
        Temporal distance and flow trust cannot settle two confident chains that disagree (a door swinging
        shut just before the next keyframe: the backward chain confidently tracks the background over the
        door's face). Each connected region of disagreement votes once, with the mean colour log-likelihood
        of each chain's labels there; thin boundary slivers (removed by an opening) and close calls abstain.
        """
        dis_full = lf != lb
        rows, cols = np.flatnonzero(dis_full.any(1)), np.flatnonzero(dis_full.any(0))
        if not len(rows):
            return wf, wb
        # only the box around the disagreement (a small part of the frame), with a margin past the 5x5 kernel's
        # reach: the opening, the components and the growing back are the same there as on the whole frame
        pad = 4
        win = (slice(max(rows[0] - pad, 0), rows[-1] + pad + 1), slice(max(cols[0] - pad, 0), cols[-1] + pad + 1))
        lf, lb, bins, dis = lf[win], lb[win], bins[win], dis_full[win]
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
        q = bins[dis]
        diff = np.zeros(lf.shape, np.float32)
        diff[dis] = table[q, lf[dis]] - table[q, lb[dis]]  # only where the chains disagree: a small part
        m = np.zeros(lf.shape, np.float32)
        # one region per (forward label, backward label) pair: a part that sits in different places in the two
        # chains makes two regions side by side (door here / background there, and the reverse) that vote apart
        pair = np.where(dis, lf.astype(np.int32) * (self.k + 1) + lb, -1)
        for code in np.unique(pair[dis]):
            sel = (pair == code).astype(np.uint8)
            core = cv2.morphologyEx(sel, cv2.MORPH_OPEN, kernel)
            if int(core.sum()) < self.cfg.vote_min_px:
                continue
            n, comp = cv2.connectedComponents(core, connectivity=8)
            count = np.bincount(comp.ravel(), minlength=n)
            mean = np.bincount(comp.ravel(), weights=diff.ravel(), minlength=n) / np.maximum(count, 1)
            mean[(count < self.cfg.vote_min_px) | (np.arange(n) == 0)] = 0.0
            margin = np.sign(mean) * np.clip(np.abs(mean) - self.cfg.vote_margin, 0.0, None)
            # the vote covers the whole region, not only its opened core: grow the cores back over it
            grown = cv2.dilate(comp.astype(np.float32), kernel).astype(np.int32)
            m = np.where(sel > 0, margin[grown], m).astype(np.float32)
        if m.any():
            wf, wb = wf.copy(), wb.copy()
            wf[win] *= np.exp(-self.cfg.vote * np.clip(-m, 0.0, None))
            wb[win] *= np.exp(-self.cfg.vote * np.clip(m, 0.0, None))
        return wf, wb

    def _keyframe(self, k: int, index_map: np.ndarray, arr: list) -> FrameResult:
        """A keyframe is its annotation; pixels marked 255 take the chains that arrive there (else background)."""
        labels = index_map.copy()
        unknown = labels == UNANNOTATED
        if unknown.any():
            if arr:
                num = sum(s * (c[..., 1:2] * (c[..., 0:1] + self.cfg.min_weight) + 1e-6) for s, c in arr)
                self.cache.keep_only({k})
                fill = self.labels_full(num, k)
            else:
                fill = np.zeros_like(labels)
            labels[unknown] = fill[unknown]
        return FrameResult(k, labels, keyframe=True, dist=(0, 0))


def _resolved(res: FrameResult) -> FrameResult:
    """A FrameResult whose labels were a Future, with them in place (an error there is raised here)."""
    res.labels = res.labels.result()
    return res


def median_motion(flow: np.ndarray, stride: int = 4) -> float:
    """Median displacement of a (h, w, 2) flow field as a fraction of its width: how far the view moved."""
    f = flow[::stride, ::stride]
    return float(np.median(np.sqrt(f[..., 0] ** 2 + f[..., 1] ** 2))) / flow.shape[1]
