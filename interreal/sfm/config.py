"""What one SfM run does: its settings (`SfMConfig`), the rules that pick SIFT octaves, track refinement and key
strides for a capture ("auto"), which image pairs are matched, and the retry ladder (`ladder`) of attempts.

Pure functions of the settings and the capture's size: nothing here touches pycolmap. The measurements behind
each auto rule are in docs/sfm-measurements.md.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from ..dataset import image_hw
from ..keypoints import TRACK_WINDOW
from ..options import option

BA_LOSSES = ("trivial", "soft_l1", "cauchy", "huber")  # pycolmap.LossFunctionType, lower case
KEY_STRIDE_MIN = 150  # frames from which a sequential capture gets SIFT's upsampled octave on every 3rd frame only
FINE_MIN_SIDE = 640  # ... if its frames are this large (smaller frames find too few features at octave 0)


@dataclass
class SfMConfig:
    """Settings of one SfM run (all of them enter the resume fingerprint). The fields declared with `option` are
    the flags of `interreal poses` and `interreal process`; docs/sfm-measurements.md has the figures behind each
    default."""

    sfm_long_side: int = option(1000, "SIFT works at <= this long side: a fraction of full-resolution cost, same "
                                      "accuracy")
    max_features: int = option(2048, "SIFT features per image (matching cost grows with its square)")
    first_octave: int | None = None  # None = auto: -1 (2x upsampled) when SIFT sees the frames at native size, else 0
    camera_model: str = option("RADIAL", "shared camera model (RADIAL: f, cx, cy, k1, k2; never PINHOLE for phone "
                                         "frames)", choices=("SIMPLE_RADIAL", "RADIAL", "OPENCV"))
    matcher: str = option("auto", "auto = exhaustive up to 40 frames, else sequential + loop detection",
                          choices=("auto", "sequential", "exhaustive"))
    exhaustive_max: int = 40  # auto: exhaustive up to this many images (n^2/2 pairs; sequential beyond)
    overlap: int = 6  # + quadratic (i+1..6, i+2^k) + loop detection; the retry ladder triples it
    fine_octave_stride: int = option(
        0, "when SIFT sees frames at native size it also searches a 2x upsampled octave; give it to every Nth frame "
           f"only (0 = auto: 3 for sequential captures of >= {KEY_STRIDE_MIN} frames of >= {FINE_MIN_SIDE} px, else "
           "1 = every frame; 1 is twice as slow there, a bit more accurate)")
    key_stride: int = option(
        0, "map every Nth frame first, then register the others into that model (0 = auto: 3 for sequential "
           f"captures of >= {KEY_STRIDE_MIN} frames whose frames all get the same SIFT octaves or whose tracks are "
           "extended, else 1 = all at once)")
    quadratic_overlap: bool = True
    loop_detection: bool = True
    mapper: str = option("incremental", "incremental, or global (GLOMAP-style)", choices=("incremental", "global"))
    use_masks: bool = option(True, "do not mask object pixels out of SfM features", flag="--no-masks")
    retry_below: float = 0.9  # run the retry ladder under this registered fraction
    fail_below: float = 0.4  # StageError under this
    orientation: str = option("vertical", "world up: vertical (the direction the cameras' x axes avoid), up (mean "
                                          "camera up) or none", choices=("vertical", "up", "none"))
    center_scale: bool = True
    undistort: bool = option(False, "also write DS/undistorted/ (pinhole images, COLMAP model)")
    ba_tolerance: float = 1e-6  # relative cost change that ends a global BA (COLMAP: 0): half the time, same error
    refine_tracks: str = option(
        "auto", "align each track's keypoints to one view (Lucas-Kanade) before the final bundle adjustment "
                f"(auto: for sequential captures of >= {KEY_STRIDE_MIN} frames at native size >= {FINE_MIN_SIDE} px, "
                "where it was measured to help)", choices=("auto", "on", "off"))
    extend_tracks: str = option(
        "auto", "before the final bundle adjustment, add each 3-D point to the frames where it projects but was not "
                "matched (Lucas-Kanade from the projection, checked against the track's patch; auto: sequential "
                "captures that SIFT sees at native size)", choices=("auto", "on", "off"))
    track_window: int = TRACK_WINDOW  # ... in views this many frames beyond the track's first and last
    principal_point: str = option("auto", "final bundle adjustment: free (cx, cy) when it clearly lowers the error "
                                          "(auto), always (refine, as ns-process-data), or never",
                                  choices=("auto", "refine", "fixed"))
    ba_loss: str = option("soft_l1", "robust loss of the final bundle adjustment at 1 px (trivial = squared, as "
                                     "COLMAP's): a few bad observations pull a squared loss", choices=BA_LOSSES)
    ba_loss_scale: float = 1.0  # px: residuals beyond this are down-weighted
    intrinsics: str | None = option(
        None, "known camera intrinsics: a 3x3 K as text (K.txt: 9 numbers) or JSON {fx, fy, cx, cy, optional k1, "
              "k2, p1, p2 and w, h: the image size K is for}; scaled to the dataset's images (from w, h, else the "
              "capture size `frames` recorded); held fixed unless --intrinsics-refine; auto: SfM estimates them",
        metavar="FILE")
    intrinsics_refine: bool = option(False, "with --intrinsics: start from them and let bundle adjustment refine "
                                            "them (default: fixed)")
    allow_low_parallax: bool = option(
        False, "map even when the check before mapping finds that the camera barely moved (turned in place or stood "
               "still: no pair of frames shows >= ~1.5 deg of parallax), instead of refusing in seconds")
    seed: int = 0
    num_threads: int = -1
    verbose: bool = option(False, "show COLMAP's log")


@dataclass(frozen=True)
class Rung:
    """One attempt of the retry ladder."""

    name: str
    matcher: str  # sequential | exhaustive
    overlap: int
    loop_detection: bool
    mapper: str  # incremental | global
    relaxed: bool = False
    stride: int = 1  # > 1: keyframes (every stride-th frame) are matched and mapped first, the rest registered after


def _long_dense(cfg: SfMConfig, n: int, long_side: int) -> bool:
    """A sequential capture of KEY_STRIDE_MIN frames or more, of FINE_MIN_SIDE px or more: where the auto rules
    of `fine_frames` and `use_track_refinement` were measured."""
    return n >= KEY_STRIDE_MIN and long_side >= FINE_MIN_SIDE and cfg.matcher != "exhaustive"


def fine_frames(cfg: SfMConfig, n: int, octave: int, long_side: int) -> list[int]:
    """Positions of the frames that get SIFT's upsampled octave (octave -1): every `fine_octave_stride`-th frame
    (auto: every 3rd of a `_long_dense` capture, else all); all frames when the octave is not -1 (nothing to
    save)."""
    stride = cfg.fine_octave_stride or (3 if _long_dense(cfg, n, long_side) else 1)
    return key_positions(n, stride if octave < 0 else 1)


def use_track_refinement(cfg: SfMConfig, n: int, long_side: int) -> bool:
    """Whether to align each track's keypoints to one view before the final BA (`keypoints.refine_tracks`).

    auto = where it was measured to help: `_long_dense` captures that SIFT sees at native size. Elsewhere the
    translation-only alignment meets larger changes of view per pixel and did not help (docs/sfm-measurements.md)."""
    if cfg.refine_tracks in ("on", "off"):
        return cfg.refine_tracks == "on"
    return _long_dense(cfg, n, long_side) and long_side <= cfg.sfm_long_side


def _sequential(cfg: SfMConfig, n: int) -> bool:
    """Whether n frames are matched sequentially (+ loop detection) rather than exhaustively."""
    return cfg.matcher == "sequential" or (cfg.matcher == "auto" and n > cfg.exhaustive_max)


def use_track_extension(cfg: SfMConfig, n: int, long_side: int) -> bool:
    """Whether to extend tracks into the views where their point projects (`keypoints.extend_tracks`).

    auto = sequential captures that SIFT sees at native size, where it cut the errors by a third to a half; on
    downscaled photos (fox) it changed nothing beyond the run-to-run spread (docs/sfm-measurements.md)."""
    if cfg.extend_tracks in ("on", "off"):
        return cfg.extend_tracks == "on"
    return _sequential(cfg, n) and long_side <= cfg.sfm_long_side


def resolve_octave(cfg: SfMConfig, sample: Path) -> int:
    """The SIFT first octave: cfg's, else -1 for frames SIFT sees at native size and 0 for downscaled ones."""
    if cfg.first_octave is not None:
        return int(cfg.first_octave)
    return -1 if max(image_hw(sample)) <= cfg.sfm_long_side else 0


def sequential_pairs(n: int, overlap: int, quadratic: bool) -> list[tuple[int, int]]:
    """COLMAP's sequential pairing on name order: i+1..i+overlap, and i+2^k (k < overlap) when quadratic."""
    pairs = set()
    for i in range(n):
        for j in range(1, overlap + 1):
            if i + j < n:
                pairs.add((i, i + j))
        if quadratic:
            for k in range(overlap):
                if i + (1 << k) < n:
                    pairs.add((i, i + (1 << k)))
    return sorted(pairs)


def key_positions(n: int, stride: int) -> list[int]:
    """Keyframe positions for a strided run: every stride-th frame, and the last one."""
    keys = list(range(0, n, max(1, stride)))
    return keys if keys[-1] == n - 1 else keys + [n - 1]


def strided_pairs(n: int, stride: int, overlap: int, quadratic: bool) -> list[tuple[int, int]]:
    """Sequential pairing among the keyframes (in keyframe order), plus each other frame with its neighbour and
    the keyframes on both sides: enough matches to register it into the keyframes' model and extend its tracks."""
    keys = key_positions(n, stride)
    pairs = {(keys[a], keys[b]) for a, b in sequential_pairs(len(keys), overlap, quadratic)}
    for i in range(n - 1):
        pairs.add((i, i + 1))
    for lo, hi in zip(keys[:-1], keys[1:]):
        for i in range(lo + 1, hi):
            pairs.update({(lo, i), (i, hi)})
    return sorted(pairs)


def rung_pairs(rung: Rung, n: int, quadratic: bool) -> list[tuple[int, int]]:
    """The image pairs (positions in name order) a rung matches, before loop detection adds its own."""
    if rung.matcher == "exhaustive":
        return [(i, j) for i in range(n) for j in range(i + 1, n)]
    if rung.stride > 1:
        return strided_pairs(n, rung.stride, rung.overlap, quadratic)
    return sequential_pairs(n, rung.overlap, quadratic)


def loop_queries(n: int, stride: int) -> list[int]:
    """Positions whose images query the vocabulary tree: every 10th frame, as COLMAP's sequential matcher does,
    keyframes only in a strided rung."""
    step = 10 if stride <= 1 else stride * max(1, round(10 / stride))
    return list(range(0, n, step))


def ladder(cfg: SfMConfig, n: int, mixed_octaves: bool = False, extended: bool = False) -> list[Rung]:
    """The base attempt, then what to try when too few frames register (each rung only adds matches).
    mixed_octaves: only some frames got SIFT's upsampled octave (`fine_frames`); auto key_stride then maps all
    frames at once, since the strided way gives the fine frames' tracks fewer views, unless `extended`: the tracks
    are extended into their views before the final BA, which makes up for it (docs/sfm-measurements.md)."""
    if not _sequential(cfg, n):
        base = Rung("base", "exhaustive", cfg.overlap, False, cfg.mapper)
        rungs = [base, replace(base, name="relaxed", relaxed=True)]
    else:
        stride = cfg.key_stride or (3 if n >= KEY_STRIDE_MIN and (extended or not mixed_octaves) else 1)
        base = Rung("base", "sequential", cfg.overlap, cfg.loop_detection, cfg.mapper,
                    stride=stride if cfg.mapper == "incremental" else 1)
        rungs = [base, replace(base, name="more-overlap", overlap=cfg.overlap * 3, loop_detection=True, stride=1)]
        if n <= 400:
            rungs.append(replace(base, name="exhaustive", matcher="exhaustive", stride=1))
        rungs.append(replace(rungs[-1], name="relaxed", relaxed=True))
    other = "global" if cfg.mapper == "incremental" else "incremental"
    rungs.append(replace(rungs[-1], name=f"{other}-mapper", mapper=other, relaxed=False))
    return rungs
