"""Frame selection: `interreal frames INPUT DS` -> DS/images/frame_<source index>.png.

Why not ns-process-data's ffmpeg `thumbnail` filter: it picks by histogram, so blurred frames survive and a camera
that stands still yields runs of identical frames. Here one cheap analysis pass (at <= 640 px) scores each frame's
sharpness (variance of the Laplacian), texture (FAST corners) and motion from the previous frame (DIS optical flow on
160 px thumbnails). Windows are cut by *cumulative motion* (plus a little time, so a static shot still yields frames),
the sharpest usable frame of each window is taken, and a frame that barely moved from the last kept one is dropped.
A second pass decodes only the chosen frames at the working size (long side <= 1600 by default).

Image folders keep every image (index = position in name order) unless a target or spacing is given.
"""

from __future__ import annotations

import shutil
import sys
import time
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import cv2
import numpy as np

from . import atomic
from .conventions import IMAGES_DIR, frame_name
from .errors import InputError
from .ingest import Source, open_source
from .options import add_flags, config_from, option, values_from_args
from .provenance import source_key
from .report import StageReport, finished_with, fingerprint, tree_fingerprint, warning_lines

DEFAULT_VIDEO_TARGET = 300  # ns-process-data's default, so datasets are comparable


@dataclass
class FrameStats:
    """Per source frame, from the analysis pass."""

    sharpness: np.ndarray  # variance of the Laplacian at the analysis size
    corners: np.ndarray  # FAST corner count
    brightness: np.ndarray  # mean grey level
    motion: np.ndarray  # median flow from the previous frame, fraction of the image width (0 for the first)
    contrast: np.ndarray | None = None  # grey-level standard deviation (None: not measured)

    def reasons(self) -> np.ndarray:
        """(N,) why each frame is unusable ("" when it is usable): black (mean under BLACK levels), blank (grey
        levels within BLANK_STD: a lens cap, a white wall out of focus), or blurred beyond use (sharpness under
        BLUR_SHARE of the video's own median). Few corners is no reason: a plain dishwasher on a wood floor, or a
        plain door filling the view, has few in every frame, and those frames show the part (SfM may still leave
        them without a camera; `poses` names them)."""
        n = len(self.brightness)
        out = np.full(n, "", dtype=object)
        blank = self.corners == 0 if self.contrast is None else self.contrast <= BLANK_STD
        blurred = self.sharpness < BLUR_SHARE * float(np.median(self.sharpness))
        for reason, hit in (("blurred", blurred), ("blank", blank), ("black", self.brightness <= BLACK)):
            out[hit] = reason  # the last, most basic reason wins
        return out

    @property
    def usable(self) -> np.ndarray:
        """Not black, not blank, not blurred beyond the video's own frames."""
        return self.reasons() == ""


BLACK = 8.0  # mean grey level at or under which a frame is black
BLANK_STD = 2.0  # grey-level spread at or under which a frame is blank (a lens cap, a white wall out of focus)
BLUR_SHARE = 0.1  # a frame this much blurrier than the video's median is blurred beyond use


@dataclass
class FramesConfig:
    """Settings of one `interreal frames` run: its flags (and `interreal process`'s) and `extract_frames`'s keyword
    options; they all enter the resume fingerprint."""

    target: int | None = option(None, f"number of frames to select (video default {DEFAULT_VIDEO_TARGET}; folders "
                                      "keep every image unless given)", exclusive="count")
    every: int | None = option(None, "one frame (the sharpest) per EVERY source frames", exclusive="count")
    long_side: int = option(1600, "working size: long side of written images")
    keep: tuple[int, ...] = option((), "source indices that must be selected", nargs="*")


@dataclass
class SelectConfig:
    target: int | None = None  # number of frames wanted
    every: int | None = None  # or: one frame per `every` source frames
    keep_all: bool = False  # image folders: every usable image
    min_motion: float = 0.0003  # drop a frame that moved less than this (fraction of width) since the last kept one:
    # a camera at rest (0.2 px at 640 px); slow pans (the simulator moves ~1 px per frame) keep every frame
    time_weight: float = 0.25  # share of the window budget spread by time rather than motion


ANALYSIS_SIDE = 640
THUMB_W = 160


def analyse(source: Source, progress: bool = True) -> tuple[list[int], FrameStats]:
    """One pass over the source at <= 640 px: sharpness, texture, brightness and motion per frame."""
    fast = cv2.FastFeatureDetector_create(threshold=20)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST)
    idx, sharp, corners, bright, motion, contrast = [], [], [], [], [], []
    prev = None
    for i, rgb in source.frames(long_side=ANALYSIS_SIDE, progress="analyse" if progress else None):
        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        idx.append(i)
        sharp.append(float(cv2.Laplacian(grey, cv2.CV_32F).var()))
        corners.append(len(fast.detect(grey)))
        bright.append(float(grey.mean()))
        contrast.append(float(grey.std()))
        th = max(8, round(grey.shape[0] * THUMB_W / grey.shape[1]))
        thumb = cv2.resize(grey, (THUMB_W, th), interpolation=cv2.INTER_AREA)
        if prev is None:
            motion.append(0.0)
        else:
            flow = dis.calc(prev, thumb, None)
            motion.append(float(np.median(np.linalg.norm(flow, axis=2))) / THUMB_W)
        prev = thumb
    stats = FrameStats(*(np.asarray(a, dtype=np.float64) for a in (sharp, corners, bright, motion, contrast)))
    return idx, stats


def select(indices: Sequence[int], stats: FrameStats, cfg: SelectConfig,
           keep: Iterable[int] = ()) -> tuple[list[int], dict]:
    """Chosen source indices (sorted) and what was dropped, why."""
    indices = np.asarray(indices)
    n = len(indices)
    usable = stats.usable
    keep = sorted(set(int(k) for k in keep))
    missing = [k for k in keep if k not in set(indices.tolist())]
    if missing:
        raise InputError(f"frames {missing[:10]} are asked to be kept (by --keep, or named by --keyframes / "
                         f"--labels) but the source has only {n} frames (0-{n - 1}); check the frame numbers, and "
                         f"that the annotations belong to this capture")
    info: dict = {"unusable": indices[~usable].tolist(), "near_duplicates": []}
    if cfg.keep_all and not cfg.target and not cfg.every:
        chosen = set(indices[usable].tolist())
        return sorted(chosen | set(keep)), info
    if cfg.every:
        n_win = int(np.ceil(n / cfg.every))
        edges = np.minimum(np.arange(n_win + 1) * cfg.every, n)
    else:
        target = min(int(cfg.target or DEFAULT_VIDEO_TARGET), n)
        # windows of equal "progress": motion, plus a share of time so static shots still get frames
        m = stats.motion.copy()
        m_total = m.sum()
        t = np.full(n, 1.0 / n)
        prog = (1 - cfg.time_weight) * (m / m_total if m_total > 0 else t) + cfg.time_weight * t
        if m_total <= 0:
            prog = t
        cum = np.concatenate([[0.0], np.cumsum(prog)])
        cum /= cum[-1]
        edges = np.searchsorted(cum, np.linspace(0, 1, target + 1), side="left")
        edges[0], edges[-1] = 0, n
        # every window non-empty, so the target is met whenever the source has enough frames
        for k in range(1, target):
            edges[k] = min(max(edges[k], edges[k - 1] + 1), n - (target - k))
    chosen: list[int] = []
    for a, b in zip(edges[:-1], edges[1:]):
        if b <= a:
            continue
        win = np.arange(a, b)
        win = win[usable[win]]
        if win.size:
            chosen.append(int(win[np.argmax(stats.sharpness[win])]))
    # near-duplicates: cumulative motion since the last kept frame below min_motion (only when windows are by
    # count/spacing, i.e. video); keep-frames are never dropped
    cum_m = np.cumsum(stats.motion)
    kept: list[int] = []
    for pos in chosen:
        if kept and not cfg.keep_all and cum_m[pos] - cum_m[kept[-1]] < cfg.min_motion:
            info["near_duplicates"].append(int(indices[pos]))
            continue
        kept.append(pos)
    out = sorted(set(indices[kept].tolist()) | set(keep))
    return out, info


def _is_folder_source(source: Source) -> bool:
    return source.info.kind in ("images", "raw")


def _finished_images(ds: Path, key: str) -> list[Path] | None:
    """The images of a finished run with this resume key, when every one of them is still there."""
    rep = finished_with(ds, "frames", key)
    if rep is None:
        return None
    paths = [ds / IMAGES_DIR / (frame_name(int(i)) + ".png") for i in rep["figures"].get("selected_indices", [])]
    present = {p.name for p in (ds / IMAGES_DIR).glob("*.png")} if (ds / IMAGES_DIR).is_dir() else set()
    return paths if paths and present == {p.name for p in paths} else None


def extract_frames(source: str | Path, ds: str | Path, *, report: bool = True, **opts: Any) -> list[Path]:
    """Select frames from a video / image folder / RAW folder and write DS/images/frame_<index>.png; `opts`: the
    `FramesConfig` fields (target, every, long_side, keep; None = the default).

    The new images/ folder is built beside the old one and swapped in at the end, so a failed run leaves the
    dataset as it was. A finished run from the same source files and settings is reused (its images keep their
    modification times, so the masks and poses stages downstream are reused too). Returns the image paths in
    index order.
    """
    ds = Path(ds)
    opt = config_from(FramesConfig, opts, "frames")
    target, every, long_side = opt.target, opt.every, opt.long_side
    if target is not None and target < 3:
        raise InputError(f"--target {target}: at least 3 frames are needed for poses")
    if every is not None and every < 1:
        raise InputError(f"--every {every} must be >= 1")
    keep = sorted(set(int(k) for k in opt.keep))
    settings = {"target": target, "every": every, "long_side": long_side, "keep": keep}
    ds.mkdir(parents=True, exist_ok=True)
    source_fp = tree_fingerprint(Path(source))
    key = fingerprint("frames", source_fp, settings) if source_fp is not None else None
    done = _finished_images(ds, key) if report and key is not None else None
    if done is not None:
        print(f"frames: {len(done)} frames in {ds / IMAGES_DIR} are up to date (same source and settings)")
        return done
    src_key = source_key(source)
    inputs = {"source": str(source), "fingerprints": {"source": {"files": src_key, "content": src_key}} if src_key else {}}
    rep = StageReport(ds, "frames", inputs=inputs, settings=settings, resume_key=key) if report else None
    ctx = rep if rep is not None else _Null()
    with ctx:
        t0 = time.perf_counter()
        src = open_source(source)
        skipped = src.info.extra.get("skipped") or []
        if skipped:
            msg = (f"{len(skipped)} file(s) in {source} are not images and were left out: {', '.join(skipped[:5])}"
                   + (" ..." if len(skipped) > 5 else ""))
            print(f"warning: {msg}", file=sys.stderr)
            if rep is not None:
                rep.warn(msg, cause="not-an-image", files=skipped[:50])
        cfg = SelectConfig(target=target, every=every, keep_all=_is_folder_source(src))
        with _step(rep, "analyse") as st:
            indices, stats = analyse(src)
            st["frames"] = len(indices)
        n_usable = int(stats.usable.sum())
        if len(indices) < 3:
            what = ("image" if _is_folder_source(src) else "decodable frame") + ("" if len(indices) == 1 else "s")
            raise InputError(f"{source} has only {len(indices)} {what}; at least 3 views of the scene are needed "
                             "for poses: add more")
        if n_usable < 3:
            why = _unusable_reason(stats)
            raise InputError(f"{source}: only {n_usable} of {len(indices)} frames are usable ({why}); "
                             "at least 3 sharp, textured, exposed frames are needed")
        chosen, info = select(indices, stats, cfg, keep)
        if len(chosen) < 3:
            raise InputError(f"{source}: only {len(chosen)} frames survive selection; film more of the scene "
                             "or lower --every")
        out_dir = ds / IMAGES_DIR
        stage = ds / f".{IMAGES_DIR}.partial"
        shutil.rmtree(stage, ignore_errors=True)
        written: list[Path] = []
        size = None
        try:  # a failed write (disk full, read-only) leaves no partial folder behind
            stage.mkdir(parents=True)
            with _step(rep, "write") as st:
                for i, rgb in src.frames(indices=chosen, long_side=long_side, progress="frames"):
                    name = frame_name(i) + ".png"
                    atomic.write_image(stage / name, rgb)
                    written.append(out_dir / name)
                    size = (rgb.shape[1], rgb.shape[0])
                st["frames"] = len(written)
            _swap_dir(stage, out_dir)
        except BaseException:
            shutil.rmtree(stage, ignore_errors=True)
            raise
        if rep is not None:
            pos = {int(i): k for k, i in enumerate(indices)}
            sel = [pos[i] for i in chosen]
            rep.data["inputs"]["source_info"] = asdict(src.info)
            rep.figures.update({
                "source_frames": len(indices), "usable": n_usable, "selected": len(chosen), "size": list(size or ()),
                "sharpness_median_selected": float(np.median(stats.sharpness[sel])),
                "sharpness_median_all": float(np.median(stats.sharpness)),
                "motion_total_widths": float(stats.motion.sum()),
                "selected_indices": chosen,
                "unusable_indices": info["unusable"], "near_duplicates_dropped": info["near_duplicates"],
            })
            if src.info.names:
                rep.figures["source_names"] = {frame_name(i): src.info.names[i] for i in chosen}
            for message in skipped_lines(indices, stats, keep):
                rep.warn(message, cause="texture/exposure")
            rep.data["wall_s_total"] = round(time.perf_counter() - t0, 3)
    return written


def _swap_dir(new: Path, dest: Path) -> None:
    """Replace `dest` by `new` with renames only (the old folder goes away after the swap)."""
    old = dest.with_name(f".{dest.name}.old")
    shutil.rmtree(old, ignore_errors=True)
    if dest.exists():
        dest.rename(old)
    new.rename(dest)
    shutil.rmtree(old, ignore_errors=True)


def skipped_lines(indices: Sequence[int], stats: FrameStats, keep: Iterable[int] = ()) -> list[str]:
    """One line per reason frames were skipped, naming them; a run at the start or the end of the video is called
    out (what the user filmed there is lost). Frames kept for annotations are not skipped."""
    reasons, kept = stats.reasons(), set(int(k) for k in keep)
    indices = [int(i) for i in indices]
    lines = []
    for reason in ("black", "blank", "blurred"):
        ids = [i for i, r in zip(indices, reasons) if r == reason and i not in kept]
        if not ids:
            continue
        ends = [w for w, hit in (("start", ids[0] == indices[0]), ("end", ids[-1] == indices[-1])) if hit]
        lines.append(f"{len(ids)} {reason} frame(s) skipped: {_ranges(ids)}"
                     + (f" (at the {' and the '.join(ends)} of the video)" if ends else "")
                     + {"black": "", "blank": " (no texture at all)",
                        "blurred": " (far blurrier than the video's other frames)"}[reason])
    return lines


def _unusable_reason(stats: FrameStats) -> str:
    reasons = [r for r in stats.reasons() if r]
    if not reasons:
        return "the frames are usable"
    counts = {r: reasons.count(r) for r in dict.fromkeys(reasons)}
    return "the frames are " + ", ".join(f"{r} ({n})" for r, n in counts.items())


def _ranges(ids: Sequence[int], limit: int = 6) -> str:
    """[1,2,3,7,9,10] -> '1-3, 7, 9-10'."""
    out, ids = [], sorted(ids)
    start = prev = ids[0]
    for v in list(ids[1:]) + [None]:
        if v is not None and v == prev + 1:
            prev = v
            continue
        out.append(f"{start}-{prev}" if prev != start else f"{start}")
        if v is not None:
            start = prev = v
    return ", ".join(out[:limit]) + (", ..." if len(out) > limit else "")


class _Null:
    def __enter__(self):
        return None

    def __exit__(self, *a):
        return None


def _step(rep: StageReport | None, name: str):
    return rep.step(name) if rep is not None else nullcontext({})


# ----------------------------------------------------------------------------------------------------------------
# CLI
# ----------------------------------------------------------------------------------------------------------------
def add_arguments(p) -> None:
    p.add_argument("input", type=Path, help="video file (mp4/mov), image folder, or RAW folder (DNG, CR2, NEF, ...)")
    p.add_argument("dataset", type=Path, help="dataset folder; frames go to DATASET/images/")
    add_flags(p, FramesConfig)
    p.epilog = ("examples:\n  interreal frames room.mp4 out/room                 # 300 sharpest frames, motion-aware\n"
                "  interreal frames room.mp4 out/room --target 150 --long-side 1280\n"
                "  interreal frames photos/ out/room                   # every photo, format sniffed from content\n"
                "  interreal frames raw_dng/ out/room --every 2        # RAW with one white balance for all")


def frames_options(args) -> dict[str, Any]:
    """`extract_frames` options from the parsed flags of `FramesConfig` (its default when not given)."""
    return values_from_args(FramesConfig, args)


def main(args) -> int:
    paths = extract_frames(args.input, args.dataset, **frames_options(args))
    for line in warning_lines(args.dataset, ["frames"]):  # the frames skipped, and why: printed, not only reported
        print(line)
    print(f"{len(paths)} frames -> {args.dataset / IMAGES_DIR} (report: {args.dataset}/reports/frames.json)")
    return 0
