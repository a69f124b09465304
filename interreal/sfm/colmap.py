"""The thin pycolmap layer every reconstruction goes through (the pose stage and `interreal.motions`): SIFT
extraction, matching of listed pairs and loop queries, incremental / global mapping, bundle adjustment, and
COLMAP's native log kept out of the terminal. A change of matcher or extractor settings happens here once.

Always on the CPU (`use_gpu=False`): results do not depend on the machine's GPU.
"""

from __future__ import annotations

import os
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
import pycolmap
from tqdm import tqdm

from ..errors import StageError


def load_pycolmap(verbose: bool):
    """pycolmap with its glog verbosity set (quiet unless `verbose`)."""
    pycolmap.logging.minloglevel = 0 if verbose else 2
    pycolmap.logging.stderrthreshold = 0 if verbose else 2
    return pycolmap


class NativeLog:
    """Send COLMAP's native log (glog on fd 2, which `minloglevel` does not fully silence) to `path` unless
    verbose; progress bars keep writing to the terminal through a duplicate of the original stderr."""

    def __init__(self, path: Path, verbose: bool):
        self.path, self.verbose = path, verbose
        self.term = None
        self._saved = None

    def __enter__(self) -> "NativeLog":
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
        sys.stderr.flush()
        if self._saved is not None:
            os.dup2(self._saved, 2)
            os.close(self._saved)
        self.term.close()

    def bar(self, total: int, desc: str):
        return tqdm(total=total, desc=desc, file=self.term, leave=False, unit="pair" if "match" in desc else "img")


def _bar(log: NativeLog | None, total: int, desc: str):
    return log.bar(total, desc) if log else None


def _chunks(items: list, size: int | None) -> list[list]:
    size = size or max(1, len(items))
    return [items[k:k + size] for k in range(0, len(items), size)]


def threads(n: int) -> int:
    """pycolmap's thread count for a setting `n`: -1 (all cores) becomes OMP_NUM_THREADS where that is set, so a
    batch worker given a CPU budget (`interreal batch`) keeps to it instead of taking every core."""
    if n > 0:
        return n
    try:
        return max(1, int(os.environ["OMP_NUM_THREADS"]))
    except (KeyError, ValueError):
        return -1


@dataclass(frozen=True)
class Extraction:
    """SIFT settings of one database: one shared camera of `camera_model` (`camera_params`: its fixed intrinsics
    as COLMAP's comma list, "" = estimated later), features at <= `max_image_size` px, at most `max_features`."""

    camera_model: str
    max_image_size: int
    max_features: int
    camera_params: str = ""
    num_threads: int = -1


def extract_features(pc, db: Path, image_dir: Path, groups: list[tuple[int, list[str]]], ex: Extraction,
                     mask_dir: Path | None = None, log: NativeLog | None = None, chunk: int | None = 16) -> None:
    """SIFT into a fresh database: each (first octave, image names) group at its octave, in chunks of `chunk`
    images (for the progress bar; None = one call); every chunk reuses the one shared camera."""
    ext = pc.FeatureExtractionOptions(num_threads=threads(ex.num_threads), use_gpu=False,
                                      max_image_size=ex.max_image_size)
    ext.sift.max_num_features = ex.max_features
    db.unlink(missing_ok=True)
    bar = _bar(log, sum(len(g) for _, g in groups), "features")
    first = True
    for octave, group in groups:
        ext.sift.first_octave = octave
        for part in (_chunks(group, chunk) if group else []):
            reader = pc.ImageReaderOptions(camera_model=ex.camera_model)
            if ex.camera_params:
                reader.camera_params = ex.camera_params
            if mask_dir is not None:
                reader.mask_path = str(mask_dir)
            if not first:
                reader.existing_camera_id = 1
            first = False
            pc.extract_features(str(db), str(image_dir), image_names=part, camera_mode=pc.CameraMode.SINGLE,
                                reader_options=reader, extraction_options=ext, device=pc.Device.cpu)
            if bar is not None:
                bar.update(len(part))
    if bar is not None:
        bar.close()
    with pc.Database.open(str(db)) as d:
        if d.num_cameras() != 1:
            raise StageError(f"feature extraction made {d.num_cameras()} cameras, expected one shared camera")


CROP_PAD = 24  # px kept around a mask's box: SIFT's border and its largest octave's support reach past the part


def extract_cropped(pc, db: Path, image_dir: Path, names: list[str], ex: Extraction, mask_dir: Path,
                    first_octave: int = -1) -> None:
    """SIFT of one masked region per image into a fresh database: each image's mask box (`mask_dir/<name>.png`,
    COLMAP's layout) cropped, its features put back in the frame's coordinates and kept where the mask is set, as
    `extract_features` keeps them; one shared camera. A part a tenth of the frame costs a tenth of the time (at
    `first_octave` -1 the whole frame is upsampled twice over)."""
    opt = pc.FeatureExtractionOptions(num_threads=threads(ex.num_threads), use_gpu=False,
                                      max_image_size=ex.max_image_size)
    opt.sift.max_num_features, opt.sift.first_octave = ex.max_features, first_octave
    reader = pc.ImageReaderOptions(camera_model=ex.camera_model)
    if ex.camera_params:
        reader.camera_params = ex.camera_params
    db.unlink(missing_ok=True)
    pc.Database.open(str(db)).close()  # import_images wants the file there
    pc.import_images(str(db), str(image_dir), camera_mode=pc.CameraMode.SINGLE, image_names=names,
                     options=reader)
    sift = pc.FeatureExtractor.create(opt, pc.Device.cpu)
    with pc.Database.open(str(db)) as d:
        if d.num_cameras() != 1:
            raise StageError(f"image import made {d.num_cameras()} cameras, expected one shared camera")
        for name in names:
            mask = cv2.imread(str(mask_dir / f"{name}.png"), cv2.IMREAD_GRAYSCALE)
            image = pc.Bitmap.read(str(image_dir / name), False)  # COLMAP's own grey, as its extractor reads
            if mask is None or image is None:
                raise StageError(f"cannot read {name} or its mask in {mask_dir} for feature extraction")
            kp, desc = _masked_features(sift, image.to_array(), mask > 0)
            image_id = d.read_image_with_name(name).image_id
            d.write_keypoints(image_id, kp)
            d.write_descriptors(image_id, desc)


def _masked_features(sift, grey: np.ndarray, mask: np.ndarray):
    """(K, 6) keypoints in frame pixels and their descriptors, of the crop around `mask` (h, w) bool, kept where
    the mask holds (COLMAP's rule: the pixel a keypoint's coordinates truncate to)."""
    ys, xs = np.nonzero(mask)
    if not len(xs):
        return (np.zeros((0, 6), np.float32),
                pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, np.zeros((0, 128), np.uint8)))
    h, w = mask.shape
    x0, y0 = max(0, xs.min() - CROP_PAD), max(0, ys.min() - CROP_PAD)
    x1, y1 = min(w, xs.max() + CROP_PAD + 1), min(h, ys.max() + CROP_PAD + 1)
    kps, desc = sift.extract_from_uint8_array(np.ascontiguousarray(grey[y0:y1, x0:x1]))
    kp = np.array([[k.x + x0, k.y + y0, k.a11, k.a12, k.a21, k.a22] for k in kps], np.float32).reshape(-1, 6)
    xi = np.clip(kp[:, 0].astype(int), 0, w - 1)
    yi = np.clip(kp[:, 1].astype(int), 0, h - 1)
    keep = mask[yi, xi]
    return kp[keep], pycolmap.FeatureDescriptors(desc.type, np.ascontiguousarray(desc.data[keep]))


def match_pairs(pc, db: Path, names: list[str], pairs: list[tuple[int, int]], listing: Path, seed: int,
                num_threads: int = -1, log: NativeLog | None = None, desc: str = "matching",
                chunk: int | None = 200) -> None:
    """Match and verify the listed pairs (positions into `names`; pairs already matched are skipped by COLMAP),
    `chunk` pairs a call (for the progress bar; None = one call). `listing`: a scratch file, removed after."""
    bar = _bar(log, len(pairs), desc)
    for part in _chunks(pairs, chunk):
        listing.write_text("".join(f"{names[a]} {names[b]}\n" for a, b in part))
        pc.match_image_pairs(str(db), matching_options=_matching(pc, num_threads),
                             pairing_options=pc.ImportedPairingOptions(match_list_path=str(listing)),
                             verification_options=_verification(pc, seed), device=pc.Device.cpu)
        if bar is not None:
            bar.update(len(part))
    if bar is not None:
        bar.close()
    listing.unlink(missing_ok=True)


def match_loops(pc, db: Path, tree: Path, queries: list[str], listing: Path, seed: int, num_threads: int = -1,
                num_images: int = 10) -> None:
    """Loop detection: each query image matched with its `num_images` nearest images in the vocabulary tree."""
    if not tree.exists():
        raise StageError("loop detection needs a local vocabulary tree (internal error: tree not built)")
    listing.write_text("".join(f"{n}\n" for n in queries))
    popt = pc.VocabTreePairingOptions(num_images=num_images, vocab_tree_path=str(tree),
                                      match_list_path=str(listing), num_threads=threads(num_threads))
    pc.match_vocabtree(str(db), matching_options=_matching(pc, num_threads), pairing_options=popt,
                       verification_options=_verification(pc, seed), device=pc.Device.cpu)


def _matching(pc, num_threads: int):
    return pc.FeatureMatchingOptions(num_threads=threads(num_threads), use_gpu=False)


def _verification(pc, seed: int):
    vopt = pc.TwoViewGeometryOptions()
    vopt.ransac.random_seed = seed
    return vopt


def build_vocab_tree(pycolmap, db_path: Path, out: Path, max_descriptors: int = 50_000, seed: int = 0) -> Path:
    """A vocabulary tree (for loop detection) from the capture's own descriptors: no download, works offline."""
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
                                               num_threads=threads(-1)), fd)
    tmp = out.with_suffix(".tmp")
    vi.write(str(tmp))
    tmp.replace(out)
    return out


def fresh_model_dir(pc, out: Path, seed: int) -> None:
    """An empty `out` for the mapper's models, and pycolmap's global seed set (mapping is then repeatable)."""
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    pc.set_random_seed(seed)


def incremental_options(pc, num_threads: int, seed: int, fixed_intrinsics: bool = False):
    """Incremental mapper options (models of >= 3 images); `fixed_intrinsics`: the camera is known, BA keeps it."""
    opt = pc.IncrementalPipelineOptions(num_threads=threads(num_threads), random_seed=seed, min_model_size=3)
    if fixed_intrinsics:
        opt.ba_refine_focal_length = opt.ba_refine_principal_point = opt.ba_refine_extra_params = False
    return opt


def incremental_map(pc, db: Path, image_dir: Path, out: Path, opt, input_path: Path | None = None,
                    tick: Callable[[], None] | None = None) -> dict[int, Any]:
    """Model id -> reconstruction from the incremental mapper (`input_path`: a model to register into)."""
    kw = {"input_path": str(input_path)} if input_path is not None else {}
    return dict(pc.incremental_mapping(str(db), str(image_dir), str(out), options=opt, next_image_callback=tick, **kw))


def global_map(pc, db: Path, image_dir: Path, out: Path, num_threads: int, seed: int,
               fixed_intrinsics: bool = False) -> dict[int, Any]:
    """Model id -> reconstruction from the global (GLOMAP-style) mapper, on the CPU (`fixed_intrinsics`: the
    camera is known, its BA keeps it)."""
    gopt = pc.GlobalPipelineOptions(num_threads=threads(num_threads), random_seed=seed)
    gopt.mapper.global_positioning.use_gpu = False
    gopt.mapper.bundle_adjustment.ceres.use_gpu = False
    if fixed_intrinsics:
        ba = gopt.mapper.bundle_adjustment
        ba.refine_focal_length = ba.refine_principal_point = ba.refine_extra_params = False
    return dict(pc.global_mapping(str(db), str(image_dir), str(out), options=gopt))


def bundle_adjust(pc, rec, principal_point: bool, loss: str, loss_scale: float, tolerance: float,
                  num_threads: int = -1, intrinsics: bool = True) -> float:
    """One global bundle adjustment in place (focal length and distortion free unless `intrinsics` is False,
    (cx, cy) when `principal_point`; robust `loss`, a pycolmap.LossFunctionType in lower case); returns the
    points' RMS reprojection error."""
    opt = pc.BundleAdjustmentOptions(refine_focal_length=intrinsics, refine_principal_point=principal_point,
                                     refine_extra_params=intrinsics, print_summary=False)
    opt.ceres.loss_function_type = getattr(pc.LossFunctionType, loss.upper())
    opt.ceres.loss_function_scale = loss_scale
    opt.ceres.solver_options.num_threads = threads(num_threads)
    opt.ceres.solver_options.function_tolerance = tolerance
    pc.bundle_adjustment(rec, opt)
    errs = np.fromiter((p.error for p in rec.points3D.values()), dtype=np.float64)
    return float(np.sqrt(np.mean(errs ** 2))) if errs.size else 0.0


def model_stats(rec) -> dict[str, Any]:
    """Registered images, points, mean reprojection error and track length of a reconstruction."""
    return {"registered": int(rec.num_reg_images()), "points3D": int(rec.num_points3D()),
            "mean_reproj_error_px": float(rec.compute_mean_reprojection_error()),
            "mean_track_length": float(rec.compute_mean_track_length())}
