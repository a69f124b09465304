"""Camera poses with pycolmap: `interreal poses DS` -> transforms.json, colmap/sparse/0, sparse_pc.ply.

What differs from ns-process-data, and why (measured in reference/process-data.md and recipes/bench_poses.py):
- SIFT at <= 1000 px with a feature cap (training images stay at their size; COLMAP rescales keypoints), so
  extraction and matching cost a fraction of full-resolution SfM at no accuracy loss.
- One shared RADIAL camera (f, cx, cy, k1, k2; never PINHOLE: phone frames are distorted and PINHOLE costs 30x
  rotation error; k2 cut the error by a quarter against SIMPLE_RADIAL on both fox and the simulator).
- Per-image masks drop object pixels from features: moving parts otherwise corrupt poses.
- Exhaustive matching for small sets, sequential (quadratic overlap) + loop detection with a vocabulary tree built
  from the capture's own descriptors for larger ones (no download: an empty tree path aborts the process offline).
- Frames SIFT sees at native size (<= 1000 px) get its 2x upsampled octave, which finds the fine features that
  make small frames accurate; in long videos (>= KEY_STRIDE_MIN frames of >= FINE_MIN_SIDE px) only every 3rd
  frame gets it, the others octave 0: features, matches and mapping cost about half, the tracks still run
  through the fine frames (simulator, 300 frames at 640x480: 166 s instead of 343 s, 0.055 vs 0.040 deg).
  Long videos whose frames all get the same octaves (e.g. 320 px frames) map every 3rd frame first and register
  the rest into that model (PnP + local BA): half the mapping time on 300 frames.
- Before the final BA, on such dense captures, every track's keypoints are aligned to one view of the track
  (Lucas-Kanade on image patches, `keypoints.py`): SIFT locates each observation on its own, BA needs them to
  agree (`use_track_refinement` gives where it helped and where not). Then every 3-D point is looked for, the
  same way, in the nearby views where it projects but SIFT did not match it (`keypoints.extend_tracks`): three
  times the observations for the final BA.
- The LARGEST model is kept (not sparse/0) and the others are reported; under 90 % registered a retry ladder runs.
- Gravity-like orientation ("vertical"), centred and scaled to max |t| = 1; the transform is recorded.
- Resumable: features, matches and the final model are reused when their inputs and settings are unchanged.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from . import atomic, provenance
from .conventions import (
    IMAGES_DIR,
    MASKS_DIR,
    TRANSFORMS_FILE,
    frame_id,
    frame_index,
    opencv_to_opengl,
)
from .dataset import Frame, Intrinsics, list_images, write_transforms
from .errors import InputError, StageError
from .keypoints import TRACK_WINDOW, extend_tracks, refine_tracks
from .report import StageReport, files_fingerprint, fingerprint, warning_lines

COLMAP_DIR = "colmap"
BA_LOSSES = ("trivial", "soft_l1", "cauchy", "huber")  # pycolmap.LossFunctionType, lower case
KEY_STRIDE_MIN = 150  # frames from which a sequential capture gets SIFT's upsampled octave on every 3rd frame only
FINE_MIN_SIDE = 640  # ... if its frames are this large: octave 0 finds ~520 features a frame at 640x480 (1660 with
# octave -1), ~130 at 320x240, too few (45 frames at 320x240: 0.86 deg with every 3rd frame fine, < 0.5 all fine)
SFM_MASKS_DIR = "sfm_masks"
PLY_FILE = "sparse_pc.ply"


@dataclass
class SfMConfig:
    """Settings of one SfM run (all of them enter the resume fingerprint)."""

    sfm_long_side: int = 1000  # SIFT runs at <= this many pixels on the long side
    max_features: int = 2048  # matching cost grows with the square of this; 2048 vs 4096 changed nothing measurable
    first_octave: int | None = None  # None = auto: -1 (COLMAP's 2x upsampled octave) when SIFT sees the frames at
    # native size (5x lower rotation error at 640x480 than 0), 0 when it downscales them (fox 1600 -> 1000 px:
    # 2.3x faster and 0.21 vs 0.24 deg from the reference)
    camera_model: str = "RADIAL"  # k1, k2: 0.154 vs 0.200 deg on fox, 0.052 vs 0.068 on synth (SIMPLE_RADIAL); or OPENCV
    matcher: str = "auto"  # auto | sequential | exhaustive
    exhaustive_max: int = 40  # auto: exhaustive up to this many images (n^2/2 pairs; sequential beyond)
    overlap: int = 6  # + quadratic (i+1..6, i+2^k) + loop detection; the retry ladder triples it
    fine_octave_stride: int = 0  # with octave -1: only every Nth frame gets it, the others octave 0 (0 = auto: 3
    # for sequential captures of KEY_STRIDE_MIN frames or more at FINE_MIN_SIDE px, else 1 = every frame).
    # Simulator, 300 frames at 640x480 (rotation gauge): 166 s at 0.055 deg; every frame fine: 343 s at 0.040 deg
    key_stride: int = 0  # sequential captures: map every Nth frame first, then register the rest into that model
    # (0 = auto: 3 from KEY_STRIDE_MIN frames on unless the octaves are mixed and the tracks not extended, else 1 =
    # all at once). Simulator at 640x480 with fine_octave_stride 3, without track extension: 151 s at 0.068 deg with
    # 3, 161-166 s at 0.052-0.055 deg with 1 (with it: see `ladder`); at 320x240 (every frame fine) the strided way
    # keeps the demo's poses stage at ~68 s
    quadratic_overlap: bool = True
    loop_detection: bool = True
    mapper: str = "incremental"  # incremental | global
    use_masks: bool = True
    retry_below: float = 0.9  # run the retry ladder under this registered fraction
    fail_below: float = 0.4  # StageError under this
    orientation: str = "vertical"  # vertical | up | none
    center_scale: bool = True
    undistort: bool = False  # also write DS/undistorted/ (pinhole images + model) for splatting trainers
    ba_tolerance: float = 1e-6  # relative cost change that ends a global BA (Ceres function_tolerance; COLMAP: 0, i.e.
    # 100 iterations): the final BA took half the time at the same error (synth 60: 0.0528 vs 0.0523 deg)
    refine_tracks: str = "auto"  # align each track's keypoints to one view (KLT) before the final BA: on | off |
    # auto = on for dense captures at native size (see `use_track_refinement`)
    extend_tracks: str = "auto"  # add each 3-D point to the views where it projects but was not matched (KLT from the
    # projection, checked against the track's reference patch) before the final BA: on | off | auto (see
    # `use_track_extension`)
    track_window: int = TRACK_WINDOW  # ... in views this many frames beyond the track's first and last
    principal_point: str = "auto"  # final BA: auto (free (cx, cy) only when it clearly helps) | refine | fixed
    ba_loss: str = "soft_l1"  # final BA's robust loss (BA_LOSSES): trivial (squared, as COLMAP's global BA) |
    # soft_l1 | cauchy | huber. A few bad observations (mask edges, compression) pull a squared loss. Simulator, 300 frames at 640x480,
    # same capture (rotation deg centre / rotation gauge, centre %): trivial 0.059 / 0.054 / 0.041, soft_l1 0.053 /
    # 0.045 / 0.031; without masks 0.458 / 0.110 / 0.117 -> 0.285 / 0.090 / 0.084; another room (seed 1) 0.109 /
    # 0.071 / 0.048 -> 0.075 / 0.050 / 0.036; fox unchanged (0.135-0.145 deg).
    # cauchy went further in the rotation gauge (0.031) but 5 s slower and its centre-fitted gauge tilted more
    ba_loss_scale: float = 1.0  # px: residuals beyond this are down-weighted
    seed: int = 0
    num_threads: int = -1
    verbose: bool = False


# ----------------------------------------------------------------------------------------------------------------
# small helpers
# ----------------------------------------------------------------------------------------------------------------
def _pycolmap(verbose: bool):
    import pycolmap

    pycolmap.logging.minloglevel = 0 if verbose else 2
    pycolmap.logging.stderrthreshold = 0 if verbose else 2
    return pycolmap


class NativeLog:
    """Send COLMAP's native log (glog on fd 2, which `minloglevel` does not fully silence) to DS/colmap/colmap.log
    unless verbose; progress bars keep writing to the terminal through a duplicate of the original stderr."""

    def __init__(self, path: Path, verbose: bool):
        self.path, self.verbose = path, verbose
        self.term = None
        self._saved = None

    def __enter__(self) -> "NativeLog":
        import os
        import sys

        sys.stderr.flush()
        self.term = os.fdopen(os.dup(2), "w", buffering=1)
        if not self.verbose:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
            self._saved = os.dup(2)
            os.dup2(fd, 2)
            os.close(fd)
        return self

    def __exit__(self, *exc) -> None:
        import os
        import sys

        sys.stderr.flush()
        if self._saved is not None:
            os.dup2(self._saved, 2)
            os.close(self._saved)
        self.term.close()

    def bar(self, total: int, desc: str):
        from tqdm import tqdm

        return tqdm(total=total, desc=desc, file=self.term, leave=False, unit="pair" if "match" in desc else "img")


def _load_state(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _ranges(ids: list[int]) -> str:
    if not ids:
        return ""
    ids = sorted(ids)
    out, start, prev = [], ids[0], ids[0]
    for v in ids[1:] + [None]:
        if v is not None and v == prev + 1:
            prev = v
            continue
        out.append(f"{start}-{prev}" if prev != start else str(start))
        if v is not None:
            start = prev = v
    return ", ".join(out)


# ----------------------------------------------------------------------------------------------------------------
# masks
# ----------------------------------------------------------------------------------------------------------------
def prepare_masks(ds: Path, images: list[Path], work: Path) -> tuple[Path | None, str, list[Path]]:
    """Folder of COLMAP masks (<image name>.png, 255 = use) or None; also a label of the source and its files.

    DS/sfm_masks/ (written by `interreal masks`) wins; else masks are derived from DS/masks/<fid>.npy, where the
    background channel (last) is what SfM may use.
    """
    import cv2

    given = ds / SFM_MASKS_DIR
    if given.is_dir() and any(given.glob("*.png")):
        files = [given / f"{p.name}.png" for p in images if (given / f"{p.name}.png").exists()]
        return given, "sfm_masks", files
    npy_dir = ds / MASKS_DIR
    if not npy_dir.is_dir():
        return None, "none", []
    out = work / "masks"
    out.mkdir(parents=True, exist_ok=True)
    used = []
    for p in images:
        src = npy_dir / f"{frame_id(p)}.npy"
        if not src.exists():
            continue
        used.append(src)
        dst = out / f"{p.name}.png"
        if dst.exists() and dst.stat().st_mtime_ns >= src.stat().st_mtime_ns:
            continue
        m = np.load(src, allow_pickle=False)
        use = (m[..., -1].astype(bool) if m.ndim == 3 else m.astype(bool)).astype(np.uint8) * 255
        h, w = _image_hw(p)
        if use.shape != (h, w):
            use = cv2.resize(use, (w, h), interpolation=cv2.INTER_NEAREST)
        atomic.write_image(dst, use)
    return (out if used else None), ("masks.npy" if used else "none"), used


def _image_hw(path: Path) -> tuple[int, int]:
    from PIL import Image

    with Image.open(path) as im:
        return im.size[1], im.size[0]


# ----------------------------------------------------------------------------------------------------------------
# vocabulary tree (for loop detection), built from the capture's own descriptors
# ----------------------------------------------------------------------------------------------------------------
def build_vocab_tree(db_path: Path, out: Path, max_descriptors: int = 50_000, seed: int = 0) -> Path:
    import pycolmap

    rng = np.random.default_rng(seed)
    chunks = []
    with pycolmap.Database.open(str(db_path)) as db:
        imgs = db.read_all_images()
        per = max(32, max_descriptors // max(1, len(imgs)))
        for im in imgs:
            d = np.asarray(db.read_descriptors(im.image_id).data)
            if len(d) > per:
                d = d[rng.choice(len(d), per, replace=False)]
            chunks.append(d)
    desc = np.concatenate(chunks).astype(np.float32)
    words = 256 if len(desc) < 60_000 else 512
    fd = pycolmap.FeatureDescriptorsFloat(pycolmap.FeatureExtractorType.SIFT, desc)
    vi = pycolmap.VisualIndex.create(128, 64)
    vi.build(pycolmap.VisualIndex.BuildOptions(num_visual_words=words, num_iterations=10, num_rounds=1,
                                               num_threads=-1), fd)
    tmp = out.with_suffix(".tmp")
    vi.write(str(tmp))
    tmp.replace(out)
    return out


# ----------------------------------------------------------------------------------------------------------------
# pipeline steps
# ----------------------------------------------------------------------------------------------------------------
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


def extract(pc, db: Path, image_dir: Path, names: list[str], mask_dir: Path | None, cfg: SfMConfig,
            octave: int, fine: set[int], log: NativeLog | None = None, chunk: int = 16) -> None:
    """SIFT into a fresh database, in chunks (for the progress bar); every chunk reuses the one shared camera.
    Frames at the positions `fine` (from `fine_frames`) get the first octave `octave`, the others octave 0."""
    ext = pc.FeatureExtractionOptions(num_threads=cfg.num_threads, use_gpu=False, max_image_size=cfg.sfm_long_side)
    ext.sift.max_num_features = cfg.max_features
    groups = [(octave, [n for i, n in enumerate(names) if i in fine]),
              (0, [n for i, n in enumerate(names) if i not in fine])]
    if db.exists():
        db.unlink()
    bar = log.bar(len(names), "features") if log else None
    first = True
    for oct_, group in groups:
        ext.sift.first_octave = oct_
        for k in range(0, len(group), chunk):
            reader = pc.ImageReaderOptions(camera_model=cfg.camera_model)
            if mask_dir is not None:
                reader.mask_path = str(mask_dir)
            if not first:
                reader.existing_camera_id = 1
            first = False
            pc.extract_features(str(db), str(image_dir), image_names=group[k:k + chunk],
                                camera_mode=pc.CameraMode.SINGLE, reader_options=reader, extraction_options=ext,
                                device=pc.Device.cpu)
            if bar is not None:
                bar.update(len(group[k:k + chunk]))
    if bar is not None:
        bar.close()
    with pc.Database.open(str(db)) as d:
        if d.num_cameras() != 1:
            raise StageError(f"feature extraction made {d.num_cameras()} cameras, expected one shared camera")


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

    auto = where it was measured to help: `_long_dense` captures that SIFT sees at native size (simulator, 300 frames at 640x480: rotation error 0.065 -> 0.060 deg and
    centres 0.048 -> 0.042 % on one model, 0.056 -> 0.046 deg and 0.037 -> 0.033 % on another). Elsewhere the
    translation-only alignment meets larger changes of view per pixel and did not help: 300 frames at 320x240
    0.115 -> 0.118 deg, centres 0.104 -> 0.116 %; 90 frames at 320x240 0.163 -> 0.143 deg but centres 0.079 ->
    0.104 %; fox (50 photos, SIFT at 1000 of 1600 px) unchanged (0.0925 -> 0.0922 deg, 0.032 -> 0.033 %)."""
    if cfg.refine_tracks in ("on", "off"):
        return cfg.refine_tracks == "on"
    return _long_dense(cfg, n, long_side) and long_side <= cfg.sfm_long_side


def _sequential(cfg: SfMConfig, n: int) -> bool:
    """Whether n frames are matched sequentially (+ loop detection) rather than exhaustively."""
    return cfg.matcher == "sequential" or (cfg.matcher == "auto" and n > cfg.exhaustive_max)


def use_track_extension(cfg: SfMConfig, n: int, long_side: int) -> bool:
    """Whether to extend tracks into the views where their point projects (`keypoints.extend_tracks`).

    auto = sequential captures that SIFT sees at native size, where it was measured (rotation deg centre /
    rotation gauge, centre %, from the same model): simulator 300 frames at 640x480 0.053 / 0.045 / 0.031 ->
    0.034 / 0.025 / 0.017; 300 at 320x240 0.149 / 0.115 / 0.104 -> 0.106 / 0.062 / 0.068; 90 at 320x240
    0.303 / 0.163 / 0.079 -> 0.157 / 0.077 / 0.066. Not on fox (50 photos around an object, SIFT at 1000 of 1600
    px, so not native): two whole runs gave 0.138 / 0.091 / 0.029 off, 0.148 / 0.091 / 0.028 on, the same within
    its spread."""
    if cfg.extend_tracks in ("on", "off"):
        return cfg.extend_tracks == "on"
    return _sequential(cfg, n) and long_side <= cfg.sfm_long_side


def resolve_octave(cfg: SfMConfig, sample: Path) -> int:
    """The SIFT first octave: cfg's, else -1 for frames SIFT sees at native size and 0 for downscaled ones."""
    if cfg.first_octave is not None:
        return int(cfg.first_octave)
    return -1 if max(_image_hw(sample)) <= cfg.sfm_long_side else 0


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


def match(pc, db: Path, rung: Rung, tree: Path | None, cfg: SfMConfig, names: list[str], work: Path,
          log: NativeLog | None = None, chunk: int = 200) -> None:
    """Match the rung's pairs (already matched pairs are skipped by COLMAP), in chunks for the progress bar;
    loop detection = vocabulary-tree retrieval for every 10th frame, as COLMAP's sequential matcher does it."""
    mopt = pc.FeatureMatchingOptions(num_threads=cfg.num_threads, use_gpu=False)
    vopt = pc.TwoViewGeometryOptions()
    vopt.ransac.random_seed = cfg.seed
    n = len(names)
    if rung.matcher == "exhaustive":
        pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    elif rung.stride > 1:
        pairs = strided_pairs(n, rung.stride, rung.overlap, cfg.quadratic_overlap)
    else:
        pairs = sequential_pairs(n, rung.overlap, cfg.quadratic_overlap)
    listing = work / "pairs.txt"
    bar = log.bar(len(pairs), f"matching ({rung.name})") if log else None
    for k in range(0, len(pairs), chunk):
        part = pairs[k:k + chunk]
        listing.write_text("".join(f"{names[a]} {names[b]}\n" for a, b in part))
        pc.match_image_pairs(str(db), matching_options=mopt,
                             pairing_options=pc.ImportedPairingOptions(match_list_path=str(listing)),
                             verification_options=vopt, device=pc.Device.cpu)
        if bar is not None:
            bar.update(len(part))
    if bar is not None:
        bar.close()
    if rung.loop_detection and rung.matcher == "sequential":
        if tree is None or not tree.exists():
            raise StageError("loop detection needs a local vocabulary tree (internal error: tree not built)")
        queries = work / "loop_queries.txt"
        step = 10 if rung.stride <= 1 else rung.stride * max(1, round(10 / rung.stride))  # every ~10th, keyframes only
        queries.write_text("".join(f"{names[i]}\n" for i in range(0, n, step)))
        popt = pc.VocabTreePairingOptions(num_images=10, vocab_tree_path=str(tree), match_list_path=str(queries),
                                          num_threads=cfg.num_threads)
        pc.match_vocabtree(str(db), matching_options=mopt, pairing_options=popt, verification_options=vopt,
                           device=pc.Device.cpu)
    listing.unlink(missing_ok=True)


def reconstruct(pc, db: Path, image_dir: Path, out: Path, rung: Rung, cfg: SfMConfig,
                log: NativeLog | None = None, names: list[str] | None = None) -> dict[int, Any]:
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    pc.set_random_seed(cfg.seed)
    if rung.mapper == "global":
        gopt = pc.GlobalPipelineOptions(num_threads=cfg.num_threads, random_seed=cfg.seed)
        gopt.mapper.global_positioning.use_gpu = False
        gopt.mapper.bundle_adjustment.ceres.use_gpu = False
        return dict(pc.global_mapping(str(db), str(image_dir), str(out), options=gopt))
    opt = pc.IncrementalPipelineOptions(num_threads=cfg.num_threads, random_seed=cfg.seed, min_model_size=3)
    # fewer, shorter global BAs while growing (same accuracy on fox, -30 % mapping time); refine_intrinsics polishes
    opt.ba_global_frames_ratio = opt.ba_global_points_ratio = 1.6
    opt.ba_global_max_num_iterations = 20
    opt.ba_local_max_num_iterations = 10
    opt.ba_global_max_refinements = 2
    opt.ba_global_function_tolerance = cfg.ba_tolerance
    opt.ba_local_max_refinements = 1
    if rung.relaxed:
        opt.min_num_matches = 8
        opt.mapper.init_min_num_inliers = 40
        opt.mapper.abs_pose_min_num_inliers = 15
        opt.mapper.abs_pose_min_inlier_ratio = 0.15
        opt.mapper.init_min_tri_angle = 8.0
        opt.mapper.max_reg_trials = 6
    names = names or []
    bar = log.bar(len(names), "mapping (registered)") if log and names else None
    tick = (lambda: bar.update(1)) if bar is not None else None
    try:
        if rung.stride <= 1 or not names:
            return dict(pc.incremental_mapping(str(db), str(image_dir), str(out), options=opt, next_image_callback=tick))
        # 1. the keyframes alone: a third of the frames carry the geometry at a fraction of incremental BA's cost
        key_opt = pc.IncrementalPipelineOptions(opt.todict())
        key_opt.image_names = [names[i] for i in key_positions(len(names), rung.stride)]
        for sub in ("keys", "keys_best", "all"):
            (out / sub).mkdir()
        keys = dict(pc.incremental_mapping(str(db), str(image_dir), str(out / "keys"), options=key_opt,
                                           next_image_callback=tick))
        if not keys:
            return {}
        best = max(keys, key=lambda k: keys[k].num_reg_images())
        seed = out / "keys_best"
        keys[best].write(str(seed))
        # 2. every other frame registered into it (PnP + local BA), no global BA until the final refinement
        fill = pc.IncrementalPipelineOptions(opt.todict())
        fill.ba_global_frames_ratio = fill.ba_global_points_ratio = 100.0
        return dict(pc.incremental_mapping(str(db), str(image_dir), str(out / "all"), options=fill,
                                           input_path=str(seed), next_image_callback=tick))
    finally:
        if bar is not None:
            bar.close()


PP_MIN_GAIN = 0.003  # relative RMS reprojection gain that justifies freeing (cx, cy)
PP_MAX_SHIFT = 0.02  # ... and the largest plausible move of (cx, cy), as a fraction of the image diagonal


EXTENDED_BA_TOLERANCE = 1e-3  # the BA after `extend_tracks` starts at the optimum of the same points and cameras:
# on the simulator LM's second step changed the cost by 1e-4 and the poses by < 0.002 deg, and each step costs
# ~3 s on three times the observations (12 s instead of 22 s at 1e-6)


def _ba(pc, rec, cfg: SfMConfig, principal_point: bool, tolerance: float | None = None) -> float:
    """One global bundle adjustment in place (to cfg.ba_tolerance unless told); returns the RMS reprojection
    error of the points."""
    opt = pc.BundleAdjustmentOptions(refine_focal_length=True, refine_principal_point=principal_point,
                                     refine_extra_params=True, print_summary=False)
    opt.ceres.loss_function_type = getattr(pc.LossFunctionType, cfg.ba_loss.upper())
    opt.ceres.loss_function_scale = cfg.ba_loss_scale
    opt.ceres.solver_options.num_threads = cfg.num_threads
    opt.ceres.solver_options.function_tolerance = cfg.ba_tolerance if tolerance is None else tolerance
    pc.bundle_adjustment(rec, opt)
    errs = np.fromiter((p.error for p in rec.points3D.values()), dtype=np.float64)
    return float(np.sqrt(np.mean(errs ** 2))) if errs.size else 0.0


def refine_intrinsics(pc, rec, cfg: SfMConfig, mode: str | bool = "auto") -> dict[str, Any]:
    """Final global BA; with mode "auto" the principal point is freed only when the data asks for it.

    ns-process-data always frees (cx, cy). On a short arc that lets it drift: on the simulator it moved ~1 px and
    raised rotation error 5x (0.024 -> 0.128 deg) while the reprojection error did not change (-0.03 %). On fox, a real
    phone whose principal point is 1 % off-centre, freeing it cut the RMS error by 0.8 % and the disagreement with the
    reference by 2.5x. So "auto" keeps the free solution only when it lowers the RMS error by > 0.3 % (two extra
    parameters on tens of thousands of observations explain ~0.003 %).
    """
    if mode is False or mode == "fixed":
        return {"principal_point": "fixed", "rms_px": _ba(pc, rec, cfg, False)}
    if mode is True or mode == "refine":
        return {"principal_point": "refined", "rms_px": _ba(pc, rec, cfg, True)}
    fixed_rms = _ba(pc, rec, cfg, False)
    trial = pc.Reconstruction(rec)
    free_rms = _ba(pc, trial, cfg, True)
    gain = (fixed_rms - free_rms) / max(fixed_rms, 1e-12)
    cam_a, cam_b = next(iter(rec.cameras.values())), next(iter(trial.cameras.values()))
    shift = float(np.hypot(cam_b.principal_point_x - cam_a.principal_point_x,
                           cam_b.principal_point_y - cam_a.principal_point_y))
    shift_rel = shift / float(np.hypot(cam_a.width, cam_a.height))
    info = {"rms_fixed_px": round(fixed_rms, 5), "rms_free_px": round(free_rms, 5), "gain": round(gain, 5),
            "shift_px": round(shift, 3)}
    # phones put the principal point within ~1 % of the centre; a larger move is the free point absorbing outliers
    if gain > PP_MIN_GAIN and shift_rel < PP_MAX_SHIFT:
        return {"principal_point": "refined", **info, "_rec": trial}  # the caller swaps in the refined model
    return {"principal_point": "fixed", **info}


def ladder(cfg: SfMConfig, n: int, mixed_octaves: bool = False, extended: bool = False) -> list[Rung]:
    """The base attempt, then what to try when too few frames register (each rung only adds matches).
    mixed_octaves: only some frames got SIFT's upsampled octave (`fine_frames`); auto key_stride then maps all
    frames at once, since the strided way gives the fine frames' tracks fewer views, unless `extended`: the tracks
    are extended into their views before the final BA (simulator, 300 frames at 640x480: 0.038 deg and 0.016 %
    in 203 s with stride 3, 0.038 deg and 0.017 % in 217 s all at once)."""
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


def model_stats(rec) -> dict[str, Any]:
    return {"registered": int(rec.num_reg_images()), "points3D": int(rec.num_points3D()),
            "mean_reproj_error_px": float(rec.compute_mean_reprojection_error()),
            "mean_track_length": float(rec.compute_mean_track_length())}


# ----------------------------------------------------------------------------------------------------------------
# orientation and export
# ----------------------------------------------------------------------------------------------------------------
def _rot_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation taking unit vector a onto unit vector b."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(np.dot(a, b))
    if c < -1 + 1e-10:
        axis = np.cross(a, [1.0, 0, 0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def estimate_up(c2w_cv: np.ndarray, method: str = "vertical") -> np.ndarray:
    """World 'up' from OpenCV camera-to-world poses.

    "vertical": a handheld camera's x axis stays roughly horizontal, so up is the direction most orthogonal to all
    x axes (smallest singular vector), signed by the mean camera up (-y). Falls back to the mean up when the x axes
    span a single direction (a pure pan). "up": the mean camera up (nerfstudio's default, biased when cameras pitch).
    """
    mean_up = -c2w_cv[:, :3, 1].mean(axis=0)
    mean_up /= np.linalg.norm(mean_up)
    if method == "up":
        return mean_up
    x = c2w_cv[:, :3, 0]
    _, s, vt = np.linalg.svd(x, full_matrices=False)
    if s[1] > 0.17 * np.sqrt(len(x)):
        up = vt[2]
        return up if np.dot(up, mean_up) > 0 else -up
    up = mean_up - vt[0] * np.dot(mean_up, vt[0])
    return up / np.linalg.norm(up)


def orientation_transform(c2w_cv: np.ndarray, method: str, center_scale: bool) -> np.ndarray:
    """4x4 similarity applied to world points: up -> +Z, cameras centred, max |t| = 1."""
    T = np.eye(4)
    if method != "none":
        T[:3, :3] = _rot_between(estimate_up(c2w_cv, method), np.array([0.0, 0.0, 1.0]))
    if center_scale:
        c = (T[:3, :3] @ c2w_cv[:, :3, 3].T).T
        mean = c.mean(axis=0)
        ext = float(np.abs(c - mean).max())
        s = 1.0 / ext if ext > 1e-9 else 1.0
        T[:3, :3] *= s
        T[:3, 3] = -s * mean
    return T


def apply_similarity(T: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """Similarity on world coordinates applied to camera-to-world poses (rotation kept orthonormal)."""
    s = np.cbrt(np.linalg.det(T[:3, :3]))
    R = T[:3, :3] / s
    out = np.array(c2w, dtype=np.float64, copy=True)
    out[..., :3, :3] = R @ c2w[..., :3, :3]
    out[..., :3, 3] = (T[:3, :3] @ c2w[..., :3, 3][..., None])[..., 0] + T[:3, 3]
    return out


def camera_intrinsics(cam) -> Intrinsics:
    """nerfstudio keys for a COLMAP camera; every perspective model is written as OPENCV (as colmap_to_json does)."""
    p = np.asarray(cam.params, dtype=np.float64)
    name = cam.model.name if hasattr(cam.model, "name") else str(cam.model_name)
    w, h = int(cam.width), int(cam.height)
    if name in ("SIMPLE_PINHOLE",):
        return Intrinsics(w, h, p[0], p[0], p[1], p[2], camera_model="OPENCV")
    if name == "PINHOLE":
        return Intrinsics(w, h, p[0], p[1], p[2], p[3], camera_model="OPENCV")
    if name == "SIMPLE_RADIAL":
        return Intrinsics(w, h, p[0], p[0], p[1], p[2], k1=p[3], camera_model="OPENCV")
    if name == "RADIAL":
        return Intrinsics(w, h, p[0], p[0], p[1], p[2], k1=p[3], k2=p[4], camera_model="OPENCV")
    if name == "OPENCV":
        return Intrinsics(w, h, p[0], p[1], p[2], p[3], k1=p[4], k2=p[5], p1=p[6], p2=p[7], camera_model="OPENCV")
    raise StageError(f"camera model {name} cannot be written to transforms.json; use RADIAL, SIMPLE_RADIAL or OPENCV")


def rec_poses(rec) -> tuple[list[str], np.ndarray, list[int]]:
    """(image names, OpenCV camera-to-world (N, 4, 4), image ids) of the registered images, in name order."""
    items = sorted(((im.name, iid) for iid, im in rec.images.items() if im.has_pose), key=lambda t: t[0])
    c2w = []
    for _, iid in items:
        w2c = np.eye(4)
        w2c[:3, :4] = rec.images[iid].cam_from_world().matrix()
        c2w.append(np.linalg.inv(w2c))
    return [n for n, _ in items], np.asarray(c2w).reshape(-1, 4, 4), [i for _, i in items]


def write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Binary little-endian PLY (x, y, z float, red, green, blue uchar), as nerfstudio reads sparse_pc.ply."""
    n = len(xyz)
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n").encode()
    rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    if n:
        rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        rec["r"], rec["g"], rec["b"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    atomic.write_bytes(path, header + rec.tobytes())


def export(ds: Path, rec, cfg: SfMConfig, extra: dict | None = None) -> dict[str, Any]:
    """transforms.json (OpenGL c2w, oriented) and sparse_pc.ply; returns what was applied."""
    names, c2w_cv, ids = rec_poses(rec)
    if not names:
        raise StageError("the reconstruction has no registered images")
    cams = {rec.images[i].camera_id for i in ids}
    if len(cams) != 1:
        raise StageError(f"expected one shared camera, the model has {len(cams)}")
    intr = camera_intrinsics(rec.cameras[cams.pop()])
    T = orientation_transform(c2w_cv, cfg.orientation, cfg.center_scale)
    c2w_gl = opencv_to_opengl(apply_similarity(T, c2w_cv))
    frames = [Frame(file_path=f"{IMAGES_DIR}/{n}", c2w=m, extra={"colmap_im_id": int(i)})
              for n, m, i in zip(names, c2w_gl, ids)]
    pts = [(p.xyz, p.color) for p in rec.points3D.values()]
    xyz = np.asarray([p[0] for p in pts], dtype=np.float64).reshape(-1, 3)
    rgb = np.asarray([p[1] for p in pts], dtype=np.uint8).reshape(-1, 3)
    xyz_t = (T[:3, :3] @ xyz.T).T + T[:3, 3] if len(xyz) else xyz
    write_ply(ds / PLY_FILE, xyz_t, rgb)
    meta = {"applied_transform": T[:3, :].tolist(), "ply_file_path": PLY_FILE,
            "orientation_method": cfg.orientation, **(extra or {})}
    write_transforms(ds, intr, frames, extra=meta)  # written last, atomically
    return {"applied_transform_4x4": T.tolist(), "intrinsics": intr.to_json(), "frames": len(frames)}


# ----------------------------------------------------------------------------------------------------------------
# diagnosis of frames that did not register
# ----------------------------------------------------------------------------------------------------------------
def diagnose(pc, db: Path, names_all: list[str], registered: set[str]) -> list[dict]:
    """Group unregistered frames into index ranges with a likely cause (texture / overlap / placement)."""
    missing = [n for n in names_all if n not in registered]
    if not missing:
        return []
    causes: dict[str, str] = {}
    with pc.Database.open(str(db)) as d:
        by_name = {im.name: im.image_id for im in d.read_all_images()}
        best: dict[int, int] = {}
        pair_ids, geoms = d.read_two_view_geometries()
        for pid, g in zip(pair_ids, geoms):
            a, b = pc.pair_id_to_image_pair(pid)
            k = len(g.inlier_matches)
            best[a] = max(best.get(a, 0), k)
            best[b] = max(best.get(b, 0), k)
        for n in missing:
            iid = by_name.get(n)
            kp = d.num_keypoints_for_image(iid) if iid is not None else 0
            if kp < 300:
                causes[n] = "too little texture (few features)"
            elif best.get(iid, 0) < 30:
                causes[n] = "too little overlap with other frames (fast motion or motion blur)"
            else:
                causes[n] = "matched but could not be placed (moving objects, repeated texture or weak geometry)"
    groups: dict[str, list[int]] = {}
    for n in missing:
        try:
            idx = frame_index(n.rsplit(".", 1)[0])
        except ValueError:
            idx = names_all.index(n)
        groups.setdefault(causes[n], []).append(idx)
    return [{"frames": _ranges(v), "count": len(v), "cause": c} for c, v in groups.items()]


# ----------------------------------------------------------------------------------------------------------------
# the stage
# ----------------------------------------------------------------------------------------------------------------
def estimate_poses(ds: str | Path, **opts: Any) -> dict[str, Any]:
    """Run (or resume) SfM on DS/images and write transforms.json, colmap/sparse/0, sparse_pc.ply, reports/poses.json.

    Options are `SfMConfig` fields, plus `poses=FILE` to import a transforms.json / COLMAP model instead.
    Returns the report's figures.
    """
    ds = Path(ds)
    poses_file = opts.pop("poses", None)
    unknown = set(opts) - set(SfMConfig.__dataclass_fields__)
    if unknown:
        raise InputError(f"unknown pose options {sorted(unknown)}")
    cfg = SfMConfig(**{k: v for k, v in opts.items() if v is not None})
    if cfg.ba_loss not in BA_LOSSES:
        raise InputError(f"ba_loss must be one of {', '.join(BA_LOSSES)}, not {cfg.ba_loss!r}")
    images = list_images(ds / IMAGES_DIR)
    if len(images) < 3:
        raise InputError(f"{ds / IMAGES_DIR} has {len(images)} images; run `interreal frames INPUT {ds}` first "
                         "(at least 3 frames are needed)")
    _check_sizes(images)
    if poses_file is not None:
        return import_poses(ds, Path(poses_file), images, cfg)
    pc = _pycolmap(cfg.verbose)
    work = ds / COLMAP_DIR
    work.mkdir(parents=True, exist_ok=True)
    names = [p.name for p in images]
    settings = asdict(cfg)
    fps = provenance.fingerprints(ds, ["images"])  # what validate compares later (stale poses)
    with StageReport(ds, "poses", inputs={"images": len(images), "fingerprints": fps}, settings=settings) as rep:
        state_path = work / "state.json"
        state = _load_state(state_path)
        mask_dir, mask_src, mask_files = (prepare_masks(ds, images, work) if cfg.use_masks else (None, "off", []))
        if mask_src in ("sfm_masks", "masks.npy"):
            fps.update(provenance.fingerprints(ds, ["sfm_masks" if mask_src == "sfm_masks" else "masks"]))
        rep.data["inputs"]["masks"] = {"source": mask_src, "files": len(mask_files)}
        if cfg.use_masks and mask_src == "none":
            rep.warn("no object masks (DS/masks or DS/sfm_masks): moving parts may corrupt poses; run "
                     "`interreal masks DS --keyframes DIR` first", cause="no-masks")
        octave, side = resolve_octave(cfg, images[0]), max(_image_hw(images[0]))
        fine = fine_frames(cfg, len(images), octave, side)
        fp_feat = fingerprint("features", files_fingerprint(images), files_fingerprint(mask_files) if mask_files else None,
                              cfg.sfm_long_side, cfg.max_features, octave, cfg.camera_model, fine)
        db = work / "database.db"
        with rep.step("features") as st:
            if state.get("features") == fp_feat and db.exists():
                st["reused"] = True
            else:
                state = {"features": fp_feat}
                with NativeLog(work / "colmap.log", cfg.verbose) as log:
                    extract(pc, db, ds / IMAGES_DIR, names, mask_dir, cfg, octave, set(fine), log)
                atomic.write_json(state_path, state)
                st["reused"] = False
            with pc.Database.open(str(db)) as d:
                st["keypoints_mean"] = round(d.num_keypoints() / max(1, d.num_images()), 1)
        extend = use_track_extension(cfg, len(images), side)
        rungs = ladder(cfg, len(images), mixed_octaves=len(fine) < len(images), extended=extend)
        fp_final = fingerprint(fp_feat, {k: v for k, v in settings.items() if k not in ("verbose", "undistort")},
                               [asdict(r) for r in rungs])
        final = work / "sparse" / "0"
        if state.get("final") == fp_final and (ds / TRANSFORMS_FILE).exists() and final.exists():
            rep.steps["reuse"] = {"wall_s": 0.0, "reused": True}
            rec = pc.Reconstruction(str(final))
        else:
            rec = _run_ladder(pc, ds, work, db, names, rungs, fp_feat, state, state_path, cfg, rep,
                              refine=use_track_refinement(cfg, len(images), side),
                              extend=extend, mask_dir=mask_dir)
        total = len(images)
        stats = model_stats(rec)
        frac = stats["registered"] / total
        reg_names = {rec.images[i].name for i in rec.reg_image_ids()}
        dropped = diagnose(pc, db, names, reg_names)
        for g in dropped:
            rep.warn(f"frames {g['frames']} did not register: {g['cause']}", cause=g["cause"], frames=g["frames"])
        rep.figures.update({"registered": stats["registered"], "total": total, "registered_frac": round(frac, 4),
                            **{k: v for k, v in stats.items() if k != "registered"}, "unregistered": dropped})
        if frac < cfg.fail_below:
            raise StageError(f"SfM registered only {stats['registered']}/{total} frames ({frac:.0%} < "
                             f"{cfg.fail_below:.0%}); causes: {'; '.join(g['cause'] for g in dropped) or '?'}. "
                             "Film slower with more overlap and texture, or give masks of moving objects")
        if frac < 0.8:
            rep.warn(f"only {frac:.0%} of frames registered; training will see fewer views", cause="low-registration")
        if cfg.undistort:
            with rep.step("undistort"), NativeLog(work / "colmap.log", cfg.verbose):
                und = ds / "undistorted"
                shutil.rmtree(und, ignore_errors=True)
                pc.undistort_images(str(und), str(work / "sparse" / "0"), str(ds / IMAGES_DIR),
                                    num_threads=cfg.num_threads)
        with rep.step("export") as st:
            out = export(ds, rec, cfg)
            st.update(frames=out["frames"])
        rep.figures["intrinsics"] = out["intrinsics"]
        rep.figures["applied_transform"] = out["applied_transform_4x4"]
        state["final"] = fp_final
        atomic.write_json(state_path, state)
        figures = dict(rep.figures)
    figures["wall_s"] = rep.data.get("wall_s")
    figures["steps"] = {k: v.get("wall_s") for k, v in rep.steps.items()}
    return figures


def _check_sizes(images: list[Path]) -> None:
    sizes: dict[tuple[int, int], str] = {}
    for p in images:
        try:
            h, w = _image_hw(p)
        except Exception as exc:  # noqa: BLE001 - any decode failure is bad input
            raise InputError(f"{p} is not a readable image ({exc}); re-run `interreal frames`") from exc
        sizes.setdefault((w, h), p.name)
    if len(sizes) > 1:
        raise InputError(f"images in one dataset must share one size, found {sorted(sizes)} "
                         f"(e.g. {list(sizes.values())[:2]}); re-run `interreal frames`")


def _run_ladder(pc, ds, work, db, names, rungs, fp_feat, state, state_path, cfg, rep, refine: bool,
                extend: bool = False, mask_dir: Path | None = None):
    """Match + map rung after rung until >= retry_below registered; keep the best model (its tracks aligned when
    `refine`, then the final BA; when `extend`, tracks extended off the SfM masks and a last BA); write
    colmap/sparse/."""
    n = len(names)
    best = None  # (registered, -reproj, rung, rec, models)
    tried = []
    tree = work / "vocab_tree.bin"
    matched: list[str] = state.get("matched", [])
    for k, rung in enumerate(rungs):
        t0 = time.perf_counter()
        info: dict[str, Any] = {"rung": rung.name, **asdict(rung)}
        fp_match = fingerprint(fp_feat, rung.matcher, rung.overlap, rung.loop_detection, cfg.quadratic_overlap,
                               rung.stride)
        if k == 0 and matched and matched[0] != fp_match:
            with pc.Database.open(str(db)) as d:
                d.clear_matches()
                d.clear_two_view_geometries()
            matched = []
        if fp_match not in matched:
            with rep.step(f"match:{rung.name}") as st:
                if rung.loop_detection and rung.matcher == "sequential" \
                        and (state.get("tree") != fp_feat or not tree.exists()):
                    with rep.step("vocab_tree"), NativeLog(work / "colmap.log", cfg.verbose):
                        build_vocab_tree(db, tree, seed=cfg.seed)
                    state["tree"] = fp_feat
                with NativeLog(work / "colmap.log", cfg.verbose) as log:
                    match(pc, db, rung, tree, cfg, names, work, log)
                matched.append(fp_match)
                state["matched"] = matched
                atomic.write_json(state_path, state)
                with pc.Database.open(str(db)) as d:
                    st["verified_pairs"] = int(d.num_verified_image_pairs())
            info["verified_pairs"] = st["verified_pairs"]
        with rep.step(f"map:{rung.name}"):
            with NativeLog(work / "colmap.log", cfg.verbose) as log:
                models = reconstruct(pc, db, ds / IMAGES_DIR, work / "attempts" / rung.name, rung, cfg, log, names)
        sizes = sorted(((int(r.num_reg_images()), i) for i, r in models.items()), reverse=True)
        info["models"] = [s for s, _ in sizes]
        info["wall_s"] = round(time.perf_counter() - t0, 3)
        if sizes:
            rec = models[sizes[0][1]]
            st_ = model_stats(rec)
            info.update(st_)
            key = (st_["registered"], -st_["mean_reproj_error_px"])
            if best is None or key > best[0]:
                best = (key, rung, rec, models, sizes)
        else:
            info["registered"] = 0
        tried.append(info)
        rep.data["ladder"] = tried
        rep.write()
        if best is not None and best[0][0] >= cfg.retry_below * n:
            break
    if best is None:
        raise StageError(f"SfM found no model in {n} frames after {len(tried)} attempts "
                         f"({', '.join(t['rung'] for t in tried)}): the frames share too few features; film slower, "
                         "with more texture and overlap")
    _, rung, rec, models, sizes = best
    rep.figures["track_refinement"] = refine
    if refine:
        with rep.step("refine_tracks") as st, NativeLog(work / "colmap.log", cfg.verbose) as log:
            bar = log.bar(rec.num_reg_images(), "track refinement")
            st.update(refine_tracks(rec, ds / IMAGES_DIR, bar=bar))
            bar.close()
    with rep.step("refine_intrinsics") as st:
        with NativeLog(work / "colmap.log", cfg.verbose):
            res = refine_intrinsics(pc, rec, cfg, cfg.principal_point)
        rec = res.pop("_rec", rec)
        st.update(res)
    rep.figures["principal_point"] = res["principal_point"]
    rep.figures["track_extension"] = extend
    if extend:  # from the adjusted poses; (cx, cy) stays as decided on the matched tracks
        with rep.step("extend_tracks") as st, NativeLog(work / "colmap.log", cfg.verbose) as log:
            bar = log.bar(rec.num_reg_images(), "track extension")
            st.update(extend_tracks(rec, ds / IMAGES_DIR, mask_dir, window=cfg.track_window, bar=bar))
            bar.close()
        with rep.step("final_ba") as st, NativeLog(work / "colmap.log", cfg.verbose):
            st["rms_px"] = round(_ba(pc, rec, cfg, res["principal_point"] == "refined", EXTENDED_BA_TOLERANCE), 5)
    models = {**models, sizes[0][1]: rec}
    if len(tried) > 1:
        rep.figures["ladder_helped"] = rung.name if rung.name != "base" else None
    rep.figures["chosen_attempt"] = rung.name
    rep.figures["ladder"] = [{"rung": t["rung"], "registered": t.get("registered", 0)} for t in tried]
    rep.figures["models"] = [s for s, _ in sizes]
    if len(sizes) > 1 and sizes[0][0] < n:  # a side model that re-registers frames the main one has loses nothing
        rep.warn(f"SfM split into {len(sizes)} models of {[s for s, _ in sizes]} frames; the largest is kept "
                 "(others in colmap/sparse/1..)", cause="split-model")
    sparse = work / "sparse"
    shutil.rmtree(sparse, ignore_errors=True)
    for rank, (_, mid) in enumerate(sizes):
        d = sparse / str(rank)
        d.mkdir(parents=True)
        models[mid].write(str(d))
    shutil.rmtree(work / "attempts", ignore_errors=True)
    return rec


# ----------------------------------------------------------------------------------------------------------------
# CLI
# ----------------------------------------------------------------------------------------------------------------
def add_arguments(p) -> None:
    p.add_argument("dataset", type=Path, help="dataset folder with images/ (from `interreal frames`)")
    add_sfm_options(p)
    p.add_argument("--poses", type=Path, help="import poses from a transforms.json (nerfstudio/Polycam) or a COLMAP "
                                              "model folder instead of running SfM")
    p.epilog = ("examples:\n  interreal poses out/room                       # auto matcher, incremental mapping\n"
                "  interreal poses out/room --mapper global       # GLOMAP-style global SfM\n"
                "  interreal poses out/room --matcher exhaustive --camera-model OPENCV\n"
                "  interreal poses out/room --poses polycam/transforms.json   # skip SfM")


def add_sfm_options(p) -> None:
    p.add_argument("--sfm-long-side", type=int, default=1000, help="SIFT works at <= this long side (default 1000)")
    p.add_argument("--matcher", choices=("auto", "sequential", "exhaustive"), default="auto",
                   help="auto = exhaustive up to 40 frames, else sequential + loop detection")
    p.add_argument("--mapper", choices=("incremental", "global"), default="incremental")
    p.add_argument("--camera-model", choices=("SIMPLE_RADIAL", "RADIAL", "OPENCV"), default="RADIAL",
                   help="shared camera model (default RADIAL: f, cx, cy, k1, k2; never PINHOLE for phone frames)")
    p.add_argument("--max-features", type=int, default=2048)
    p.add_argument("--key-stride", type=int, default=0,
                   help="map every Nth frame first, then register the others into that model (0 = auto: 3 for "
                        f"sequential captures of >= {KEY_STRIDE_MIN} frames whose frames all get the same SIFT "
                        "octaves or whose tracks are extended, else 1 = all at once)")
    p.add_argument("--fine-octave-stride", type=int, default=0,
                   help="when SIFT sees frames at native size it also searches a 2x upsampled octave; give it to "
                        f"every Nth frame only (0 = auto: 3 for sequential captures of >= {KEY_STRIDE_MIN} frames of "
                        f">= {FINE_MIN_SIDE} px, else 1 = every frame; 1 is twice as slow there, a bit more accurate)")
    p.add_argument("--principal-point", choices=("auto", "refine", "fixed"), default="auto",
                   help="final bundle adjustment: free (cx, cy) when it clearly lowers the error (auto), always "
                        "(refine, as ns-process-data), or never")
    p.add_argument("--ba-loss", choices=BA_LOSSES, default="soft_l1",
                   help="robust loss of the final bundle adjustment (default soft_l1 at 1 px; trivial = squared, "
                        "as COLMAP's)")
    p.add_argument("--orientation", choices=("vertical", "up", "none"), default="vertical")
    p.add_argument("--refine-tracks", choices=("auto", "on", "off"), default="auto",
                   help="align each track's keypoints to one view (Lucas-Kanade) before the final bundle adjustment "
                        f"(auto: for sequential captures of >= {KEY_STRIDE_MIN} frames at native size >= "
                        f"{FINE_MIN_SIDE} px, where it was measured to help)")
    p.add_argument("--extend-tracks", choices=("auto", "on", "off"), default="auto",
                   help="before the final bundle adjustment, add each 3-D point to the frames where it projects but "
                        "was not matched (Lucas-Kanade from the projection, checked against the track's patch; "
                        "auto: sequential captures that SIFT sees at native size)")
    p.add_argument("--no-masks", action="store_true", help="do not mask object pixels out of SfM features")
    p.add_argument("--undistort", action="store_true", help="also write DS/undistorted/ (pinhole images, COLMAP model)")
    p.add_argument("--verbose", action="store_true", help="show COLMAP's log")


def sfm_options(args) -> dict[str, Any]:
    return {"sfm_long_side": args.sfm_long_side, "matcher": args.matcher, "mapper": args.mapper,
            "camera_model": args.camera_model, "max_features": args.max_features, "orientation": args.orientation,
            "key_stride": args.key_stride, "fine_octave_stride": args.fine_octave_stride,
            "refine_tracks": args.refine_tracks, "extend_tracks": args.extend_tracks,
            "use_masks": not args.no_masks, "verbose": args.verbose,
            "principal_point": args.principal_point, "undistort": args.undistort, "ba_loss": args.ba_loss}


def summary_lines(fig: dict[str, Any], ds: Path) -> list[str]:
    intr = fig.get("intrinsics", {})
    lines = [f"poses: {fig.get('registered')}/{fig.get('total')} frames registered"
             + (f", reprojection {fig['mean_reproj_error_px']:.2f} px, track length {fig['mean_track_length']:.1f}, "
                f"{fig['points3D']} points" if "mean_reproj_error_px" in fig else ""),
             f"  camera: {intr.get('w')}x{intr.get('h')} f=({intr.get('fl_x', 0):.1f}, {intr.get('fl_y', 0):.1f}) "
             f"c=({intr.get('cx', 0):.1f}, {intr.get('cy', 0):.1f}) k1={intr.get('k1', 0):.4f}"]
    if fig.get("steps"):
        lines.append("  time: " + ", ".join(f"{k} {v:.1f}s" for k, v in fig["steps"].items() if v is not None))
    if len(fig.get("ladder", [])) > 1:
        tried = ", ".join(f"{t['rung']} {t['registered']}/{fig.get('total')}" for t in fig["ladder"])
        lines.append(f"  retry ladder: {tried}; kept '{fig.get('chosen_attempt')}'")
    lines += warning_lines(ds, ["poses"])
    outs = [ds / TRANSFORMS_FILE] + ([ds / COLMAP_DIR / "sparse" / "0", ds / PLY_FILE] if "imported" not in fig else [])
    lines.append("  -> " + ", ".join(str(p) for p in outs + [ds / "reports" / "poses.json"]))
    return lines


def main(args) -> int:
    opts = sfm_options(args)
    fig = estimate_poses(args.dataset, poses=args.poses, **opts)
    print("\n".join(summary_lines(fig, args.dataset)))
    return 0


# ----------------------------------------------------------------------------------------------------------------
# --poses: import instead of SfM
# ----------------------------------------------------------------------------------------------------------------
def _name_lookup(ds: Path, images: list[Path]) -> dict[str, Path]:
    """Keys under which a pose file may name a dataset image: its name, its stem, and the source file it came from
    (reports/frames.json keeps frame name -> original file name for image folders)."""
    look: dict[str, Path] = {}
    for p in images:
        look.setdefault(p.name, p)
        look.setdefault(p.stem, p)
    frames_rep = ds / "reports" / "frames.json"
    try:
        src_names = json.loads(frames_rep.read_text()).get("figures", {}).get("source_names", {})
    except (OSError, ValueError):
        src_names = {}
    by_stem = {p.stem: p for p in images}
    for stem, original in src_names.items():
        if stem in by_stem:
            look.setdefault(original, by_stem[stem])
            look.setdefault(Path(original).stem, by_stem[stem])
    return look


def _match_name(look: dict[str, Path], name: str) -> Path | None:
    base = Path(name).name
    return look.get(base) or look.get(Path(base).stem)


def import_poses(ds: Path, file: Path, images: list[Path], cfg: SfMConfig) -> dict[str, Any]:
    """Poses from a nerfstudio/Polycam transforms.json (kept as given) or a COLMAP model (oriented as SfM is)."""
    if not file.exists():
        raise InputError(f"--poses {file} does not exist")
    h, w = _image_hw(images[0])
    look = _name_lookup(ds, images)
    with StageReport(ds, "poses", inputs={"images": len(images), "poses_file": str(file),
                                          "fingerprints": provenance.fingerprints(ds, ["images"])},
                     settings={"import": True, **asdict(cfg)}) as rep:
        if file.is_dir():
            frames, intr, T = _import_colmap(file, look, cfg)
            meta = {"applied_transform": T[:3, :].tolist(), "orientation_method": cfg.orientation}
        else:
            frames, intr = _import_transforms(file, look)
            T = np.eye(4)
            meta = {}
        if len(frames) < 3:
            raise InputError(f"--poses {file}: only {len(frames)} of its frames match images in {ds / IMAGES_DIR} "
                             "(matched by file name, stem, or the source file names in reports/frames.json)")
        intr = intr.scaled(w, h) if (intr.w, intr.h) != (w, h) else intr
        frames.sort(key=lambda f: f.file_path)
        write_transforms(ds, intr, frames, extra={**meta, "poses_imported_from": str(file)})
        matched = {Path(f.file_path).name for f in frames}
        missing = [p.name for p in images if p.name not in matched]
        if missing:
            rep.warn(f"{len(missing)} images have no pose in {file} and are left out of transforms.json "
                     f"(e.g. {missing[:3]})", cause="import")
        rep.figures.update({"registered": len(frames), "total": len(images),
                            "registered_frac": round(len(frames) / len(images), 4), "intrinsics": intr.to_json(),
                            "applied_transform": T.tolist(), "imported": str(file)})
        figures = dict(rep.figures)
    figures["wall_s"] = rep.data.get("wall_s")
    return figures


def _import_transforms(file: Path, look: dict[str, Path]) -> tuple[list[Frame], Intrinsics]:
    try:
        meta = json.loads(file.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"--poses {file} is not valid JSON ({exc})") from exc
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise InputError(f"--poses {file} has no 'frames' list (expected a nerfstudio/Polycam transforms.json)")
    frames: list[Frame] = []
    per_frame: list[Intrinsics] = []
    for e in meta["frames"]:
        p = _match_name(look, str(e.get("file_path", "")))
        if p is None or "transform_matrix" not in e:
            continue
        m = np.asarray(e["transform_matrix"], dtype=np.float64)
        if m.shape == (3, 4):
            m = np.vstack([m, [0, 0, 0, 1]])
        merged = {**meta, **e}
        if all(k in merged for k in ("fl_x", "cx", "cy", "w", "h")):
            per_frame.append(Intrinsics.from_json(merged))
        frames.append(Frame(file_path=f"{IMAGES_DIR}/{p.name}", c2w=m))
    if "fl_x" in meta and all(k in meta for k in ("cx", "cy", "w", "h")):
        intr = Intrinsics.from_json(meta)
    elif per_frame:
        intr = per_frame[0]  # Polycam writes per-frame intrinsics of one camera
    elif "camera_angle_x" in meta and frames:
        import math

        hh, ww = _image_hw(look[Path(frames[0].file_path).name])
        f = 0.5 * ww / math.tan(0.5 * float(meta["camera_angle_x"]))
        intr = Intrinsics(ww, hh, f, f, ww / 2, hh / 2, camera_model="OPENCV")
    else:
        raise InputError(f"--poses {file} has no intrinsics (fl_x/fl_y/cx/cy/w/h or camera_angle_x)")
    return frames, intr


def _import_colmap(folder: Path, look: dict[str, Path], cfg: SfMConfig) -> tuple[list[Frame], Intrinsics, np.ndarray]:
    import pycolmap

    cands = [folder, folder / "0", folder / "sparse" / "0", folder / "sparse"]
    model = next((c for c in cands if (c / "images.bin").exists() or (c / "images.txt").exists()), None)
    if model is None:
        raise InputError(f"--poses {folder} holds no COLMAP model (images.bin / images.txt)")
    rec = pycolmap.Reconstruction(str(model))
    names, c2w_cv, ids = rec_poses(rec)
    keep = [(k, _match_name(look, n)) for k, n in enumerate(names)]
    keep = [(k, p) for k, p in keep if p is not None]
    if not keep:
        raise InputError(f"--poses {folder}: no image of the model matches {IMAGES_DIR}/")
    c2w_cv = c2w_cv[[k for k, _ in keep]]
    T = orientation_transform(c2w_cv, cfg.orientation, cfg.center_scale)
    c2w_gl = opencv_to_opengl(apply_similarity(T, c2w_cv))
    intr = camera_intrinsics(rec.cameras[rec.images[ids[keep[0][0]]].camera_id])
    frames = [Frame(file_path=f"{IMAGES_DIR}/{p.name}", c2w=m) for (_, p), m in zip(keep, c2w_gl)]
    return frames, intr, T


# ----------------------------------------------------------------------------------------------------------------
# accuracy against a reference (tests, benchmark)
# ----------------------------------------------------------------------------------------------------------------
