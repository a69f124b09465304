"""H.264 MP4 writing through PyAV (OpenCV's VideoWriter cannot write H.264), atomic: a temporary file, then rename."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path
from typing import Iterable

import av
import numpy as np


class VideoWriter:
    """Stream RGB frames (H, W, 3) uint8 into an H.264 (yuv420p) MP4; the file appears only on `close()`.

    Odd sizes are cropped by one pixel (yuv420p needs even sizes)."""

    def __init__(self, path: str | Path, width: int, height: int, fps: float = 30.0, crf: int = 18,
                 preset: str = "veryfast"):
        self._av = av
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = self.path.with_name(f".{self.path.name}.tmp.mp4")
        self.size = (width - width % 2, height - height % 2)
        self.container = av.open(str(self.tmp), mode="w", format="mp4")
        self.stream = self.container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        self.stream.width, self.stream.height = self.size
        self.stream.pix_fmt = "yuv420p"
        # no macroblock tree: with it this x264 build encoded the same frames differently from run to run (any
        # thread count), so a seeded simulated capture was not the same video twice
        self.stream.options = {"crf": str(int(crf)), "preset": preset, "x264-params": "no-mbtree=1"}
        self._pts = 0

    def write(self, rgb: np.ndarray) -> None:
        w, h = self.size
        frame = self._av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb[:h, :w]), format="rgb24")
        frame.pts, self._pts = self._pts, self._pts + 1
        for pkt in self.stream.encode(frame):
            self.container.mux(pkt)

    def close(self) -> None:
        for pkt in self.stream.encode():
            self.container.mux(pkt)
        self.container.close()
        self.tmp.replace(self.path)

    def abort(self) -> None:
        try:
            self.container.close()
        finally:
            self.tmp.unlink(missing_ok=True)

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc is None:
            self.close()
        else:
            self.abort()


def write_video(path: str | Path, frames: Iterable[np.ndarray], fps: float = 15, crf: int = 18) -> Path:
    """Write a whole list of RGB frames as an H.264 MP4."""
    frames = list(frames)
    if not frames:
        raise ValueError(f"no frames to write to {path}")
    h, w = frames[0].shape[:2]
    with VideoWriter(path, w, h, fps=fps, crf=crf) as vw:
        for f in frames:
            vw.write(f)
    return Path(path)
