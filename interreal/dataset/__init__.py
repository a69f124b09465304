"""Read, write and validate the LiveScene dataset layout (see DESIGN.md and `interreal.conventions`).

This is the public dataset API: `livescene` reads datasets through `load_dataset` only. It reads our datasets, the
official InterReal (nerfstudio `transforms.json`) layout and the official OmniSim (Blender-style `camera_angle_x`,
`file_path` without extension) layout. `types`: the data classes; `images`: the one image reader; `io`: readers and
writers of every file; `validation`: `validate` and the `interreal validate` command.
"""

from ..errors import DatasetError
from ..images import IMAGE_SUFFIXES, decode_image, image_hw, image_size, list_images, read_image_rgb
from .io import (
    SAME_STATE,
    camera_angle_intrinsics,
    known_states,
    label_value_problem,
    load_dataset,
    load_transforms,
    npy_header,
    parse_transforms,
    pose_matrix,
    read_articulation,
    read_labels,
    read_labels_raw,
    read_mapping,
    point_cloud_path,
    read_point_cloud,
    read_prompts,
    read_transforms_file,
    read_yaml,
    write_articulation,
    write_labels,
    write_mapping,
    write_mask,
    write_prompts,
    write_transforms,
)
from .types import (
    CAMERA_MODELS,
    DISTORTION_KEYS,
    INTRINSIC_KEYS,
    MOTION_KINDS,
    Articulation,
    Frame,
    Intrinsics,
    LiveSceneDataset,
)
from .validation import (
    MIN_LABEL_FRACTION,
    MIN_LABELS,
    Problem,
    ValidationResult,
    format_problems,
    format_summary,
    label_shortage,
    validate,
)

__all__ = [
    "CAMERA_MODELS", "DISTORTION_KEYS", "IMAGE_SUFFIXES", "INTRINSIC_KEYS", "MIN_LABELS", "MIN_LABEL_FRACTION",
    "MOTION_KINDS", "Articulation", "DatasetError", "Frame", "Intrinsics", "LiveSceneDataset", "Problem",
    "ValidationResult", "format_problems", "format_summary", "decode_image", "image_hw", "image_size", "camera_angle_intrinsics", "known_states", "SAME_STATE", "label_shortage",
    "label_value_problem", "list_images", "load_dataset", "load_transforms", "npy_header", "parse_transforms", "pose_matrix",
    "read_articulation", "read_image_rgb", "read_labels", "read_labels_raw", "read_mapping", "point_cloud_path", "read_point_cloud",
    "read_prompts", "read_transforms_file", "read_yaml", "validate", "write_articulation", "write_labels", "write_mapping", "write_mask",
    "write_prompts", "write_transforms",
]
