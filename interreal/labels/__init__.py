"""Keyframe state labels: `key_frame_value.yaml` and the object list `mapping.yaml`.

A label is an object's state on one frame, 0 = closed .. 1 = fully open. People measure states in physical
units ("the door is at 45 degrees", "the drawer is out 12 cm"), so values may be given with a unit and a range
(`--degrees 0:90`) and are normalised here. Every edit is validated first and written atomically under a
dataset-wide edit lock, so the CLI and the annotation app (`interreal.annotate`) can edit the same dataset
without losing each other's changes.

Modules: `values` (units and ranges), `objects` (the edit lock, frames, `mapping.yaml`), `edit` (set / unset /
`merge_labels` / list / check), `importing` (`--from FILE`), `cli` (`interreal label`).
"""

from ..conventions import FORBIDDEN_NAME_CHARS
from ..layout import KEYFRAMES_DIR, LOCK_FILE
from .cli import add_arguments, add_unit_arguments, main
from .edit import (check_labels, format_table, list_labels, merge_labels, refuse_new_objects_with_masks, set_label,
                   unset_label)
from .importing import ParsedImport, import_labels, labels_fingerprints, parse_import, read_label_file
from .objects import (add_object, check_object_name, dataset_frames, edit_lock, read_objects,
                      rename_object, require_object, resolve_frame)
from .values import UNIT_ALIASES, Unit, normalise_value, parse_range

__all__ = [
    "FORBIDDEN_NAME_CHARS", "KEYFRAMES_DIR", "LOCK_FILE", "UNIT_ALIASES", "ParsedImport", "Unit", "add_arguments",
    "add_object", "add_unit_arguments", "check_labels", "check_object_name", "dataset_frames", "edit_lock",
    "format_table", "import_labels", "labels_fingerprints", "list_labels", "main", "merge_labels", "normalise_value",
    "parse_import", "parse_range", "read_label_file", "read_objects", "refuse_new_objects_with_masks",
    "rename_object", "require_object", "resolve_frame", "set_label", "unset_label",
]
