"""Every file and folder name of the dataset layout, in one place (DESIGN.md draws the tree).

Stages build paths from these names only, so a rename happens here and nowhere else. Frame naming, the mask
encoding and camera axes are in `interreal.conventions`.
"""

from __future__ import annotations

# what livescene and the official reader read
IMAGES_DIR = "images"  # the frames, frame_<index>.png
MASKS_DIR = "masks"  # <fid>.npy one-hot masks, background last
TRANSFORMS_FILE = "transforms.json"  # intrinsics and OpenGL camera-to-world poses (nerfstudio)
MAPPING_FILE = "mapping.yaml"  # object id -> name
LABELS_FILE = "key_frame_value.yaml"  # frame key -> {object: state}
PROMPTS_FILE = "prompts.yaml"  # object -> language prompt
ARTICULATION_FILE = "articulation.json"  # optional part motions
PLY_FILE = "sparse_pc.ply"  # the SfM point cloud; transforms.json's `ply_file_path` names it (this by default)

# what the stages keep for themselves
REPORTS_DIR = "reports"  # <stage>.json: what each stage did and from what (`report.report_path`)
COLMAP_DIR = "colmap"  # the pose stage's database and models (sparse/<n>)
UNDISTORTED_DIR = "undistorted"  # undistorted frames when the poses stage writes them
SFM_MASKS_DIR = "sfm_masks"  # <fid>.png: pixels SfM ignores (moving parts), written by the masks stage
TRANSIENTS_DIR = "transients"  # <fid>.png: people / hands (255), left out of SfM, motions, training
PREVIEWS_DIR = "previews"  # the masks stage's contact sheets and videos
KEYFRAMES_DIR = "keyframes"  # where `interreal annotate` stores keyframe masks (the `--keyframes DIR` format)
LOCK_FILE = ".edit.lock"  # held while a label tool edits the dataset
CACHE_DIR = "cache"  # what a stage keeps to make its next run faster, never read as a result
MASKS_CACHE_DIR = f"{CACHE_DIR}/masks"  # the masks stage's stretches of frames (`interreal.masks.reuse`)
TRANSIENTS_CACHE_FILE = f"{CACHE_DIR}/transients_auto.npz"  # `--transients auto`'s layer (`transients.auto`)
MOTIONS_DIR = "motions"  # object_<k>/: the motion stage's part work (database, masks, model, measured.json)
