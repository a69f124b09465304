"""Read a capture as a stream of upright RGB frames: a video file, an image folder or a RAW folder.

- Videos are decoded with PyAV; the display matrix phones write (portrait = stored landscape + rotation) is honoured,
  so frames come out the way the phone showed them (checked against ffmpeg's autorotate).
- Image folders are decoded by content, not extension (real captures have JPEG bytes in `.png` files);
  EXIF orientation is applied. HEIC / HEIF photos (an iPhone's default) are read with pillow-heif, their own
  rotation applied. The frame index is the file's position in name order.
- RAW folders (DNG, CR2, NEF, ...) go through rawpy with ONE white balance and ONE exposure gain for the whole
  sequence (median of the per-file as-shot balance; a gain from the pooled brightness), so colours do not flicker.

Every failure is an `InputError` that names the file and says what to do.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator

import av
import cv2
import numpy as np
import rawpy
from PIL import Image, ImageOps
from tqdm import tqdm

try:  # HEIC / HEIF photos, the iPhone's default: a dependency, but an install without it still reads the rest
    import pillow_heif
except ImportError:  # pragma: no cover - named in the error a HEIC file then gets
    pillow_heif = None
else:
    pillow_heif.register_heif_opener()

from .dataset import decode_image as decode_file
from .errors import InputError
from .images import at_size

VIDEO_SUFFIXES = {".mp4", ".mov", ".m4v", ".mkv", ".avi", ".webm", ".3gp", ".mts", ".m2ts"}
RAW_SUFFIXES = {".dng", ".cr2", ".cr3", ".crw", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".raf", ".orf", ".rw2",
                ".pef", ".srw", ".3fr", ".erf", ".kdc", ".dcr", ".mrw", ".x3f", ".iiq", ".rwl", ".mef", ".mos"}

# magic bytes -> format; checked against the first 16 bytes of a file
_MAGIC: tuple[tuple[int, bytes, str], ...] = (
    (0, b"\xff\xd8\xff", "jpeg"),
    (0, b"\x89PNG\r\n\x1a\n", "png"),
    (0, b"II*\x00", "tiff"),
    (0, b"MM\x00*", "tiff"),
    (0, b"BM", "bmp"),
    (0, b"GIF8", "gif"),
    (8, b"WEBP", "webp"),
    (4, b"ftyp", "isobmff"),  # mp4 / mov / heic / avif / cr3
    (0, b"\x1a\x45\xdf\xa3", "matroska"),
    (8, b"AVI ", "avi"),
)
IMAGE_FORMATS = {"jpeg", "png", "tiff", "bmp", "webp", "heif"}
HEIF_BRANDS = {b"heic", b"heix", b"hevc", b"hevx", b"heim", b"heis", b"hevm", b"hevs", b"mif1", b"msf1"}
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp", ".heic", ".heif", ".gif"}


def sniff(path: str | Path) -> str | None:
    """The file's format from its first bytes ('jpeg', 'png', ..., 'isobmff'), or None when unknown/empty."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
    except OSError:
        return None
    for offset, magic, fmt in _MAGIC:
        if head[offset:offset + len(magic)] == magic:
            return "heif" if fmt == "isobmff" and head[8:12] in HEIF_BRANDS else fmt
    return None


def fit_long_side(w: int, h: int, long_side: int | None) -> tuple[int, int]:
    """(w, h) scaled so that max(w, h) <= long_side (never upscaled); even-rounding is not needed for PNG."""
    if not long_side or max(w, h) <= long_side:
        return w, h
    s = long_side / max(w, h)
    return max(1, round(w * s)), max(1, round(h * s))


@dataclass
class SourceInfo:
    """What the capture is; recorded in reports/frames.json."""

    kind: str  # "video" | "images" | "raw"
    path: str
    count: int  # number of frames (video: as declared by the container until decoded)
    width: int  # upright size
    height: int
    fps: float | None = None
    rotation: int = 0  # degrees counter-clockwise applied to stored video frames
    names: list[str] = field(default_factory=list)  # file names for folders, in index order
    extra: dict = field(default_factory=dict)


class Source:
    """A capture; `frames()` yields (source index, RGB uint8 upright) in index order."""

    info: SourceInfo

    def frames(self, indices: Iterable[int] | None = None, long_side: int | None = None,
               progress: str | None = None) -> Iterator[tuple[int, np.ndarray]]:
        raise NotImplementedError


def _bar(total: int | None, desc: str | None):
    return tqdm(total=total, desc=desc, unit="frame", disable=desc is None, leave=False)


# ----------------------------------------------------------------------------------------------------------------
# Video
# ----------------------------------------------------------------------------------------------------------------
class VideoSource(Source):
    def __init__(self, path: Path):
        self.path = path
        if path.stat().st_size == 0:
            raise InputError(f"{path} is empty (0 bytes): copy the video from the phone again")
        try:
            with av.open(str(path)) as c:
                if not c.streams.video:
                    raise InputError(f"{path} has no video stream: give a video file, an image folder or a RAW folder")
                s = c.streams.video[0]
                declared = int(s.frames or 0)
                fps = float(s.average_rate or s.guessed_rate or 0) or None
                if not declared and s.duration and fps:
                    declared = int(round(float(s.duration * s.time_base) * fps))
                first = next(c.decode(video=0), None)
        except InputError:
            raise
        except (av.FFmpegError, StopIteration, ValueError, OSError) as exc:
            raise InputError(f"{path} is not a readable video ({exc}); it may be truncated or in an unsupported "
                             "codec: re-export it as H.264/HEVC MP4") from exc
        if first is None:
            raise InputError(f"{path} contains no decodable frames (empty or truncated video): copy it again")
        self.rotation = _frame_rotation(first, s.metadata)
        w, h = first.width, first.height
        if self.rotation % 180:
            w, h = h, w
        self.info = SourceInfo("video", str(path), declared, w, h, fps=fps, rotation=self.rotation)

    def frames(self, indices=None, long_side=None, progress=None):
        wanted = None if indices is None else set(int(i) for i in indices)
        last = max(wanted) if wanted else None
        k = (round(self.rotation / 90) % 4) if self.rotation else 0
        sw, sh = (self.info.height, self.info.width) if k % 2 else (self.info.width, self.info.height)
        tw, th = fit_long_side(sw, sh, long_side)
        i = -1
        bar = _bar(len(wanted) if wanted is not None else (self.info.count or None), progress)
        try:
            with av.open(str(self.path)) as c:
                stream = c.streams.video[0]
                stream.thread_type = "AUTO"
                try:
                    for frame in c.decode(stream):
                        i += 1
                        if wanted is not None and i not in wanted:
                            if last is not None and i > last:
                                break
                            continue
                        rgb = frame.to_ndarray(format="rgb24", width=tw, height=th,
                                               interpolation="AREA" if (tw, th) != (sw, sh) else None)
                        if k:
                            rgb = np.ascontiguousarray(np.rot90(rgb, k))
                        bar.update(1)
                        yield i, rgb
                except av.FFmpegError as exc:
                    raise InputError(f"{self.path}: the video is damaged or truncated after frame {i} ({exc}); "
                                     "copy the file from the phone again") from exc
        finally:
            bar.close()
        n = i + 1
        if wanted is None:
            if n == 0:
                raise InputError(f"{self.path} contains no decodable frames (empty or truncated video)")
            if self.info.count and n < 0.9 * self.info.count:
                raise InputError(f"{self.path} is truncated: the container declares {self.info.count} frames but only "
                                 f"{n} decode; copy the file from the phone again")
            self.info.count = n
        elif last is not None and n <= last:
            raise InputError(f"{self.path}: frame {last} was asked for but the video ends at frame {n - 1}")


def _frame_rotation(frame, metadata) -> int:
    """Counter-clockwise degrees to apply to a decoded frame (display matrix, else the legacy 'rotate' tag)."""
    rot = int(round(getattr(frame, "rotation", 0) or 0))
    if not rot:
        tag = (metadata or {}).get("rotate")
        if tag:
            try:
                rot = -int(float(tag))  # the legacy tag is clockwise
            except ValueError:
                rot = 0
    return ((rot + 180) % 360) - 180 if rot % 90 == 0 else 0


# ----------------------------------------------------------------------------------------------------------------
# Image folders
# ----------------------------------------------------------------------------------------------------------------
def decode_image(path: Path) -> np.ndarray:
    """RGB uint8, EXIF orientation applied; the format is detected from the bytes, whatever the extension says."""
    if sniff(path) == "heif":
        return _decode_heif(path)
    img = decode_file(path, cv2.IMREAD_COLOR)  # IMREAD_COLOR applies the EXIF orientation
    if img is None:
        raise InputError(f"{path} cannot be decoded: the file is truncated or not an image; remove or replace it")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _decode_heif(path: Path) -> np.ndarray:
    """A HEIC / HEIF photo as RGB uint8, upright (pillow-heif applies the file's rotation, EXIF the rest)."""
    if pillow_heif is None:
        raise InputError(f"{path} is a HEIC photo (an iPhone's default) and pillow-heif is not installed: "
                         f"`pip install pillow-heif`, or export the photos as JPEG")
    try:
        with Image.open(path) as im:
            return np.asarray(ImageOps.exif_transpose(im).convert("RGB"))
    except Exception as exc:  # noqa: BLE001 - any decoder failure is this file's problem, named
        raise InputError(f"{path} cannot be decoded as HEIC ({exc}): the file is truncated or damaged; remove or "
                         f"replace it") from None


def _upright_size(path: Path) -> tuple[int, int] | None:
    """(w, h) after EXIF rotation, from the header only; None when the header is unreadable."""
    try:
        with Image.open(path) as im:
            w, h = im.size
            orient = im.getexif().get(274, 1)
    except Exception:  # noqa: BLE001 - any header failure means "not a usable image"
        return None
    return (h, w) if orient in (5, 6, 7, 8) else (w, h)


def _list_folder(folder: Path) -> list[Path]:
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    if not files:
        raise InputError(f"{folder} is empty: give a folder of images or RAW files, or a video file")
    return files


def mixed_sizes_message(folder: Path, sizes: dict[tuple[int, int], list[str]]) -> str:
    """Why a folder of photos of several sizes is refused, and what to do: photos of one camera held both ways
    (portrait and landscape, the same size turned) are told so, not to resize."""
    desc = "; ".join(f"{w}x{h}: {len(n)} files (e.g. {n[0]})" for (w, h), n in sorted(sizes.items()))
    if len(sizes) == 2:
        (a, na), (b, nb) = sorted(sizes.items(), key=lambda kv: -len(kv[1]))
        if a == b[::-1]:
            turned = "portrait" if b[1] > b[0] else "landscape"
            return (f"{folder} mixes {'landscape' if turned == 'portrait' else 'portrait'} and {turned} photos "
                    f"({desc}): the camera was turned for {len(nb)} of them (e.g. {nb[0]}); one capture must be one "
                    f"orientation: leave those out or rotate them to the others' orientation (not resize)")
    return f"{folder} mixes image sizes ({desc}); one capture must have one size: split the folder or resize the odd images"


class ImageFolderSource(Source):
    def __init__(self, folder: Path, files: list[Path]):
        self.folder = folder
        self.files = files
        sizes: dict[tuple[int, int], list[str]] = {}
        for p in files:
            size = _upright_size(p)
            if size is None:
                raise InputError(f"{p} cannot be read as an image (truncated or damaged); remove or replace it")
            sizes.setdefault(size, []).append(p.name)
        if len(sizes) > 1:
            raise InputError(mixed_sizes_message(folder, sizes))
        (w, h), = sizes
        fmts = sorted({sniff(p) or "?" for p in files})
        self.info = SourceInfo("images", str(folder), len(files), w, h, names=[p.name for p in files],
                               extra={"formats": fmts})

    def frames(self, indices=None, long_side=None, progress=None):
        order = range(len(self.files)) if indices is None else sorted(set(int(i) for i in indices))
        size = fit_long_side(self.info.width, self.info.height, long_side)
        bar = _bar(len(order), progress)
        try:
            for i in order:
                img = decode_image(self.files[i])
                if (img.shape[1], img.shape[0]) != (self.info.width, self.info.height):
                    raise InputError(f"{self.files[i]} decodes to {img.shape[1]}x{img.shape[0]}, the others are "
                                     f"{self.info.width}x{self.info.height}; one capture must have one size")
                bar.update(1)
                yield i, at_size(img, size)
        finally:
            bar.close()


# ----------------------------------------------------------------------------------------------------------------
# RAW folders
# ----------------------------------------------------------------------------------------------------------------
def _srgb_encode(lin: np.ndarray) -> np.ndarray:
    lin = np.clip(lin, 0.0, 1.0)
    out = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * np.power(lin, 1 / 2.4) - 0.055)
    return (out * 255.0 + 0.5).astype(np.uint8)


class RawFolderSource(Source):
    """RAW files developed with one white balance and one exposure for the whole sequence."""

    STATS_FILES = 16  # files sampled for the shared exposure
    WHITE = 0.92  # the pooled 99th luminance percentile maps here (linear)

    def __init__(self, folder: Path, files: list[Path]):
        self.folder = folder
        self.files = files
        wbs, sizes = [], {}
        for p in files:
            with self._open(p) as raw:
                s = raw.sizes
                size = (s.height, s.width) if s.flip in (5, 6) else (s.width, s.height)
                sizes.setdefault(size, []).append(p.name)
                wb = np.asarray(raw.camera_whitebalance[:3], dtype=np.float64)
                if np.all(wb[:3] > 0):
                    wbs.append(wb / wb[1])
        if len(sizes) > 1:
            desc = "; ".join(f"{w}x{h}: {len(n)} files" for (w, h), n in sorted(sizes.items()))
            raise InputError(f"{folder} mixes RAW sizes ({desc}); one capture must have one camera and size")
        (w, h), = sizes
        wb = np.median(np.stack(wbs), axis=0) if wbs else np.ones(3)
        self.wb = [float(wb[0]), 1.0, float(wb[2]), 1.0]
        self.gain = self._shared_gain()
        self.info = SourceInfo("raw", str(folder), len(files), w, h, names=[p.name for p in files],
                               extra={"white_balance": self.wb, "exposure_gain": self.gain})

    @staticmethod
    def _open(path: Path):
        try:
            return rawpy.imread(str(path))
        except (rawpy.LibRawFileUnsupportedError, rawpy.LibRawDataError, rawpy.LibRawIOError,
                rawpy.LibRawError) as exc:
            raise InputError(f"{path}: unsupported or damaged RAW file ({type(exc).__name__}: {exc}); "
                             "convert it to DNG/TIFF/JPEG first") from exc

    def _develop_linear(self, path: Path, half: bool) -> np.ndarray:
        with self._open(path) as raw:
            try:
                rgb = raw.postprocess(user_wb=self.wb, no_auto_bright=True, gamma=(1, 1), output_bps=16,
                                      half_size=half, use_camera_wb=False, use_auto_wb=False)
            except rawpy.LibRawError as exc:
                raise InputError(f"{path}: RAW decoding failed ({exc}); convert it to DNG/TIFF/JPEG first") from exc
        return rgb.astype(np.float32) / 65535.0

    def _shared_gain(self) -> float:
        """One exposure gain for the sequence: the pooled 99th percentile of luminance maps to WHITE."""
        pick = np.unique(np.linspace(0, len(self.files) - 1, min(self.STATS_FILES, len(self.files))).round().astype(int))
        p99 = []
        for i in pick:
            lin = self._develop_linear(self.files[i], half=True)
            lum = lin @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
            p99.append(float(np.percentile(lum, 99)))
        ref = float(np.median(p99))
        return float(self.WHITE / ref) if ref > 1e-6 else 1.0

    def frames(self, indices=None, long_side=None, progress=None):
        order = range(len(self.files)) if indices is None else sorted(set(int(i) for i in indices))
        size = fit_long_side(self.info.width, self.info.height, long_side)
        bar = _bar(len(order), progress)
        try:
            half = bool(long_side) and long_side <= max(self.info.width, self.info.height) // 2
            for i in order:
                img = _srgb_encode(self._develop_linear(self.files[i], half=half) * self.gain)
                bar.update(1)
                yield i, at_size(img, size)
        finally:
            bar.close()


# ----------------------------------------------------------------------------------------------------------------
def open_source(path: str | Path) -> Source:
    """A video file, an image folder or a RAW folder; InputError with the reason otherwise."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path} does not exist: give a video file, an image folder or a RAW folder")
    if path.is_file():
        fmt = sniff(path)
        if path.suffix.lower() in VIDEO_SUFFIXES or fmt in ("isobmff", "matroska", "avi"):
            return VideoSource(path)
        if path.stat().st_size == 0:
            raise InputError(f"{path} is empty (0 bytes)")
        raise InputError(f"{path} is a single file that is not a video; put photos or RAW files in a folder "
                         "and pass the folder")
    files = _list_folder(path)
    # a stray note or sidecar file (K.txt, notes.txt, .xmp, .json) and hidden files (.DS_Store) are left out with a
    # warning naming them; a file that claims to be an image by its name but is not one is an error (a damaged photo
    # must not silently shift the frame indices)
    hidden = sorted(p for p in path.iterdir() if p.is_file() and p.name.startswith("."))
    stray = [p for p in files if p.suffix.lower() not in RAW_SUFFIXES | IMAGE_SUFFIXES and sniff(p) not in IMAGE_FORMATS]
    files = [p for p in files if p not in stray]
    if not files:
        raise InputError(f"{path} holds no images ({', '.join(p.name for p in stray[:5])}"
                         f"{', ...' if len(stray) > 5 else ''}): give a folder of images or RAW files, or a video")
    raws = [p for p in files if p.suffix.lower() in RAW_SUFFIXES]
    others = [p for p in files if p.suffix.lower() not in RAW_SUFFIXES]
    if raws and others:
        raise InputError(f"{path} mixes RAW files ({raws[0].name}, ...) and other files ({others[0].name}, ...): "
                         "keep one kind per folder")
    if raws:
        source: Source = RawFolderSource(path, raws)
    else:
        bad = [p.name for p in files if sniff(p) not in IMAGE_FORMATS]
        if bad:
            more = f" and {len(bad) - 5} more" if len(bad) > 5 else ""
            raise InputError(f"{path} holds files that are not images: {', '.join(bad[:5])}{more}; remove them "
                             "(supported: JPEG, PNG, TIFF, BMP, WebP, HEIC by content; RAW by extension)")
        source = ImageFolderSource(path, files)
    if stray or hidden:
        source.info.extra["skipped"] = [p.name for p in stray + hidden]
    return source
