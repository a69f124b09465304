"""Round trip with the official LiveScene code (Tavish9/livescene; facts in ../shared/reference/livescene-official.md).

Out: `interreal export-official DS OUT` writes a copy of a dataset that the official trainer reads without a silent
change, and `--check FOLDER` runs the official reader's rules on any folder. The rules that bite:
- every frame of a split needs `masks/<fid>.npy`, exactly one-hot over objects + background, at the image size
  (nothing is resized; nerfstudio downsizes images > 1600 px only when an `images_<n>/` folder exists);
- labels are zero-filled where a (frame, object) pair has none and min-max normalised per object over each split
  (train and eval apart), zeros included: a split whose largest label for an object is 0.5 reads it as 1.0, and one
  with no non-zero label for an object divides 0 by 0 (NaN). A label survives unchanged only when the split's
  column holds a 1.0 and a 0 (a 0.0 label or an unlabelled frame);
- the split: real data (nerfstudio layout) trains on `linspace(0, N-1, ceil(0.9 N))` of the frames sorted by file
  path and evaluates on the rest, unless transforms.json lists `train_filenames` / `val_filenames` /
  `test_filenames`; synthetic data (Blender layout) evaluates on the even positions, trains on the odd ones.

In: official data may store raw interaction values outside [0, 1] and mask pixels with no channel set; our reader
normalises such labels the official way (with a note, never a clip) and reads empty pixels as unknown. A folder is
read as official data when interreal did not write it (no `reports/`) and its cameras are in an official layout
(OmniSim's `camera_angle_x`, or Polycam's per-frame intrinsics); our own datasets stay strict (a 5.0 is a mistake).

Modules: `rules` (the reader's rules, the official split, `check_official`), `export` (split choice, scene box,
`export_official`), `interreal.dataset.official` (official data in our reader), `cli` (the command).
"""

from __future__ import annotations

from .export import choose_split, export_official, nerfstudio_transform, ns_train_command, scene_scale
from ..dataset.official import is_official_data, label_columns, normalise_raw_labels, raw_value_ok
from .rules import (EVAL_INTERVAL, SPLIT_KEYS, TRAIN_FRACTION, OfficialCheck, check_official, fraction_split,
                    interval_split, minmax_columns, official_frames, official_positions, official_split)

__all__ = ["EVAL_INTERVAL", "SPLIT_KEYS", "TRAIN_FRACTION", "OfficialCheck", "check_official", "choose_split",
           "export_official", "fraction_split", "interval_split", "is_official_data", "label_columns",
           "minmax_columns", "nerfstudio_transform", "normalise_raw_labels", "ns_train_command", "official_frames",
           "official_positions", "official_split", "raw_value_ok", "scene_scale"]
