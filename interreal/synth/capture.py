"""Write a simulated capture folder (video + truth + sparse annotations) and read it back.

Layout (docs/interfaces.md, docs/synth.md): OUT/video.mp4, OUT/gt/..., OUT/annotations/....
Everything is written into a staging folder inside OUT and moved into place at the end, so a crashed run never
leaves a capture that looks complete; `gt/meta.json` is the marker that OUT holds a finished capture.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Iterator

import av
import cv2
import numpy as np
import yaml
from tqdm import tqdm

from .. import __version__, atomic
from ..conventions import fid_of_index, frame_name
from ..dataset import Intrinsics
from ..errors import DatasetError, InputError
from ..transients import IGNORE
from ..video import VideoWriter
from .config import SynthConfig
from .scene import RenderResult, Scene, build_scene

DEPTH_SCALE = 4000.0  # gt depth PNG: uint16 = metres * 4000 (0 = nothing hit; max 16.38 m)
VIDEO = "video.mp4"
GT = "gt"
ANNOTATIONS = "annotations"


def keyframe_indices(frames: int, every: int) -> list[int]:
    """Annotated keyframes: every `every`-th frame plus the first and the last."""
    return sorted(set(range(0, frames, every)) | {0, frames - 1})


def extra_keyframes(visible_px: np.ndarray, keyframes: list[int]) -> list[int]:
    """Frames to annotate as well, so every part is drawn on some keyframe (as a person annotating would): for each
    part visible on no regular keyframe, the frame where it shows most. visible_px (frames, parts) pixel counts."""
    extra = set()
    for k in range(visible_px.shape[1]):
        if visible_px[keyframes, k].sum() == 0 and visible_px[:, k].max() > 0:
            extra.add(int(np.argmax(visible_px[:, k])))
    return sorted(extra - set(keyframes))


def label_indices(frames: int, fraction: float, keyframes: list[int]) -> list[int]:
    """Frames with annotated states: `fraction` of all frames, evenly spread, plus the keyframes."""
    n = int(round(fraction * frames))
    spread = np.round(np.linspace(0, frames - 1, n)).astype(int).tolist() if n > 0 else []
    return sorted(set(spread) | set(keyframes))


def annotation_index(instance: np.ndarray, lut: np.ndarray | None = None, paint_occluders: bool = False
                     ) -> np.ndarray:
    """Keyframe mask a person would draw: the truth with the occluding person and arm as background, or as the
    ignore class when `paint_occluders`; `lut` (256,) renumbers the parts when some never appear (a person names
    only what the video shows)."""
    occluded = instance == 255
    out = instance.copy()
    out[occluded] = 0
    out = out if lut is None else lut[out]
    if paint_occluders:
        out[occluded] = IGNORE
    return out


def _encode_png(img: np.ndarray, level: int = 1) -> bytes:
    ok, enc = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, level,
                                          cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_FILTERED])
    if not ok:
        raise OSError("PNG encoding failed")
    return enc.tobytes()


def depth_to_png(depth: np.ndarray) -> np.ndarray:
    d = np.where(np.isfinite(depth), depth, 0.0) * DEPTH_SCALE
    return np.clip(np.round(d), 0, 65535).astype(np.uint16)


def _render_one(scene: Scene, i: int) -> tuple[int, RenderResult, bytes, bytes, float]:
    t0 = time.perf_counter()
    r = scene.render_frame(i)
    depth_png = _encode_png(depth_to_png(r.depth))
    inst_png = _encode_png(r.instance)
    return i, r, depth_png, inst_png, time.perf_counter() - t0


def write_capture(cfg: SynthConfig, out_dir: str | Path, progress: bool = True,
                  log: Callable[[str], None] | None = None) -> Path:
    """Simulate the capture for `cfg` into `out_dir` (see docs/synth.md); returns out_dir.

    An existing capture in out_dir is replaced; any other existing video.mp4 / gt / annotations is an error.
    """
    cfg.check()
    out = Path(out_dir)
    _check_target(out)
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    scene = build_scene(cfg)
    timings["build_s"] = time.perf_counter() - t0
    n = cfg.frames
    stage = out / f".synth-partial-{os.getpid()}"
    if stage.exists():
        shutil.rmtree(stage)
    gt = stage / GT
    (gt / "depth").mkdir(parents=True)
    (gt / "instance").mkdir(parents=True)
    ann = stage / ANNOTATIONS
    (ann / "keyframes").mkdir(parents=True)

    keyframes = keyframe_indices(n, cfg.keyframe_every)
    key_set = set(keyframes)
    poses = scene.camera_path()
    states = scene.states()
    names = scene.object_names
    scene.caster()  # the per-pixel rays, once, before the render threads start
    visible_px = np.zeros((n, len(names)), np.int64)
    try:
        video = VideoWriter(stage / VIDEO, cfg.width, cfg.height, cfg.fps, cfg.crf)
        render_s = encode_s = write_s = 0.0
        t_loop = time.perf_counter()
        with ThreadPoolExecutor(max_workers=cfg.threads) as pool:
            pending: deque = deque()
            next_i = 0
            bar = tqdm(total=n, desc="synth", unit="frame", disable=not progress, leave=False)
            while next_i < n or pending:
                while next_i < n and len(pending) < 2 * cfg.threads:
                    pending.append(pool.submit(_render_one, scene, next_i))
                    next_i += 1
                i, r, depth_png, inst_png, dt = pending.popleft().result()
                render_s += dt
                t1 = time.perf_counter()
                video.write(r.rgb)
                t2 = time.perf_counter()
                fid = fid_of_index(i)
                (gt / "depth" / f"{fid}.png").write_bytes(depth_png)
                (gt / "instance" / f"{fid}.png").write_bytes(inst_png)
                visible_px[i] = np.bincount(r.instance.ravel(), minlength=256)[1:len(names) + 1]
                if i in key_set:
                    key = annotation_index(r.instance, paint_occluders=cfg.paint_occluders)
                    (ann / "keyframes" / f"{fid}.png").write_bytes(_encode_png(key, 3))
                encode_s += t2 - t1
                write_s += time.perf_counter() - t2
                bar.update(1)
            bar.close()
        t1 = time.perf_counter()
        video.close()
        encode_s += time.perf_counter() - t1
        timings["frames_wall_s"] = time.perf_counter() - t_loop
        timings["render_cpu_s"] = render_s  # summed over threads (includes gt PNG encoding)
        timings["video_encode_s"] = encode_s
        timings["gt_write_s"] = write_s

        # the simulated person annotates what the video shows: every part on some keyframe (extra keyframes where
        # the regular ones miss a part), and parts that never appear are not named at all
        shown = [k for k in range(len(names)) if visible_px[:, k].max() > 0]
        lut = None
        if len(shown) < len(names):
            lut = np.zeros(256, np.uint8)
            lut[[k + 1 for k in shown]] = np.arange(1, len(shown) + 1)
        extra = extra_keyframes(visible_px, keyframes)
        for i in extra if lut is None else sorted(set(keyframes) | set(extra)):
            fid = fid_of_index(i)
            inst = cv2.imread(str(gt / "instance" / f"{fid}.png"), cv2.IMREAD_UNCHANGED)
            (ann / "keyframes" / f"{fid}.png").write_bytes(_encode_png(annotation_index(inst, lut, cfg.paint_occluders), 3))
        keyframes = sorted(set(keyframes) | set(extra))
        intr = scene.intrinsics
        mapping = {i: name for i, name in enumerate(names)}
        atomic.write_json(gt / "cameras.json", {
            "intrinsics": intr.to_json(), "fps": cfg.fps, "pixel_centre": 0.5,
            "frames": [{"index": i, "transform_matrix": poses[i].tolist()} for i in range(n)],
        })
        atomic.write_json(gt / "states.json", {"objects": names, "values": states.tolist()})
        atomic.write_yaml(gt / "mapping.yaml", mapping)
        for folder in (ann, ann / "keyframes"):
            atomic.write_yaml(folder / "mapping.yaml", {j: names[k] for j, k in enumerate(shown)})
        atomic.write_yaml(gt / "prompts.yaml", scene.descriptions)
        atomic.write_yaml(ann / "prompts.yaml", {names[k]: scene.descriptions[names[k]] for k in shown})
        labels = {frame_name(i): {names[k]: float(states[i, k]) for k in shown}
                  for i in label_indices(n, cfg.label_fraction, keyframes)}
        atomic.write_yaml(ann / "states.yaml", labels)
        timings["total_s"] = time.perf_counter() - t_start
        timings["fps"] = n / timings["total_s"]
        meta = {
            "generator": f"interreal {__version__} synth", "config": cfg.to_dict(), "frames": n,
            "size": [cfg.width, cfg.height], "objects": names, "annotated_objects": [names[k] for k in shown],
            "descriptions": scene.descriptions,
            "keyframes": keyframes, "label_frames": list(labels),
            "depth_scale": DEPTH_SCALE, "timings": {k: round(v, 4) for k, v in timings.items()},
            "visible_fraction": _visible_fraction(stage, n, len(names)),
        }
        atomic.write_json(gt / "meta.json", meta)
        _move_into_place(stage, out)
    finally:
        if stage.exists():
            shutil.rmtree(stage, ignore_errors=True)
    if log:
        log(_summary(out, meta))
    return out


def _visible_fraction(stage: Path, n: int, m: int) -> list[float]:
    """Mean image fraction covered by each object (read back from a few gt masks): are the parts big enough?"""
    idx = sorted(set(np.linspace(0, n - 1, min(n, 10)).round().astype(int)))
    acc = np.zeros(m)
    for i in idx:
        inst = cv2.imread(str(stage / GT / "instance" / f"{fid_of_index(i)}.png"), cv2.IMREAD_UNCHANGED)
        acc += [(inst == k + 1).mean() for k in range(m)]
    return [round(float(v), 4) for v in acc / len(idx)]


def _check_target(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise InputError(f"{out} exists and is not a folder: choose another output folder")
    if not out.exists():
        return
    is_capture = (out / GT / "meta.json").exists()
    clash = [name for name in (VIDEO, GT, ANNOTATIONS) if (out / name).exists()]
    if clash and not is_capture:
        raise InputError(f"{out} already holds {clash} but is not a synth capture: choose an empty folder")


def _move_into_place(stage: Path, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name in (GT, ANNOTATIONS, VIDEO):  # gt (with its meta.json) is replaced first: a mixed state never has meta
        target = out / name
        if target.is_dir():
            shutil.rmtree(target)
        elif target.exists():
            target.unlink()
    for name in (VIDEO, ANNOTATIONS, GT):  # ... and it comes back last
        os.replace(stage / name, out / name)


def _summary(out: Path, meta: dict[str, Any]) -> str:
    t = meta["timings"]
    cfg = meta["config"]
    lines = [
        f"wrote {out}/",
        f"  {VIDEO:<24} {meta['frames']} frames {cfg['width']}x{cfg['height']} @ {cfg['fps']:g} fps, H.264 crf {cfg['crf']}",
        f"  {GT + '/':<24} cameras.json, states.json, depth/ + instance/ ({meta['frames']} each), mapping, prompts, meta",
        f"  {ANNOTATIONS + '/':<24} keyframes/ ({len(meta['keyframes'])} masks), states.yaml ({len(meta['label_frames'])} frames), prompts.yaml",
        "  objects: " + ", ".join(f"{name} ({100 * v:.1f} % of image)" for name, v in
                                  zip(meta["objects"], meta["visible_fraction"])),
        f"  time: {t['total_s']:.1f} s total = {t['fps']:.1f} frames/s (build {t['build_s']:.1f} s, frames {t['frames_wall_s']:.1f} s; "
        f"render cpu {t['render_cpu_s']:.1f} s, video encode {t['video_encode_s']:.1f} s, gt write {t['gt_write_s']:.1f} s)",
    ]
    return "\n".join(lines)


class Capture:
    """A finished capture folder, read back: poses, states, truth maps, and the Scene for on-demand renders."""

    def __init__(self, root: Path, meta: dict, cameras: dict, states: dict):
        self.root = root
        self.meta = meta
        self.config = SynthConfig.from_dict(meta["config"])
        self.intrinsics = Intrinsics.from_json(cameras["intrinsics"])
        self.fps = float(cameras.get("fps", 30.0))
        self.poses = np.array([f["transform_matrix"] for f in cameras["frames"]], dtype=np.float64)
        self.names: list[str] = list(states["objects"])
        self.states = np.array(states["values"], dtype=np.float64).reshape(len(self.poses), len(self.names))
        self.descriptions: dict[str, str] = dict(meta.get("descriptions", {}))
        self.keyframes: list[int] = list(meta.get("keyframes", []))
        self._scene: Scene | None = None

    @classmethod
    def open(cls, root: str | Path) -> "Capture":
        root = Path(root)
        try:
            meta = json.loads((root / GT / "meta.json").read_text())
            cameras = json.loads((root / GT / "cameras.json").read_text())
            states = json.loads((root / GT / "states.json").read_text())
        except FileNotFoundError as exc:
            raise DatasetError(f"{root} is not a finished synth capture ({exc.filename} missing): "
                               f"run `interreal synth {root}`") from exc
        except ValueError as exc:
            raise DatasetError(f"{root}: broken capture metadata ({exc}); re-run `interreal synth`") from exc
        return cls(root, meta, cameras, states)

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def video_path(self) -> Path:
        return self.root / VIDEO

    def depth(self, i: int) -> np.ndarray:
        """(H, W) float32 metric z-depth of frame i (0 where nothing was hit)."""
        raw = cv2.imread(str(self.root / GT / "depth" / f"{fid_of_index(i)}.png"), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise DatasetError(f"{self.root}: missing gt depth for frame {i}")
        return raw.astype(np.float32) / float(self.meta.get("depth_scale", DEPTH_SCALE))

    def instance(self, i: int) -> np.ndarray:
        """(H, W) uint8: 0 static, k object k-1, 255 occluder."""
        raw = cv2.imread(str(self.root / GT / "instance" / f"{fid_of_index(i)}.png"), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise DatasetError(f"{self.root}: missing gt instance mask for frame {i}")
        return raw

    def labels(self) -> dict[str, dict[str, float]]:
        with open(self.root / ANNOTATIONS / "states.yaml", encoding="utf-8") as fh:
            return yaml.safe_load(fh) or {}

    def scene(self) -> Scene:
        """The Scene (rebuilt from the stored config) for renders at any camera and states."""
        if self._scene is None:
            self._scene = build_scene(self.config)
        return self._scene

    def frames(self) -> Iterator[tuple[int, np.ndarray]]:
        """(index, RGB uint8) for every video frame, decoded with PyAV."""
        with av.open(str(self.video_path)) as container:
            for i, frame in enumerate(container.decode(video=0)):
                yield i, frame.to_ndarray(format="rgb24")
