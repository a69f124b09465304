"""Camera poses with pycolmap: `interreal poses DS` -> transforms.json, colmap/sparse/0, sparse_pc.ply.

What differs from ns-process-data (its recipe: ../shared/reference/process-data.md), and why (figures in
docs/sfm-measurements.md, from recipes/bench_poses.py):
- SIFT at <= 1000 px with a feature cap (training images stay at their size; COLMAP rescales keypoints), so
  extraction and matching cost a fraction of full-resolution SfM at no accuracy loss.
- One shared RADIAL camera (f, cx, cy, k1, k2; never PINHOLE: phone frames are distorted).
- Per-image masks drop object pixels from features: moving parts otherwise corrupt poses.
- Exhaustive matching for small sets, sequential (quadratic overlap) + loop detection with a vocabulary tree built
  from the capture's own descriptors for larger ones (no download: an empty tree path aborts the process offline).
- Frames SIFT sees at native size get its 2x upsampled octave (in long videos every 3rd frame only); long videos
  whose frames all get the same octaves map every 3rd frame first and register the rest into that model.
- Before the final BA, on dense captures, every track's keypoints are aligned to one view of the track and each
  3-D point is looked for in the nearby views where it projects but SIFT did not match it (`keypoints.py`).
- The LARGEST model is kept (not sparse/0) and the others are reported; under 90 % registered a retry ladder runs.
- Gravity-like orientation ("vertical"), centred and scaled to max |t| = 1; the transform is recorded.
- Resumable: features, matches and the final model are reused when their inputs and settings are unchanged.

- Before mapping, a check of seconds (`parallax`) refuses a camera that only turned in place or stood still.
- Known intrinsics (`--intrinsics K.txt | K.json`, `intrinsics`) are scaled to the images and held by every BA.

Modules: `config` (settings, auto rules, pairs, the retry ladder), `colmap` (the one pycolmap layer, shared with
`interreal.motions`), `ladder` (the run's workspace, the attempts and the polishing of the kept model), `parallax`,
`intrinsics`, `geometry`, `export`, `pose_import` (--poses), `stage` (`estimate_poses`), `cli` (`interreal poses`).
"""

from .cli import add_arguments, add_sfm_options, main, sfm_options, summary_lines
from .colmap import NativeLog, load_pycolmap, model_stats
from .config import (
    BA_LOSSES,
    FINE_MIN_SIDE,
    KEY_STRIDE_MIN,
    Rung,
    SfMConfig,
    fine_frames,
    key_positions,
    ladder,
    resolve_octave,
    sequential_pairs,
    strided_pairs,
    use_track_extension,
    use_track_refinement,
)
from .export import export, write_ply
from .geometry import _rot_between, apply_similarity, camera_intrinsics, estimate_up, orientation_transform, rec_poses
from .ladder import refine_intrinsics
from .pose_import import import_poses
from .stage import estimate_poses, make_config, prepare_masks

__all__ = [
    "BA_LOSSES", "FINE_MIN_SIDE", "KEY_STRIDE_MIN", "NativeLog", "Rung", "SfMConfig", "_rot_between",
    "add_arguments", "add_sfm_options", "apply_similarity", "camera_intrinsics", "estimate_poses", "estimate_up",
    "export", "fine_frames", "import_poses", "key_positions", "ladder", "load_pycolmap", "main", "make_config",
    "model_stats", "orientation_transform", "prepare_masks", "rec_poses", "refine_intrinsics", "resolve_octave",
    "sequential_pairs", "sfm_options", "strided_pairs", "summary_lines", "use_track_extension",
    "use_track_refinement", "write_ply",
]
