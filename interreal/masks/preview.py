"""Compact previews of the propagated masks: a contact-sheet PNG and a small overlay MP4 (PyAV)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .. import atomic

PALETTE = np.array([(230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48), (145, 30, 180),
                    (70, 240, 240), (240, 50, 230), (210, 245, 60), (250, 190, 212)], np.uint8)


IGNORE_GREY = np.array((158, 158, 158), np.uint8)  # the ignore class (people, hands), as the annotate app draws it


def overlay(image: np.ndarray, labels: np.ndarray, alpha: float = 0.5, ignore: int | None = None) -> np.ndarray:
    """RGB image with each object tinted and outlined in its palette colour (label `ignore` in grey)."""
    out = image.copy()
    for k in range(1, int(labels.max()) + 1):
        m = labels == k
        if not m.any():
            continue
        colour = IGNORE_GREY if k == ignore else PALETTE[(k - 1) % len(PALETTE)]
        out[m] = (out[m] * (1 - alpha) + colour.astype(np.float32) * alpha).astype(np.uint8)
        edge = cv2.morphologyEx(m.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
        out[edge] = colour
    return out


def thumb(image: np.ndarray, labels: np.ndarray, width: int, caption: str, ignore: int | None = None) -> np.ndarray:
    h = max(8, round(image.shape[0] * width / image.shape[1]))
    small = cv2.resize(image, (width, h), interpolation=cv2.INTER_AREA)
    lab = cv2.resize(labels, (width, h), interpolation=cv2.INTER_NEAREST)
    t = overlay(small, lab, ignore=ignore)
    cv2.putText(t, caption, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(t, caption, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return t


def second_line(tile: np.ndarray, text: str, alert: bool = False) -> None:
    """A second caption line, drawn once the whole sequence is judged (state and confidence); red on alert."""
    colour = (255, 80, 80) if alert else (255, 255, 255)
    cv2.putText(tile, text, (4, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(tile, text, (4, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour, 1, cv2.LINE_AA)


def contact_sheet(path: Path, tiles: list[np.ndarray], cols: int = 6) -> None:
    if not tiles:
        return
    h, w = tiles[0].shape[:2]
    rows = (len(tiles) + cols - 1) // cols
    sheet = np.full((rows * h, min(cols, len(tiles)) * w, 3), 255, np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, cols)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = t[:h, :w]
    atomic.write_image(path, sheet)
