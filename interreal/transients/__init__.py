"""Transients: pixels that are no object and not static (people, hands, arms), kept out of SfM, motions and
training's losses.

`layer`: the `DS/transients/` files (written, read, validated); `hands`: the hand model that ships in mediapipe's
wheel (an optional extra); `auto`: the layer proposed from it without painting (`--transients auto`).
"""

from ..layout import TRANSIENTS_DIR
from .layer import (IGNORE, IGNORE_LABELS, WHOLE_FRAME, clear_transients, content_problem, excluded, has_transients,
                    is_ignore_label, problems, read_transient, split_labels, track_labels, transient_file, whole_frame,
                    write_transient)

__all__ = ["TRANSIENTS_DIR", "IGNORE", "IGNORE_LABELS", "WHOLE_FRAME", "clear_transients", "content_problem",
           "excluded", "has_transients", "is_ignore_label", "problems", "read_transient", "split_labels",
           "track_labels", "transient_file", "whole_frame", "write_transient"]
