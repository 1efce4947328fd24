"""Reading and writing videos: PyAV for video files, OpenCV for folders of images.

Every frame is an (H, W, 3) uint8 RGB array and a video is a (T, H, W, 3) stack of them.
Reading is lazy: `iter_frames` decodes one frame at a time and `video_info` looks at the
header and the first frame only. Files are turned upright by their display matrix (phones
store portrait videos as rotated landscape). Writing makes H.264 mp4 through PyAV's bundled
FFmpeg, because OpenCV's pip wheel cannot encode H.264.

Problems with the input are reported as one-line errors that name the file:
`FileNotFoundError` when it is missing and `ValueError` when it is unsupported, unreadable,
has no frames, or would exceed a limit of `taptr.io.limits` (``video_bytes`` for a whole video,
``image_pixels`` for one frame; both checked from headers before decoding). A file that
decodes to fewer or more frames than its container states gives a warning with both
numbers.
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from fractions import Fraction
from itertools import chain, islice
from pathlib import Path

import av
import cv2
import numpy as np

from taptr.io import limits
from taptr.io.atomic import atomic_path
from taptr.io.image_guard import image_size

VIDEO_SUFFIXES = (".mp4", ".webm", ".avi", ".gif", ".mov", ".mkv")
"""File suffixes read through PyAV."""

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
"""Suffixes of the frames of an image folder."""

H264_CRF = 18
"""x264 constant rate factor: visually lossless for overlays without huge files."""

H264_PRESET = "veryfast"
"""x264 speed preset: 2.5x faster than the default ``medium`` on a 1080p overlay, with files
of about the same size at `H264_CRF` (encoding was most of ``taptr track``'s time at 1080p)."""

H264_PARAMS = "mbtree=0"
"""x264 options: no macroblock-tree rate control, so that a video encodes to the same bytes
every time. With it, x264 read memory it had not written: the same frames gave different
files once the process had freed other data (``taptr edit`` differed by up to 56/255 per
pixel between runs). Without it, files of 1296 × 720 frames were 8-12% larger, encoding 25%
faster, PSNR the same (40.1 dB)."""


@dataclass(frozen=True)
class VideoInfo:
    """What is known about a video before decoding it.

    Attributes:
        num_frames: number of frames T as the container states it; None when it does not
            say (webm files, for example) and only decoding would tell.
        fps: frames per second; None when unknown (image folders).
        height: frame height H in pixels, after turning the video upright.
        width: frame width W in pixels, after turning the video upright.
    """

    num_frames: int | None
    fps: float | None
    height: int
    width: int


def video_info(path: str | os.PathLike[str]) -> VideoInfo:
    """Reads the frame count, frame rate and frame size of a video file or image folder.

    Only the header and the first frame are decoded.

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: the suffix is unsupported, or the file is unreadable or has no frames.
    """
    source = _check_source(path)
    if source.is_dir():
        images = _image_files(source)
        height, width = _read_image(images[0]).shape[:2]
        return VideoInfo(num_frames=len(images), fps=None, height=height, width=width)
    with _open_video(source) as container:
        stream = container.streams.video[0]
        first = _first(source, _decode(source, container, stride=1))
        height, width = first.shape[:2]
        rate = stream.average_rate or stream.guessed_rate
        return VideoInfo(
            num_frames=stream.frames or None,
            fps=float(rate) if rate else None,
            height=height,
            width=width,
        )


def iter_frames(
    path: str | os.PathLike[str], *, stride: int = 1, max_frames: int | None = None
) -> Iterator[np.ndarray]:
    """Iterates over the frames of a video file or an image folder, decoding one at a time.

    The path, suffix and arguments are checked at the call; decoding errors surface while
    iterating.

    Args:
        path: a video file (mp4, webm, avi, gif, mov, mkv) or a folder of png/jpg images,
            read in natural order (``frame2.png`` before ``frame10.png``).
        stride: yield every ``stride``-th frame, starting with the first.
        max_frames: stop after yielding this many frames (counted after the stride).

    Returns:
        An iterator of (H, W, 3) uint8 RGB frames.

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: the suffix is unsupported, a file is unreadable, or there are no frames.
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    source = _check_source(path)
    if source.is_dir():
        return _read_images(_image_files(source)[::stride][:max_frames])
    return _iter_video(source, stride, max_frames)


def read_video(
    path: str | os.PathLike[str], *, stride: int = 1, max_frames: int | None = None
) -> np.ndarray:
    """Reads a whole video file or image folder into memory.

    Args:
        path: a video file or a folder of images, as for `iter_frames`.
        stride: keep every ``stride``-th frame, starting with the first.
        max_frames: keep at most this many frames (counted after the stride).

    Returns:
        (T, H, W, 3) uint8 RGB frames.

    Raises:
        ValueError: as `iter_frames`, and when the decoded frames would exceed the
            ``video_bytes`` limit of `taptr.io.limits` (checked from the header before decoding
            when the container states its frame count, and while decoding in any case).
    """
    frames = iter_frames(path, stride=stride, max_frames=max_frames)
    source = Path(path)
    declared, height, width = _declared_size(source)
    if declared is not None:
        count = (
            -(-declared // stride)
            if max_frames is None
            else min(-(-declared // stride), max_frames)
        )
        what = f"{source}: {count} frames of {width}x{height}"
        limits.check("video_bytes", count * height * width * 3, what)
    decoded: list[np.ndarray] = []
    total = 0
    for frame in frames:
        # the header can understate the count: keep counting what is really decoded
        total += frame.nbytes
        if total > limits.limit("video_bytes"):
            what = f"{source}: more than {len(decoded)} frames of {frame.shape[1]}x{frame.shape[0]}"
            limits.check("video_bytes", total, what)
        decoded.append(frame)
    return np.stack(decoded)


def write_video(path: str | os.PathLike[str], frames: Iterable[np.ndarray], fps: float) -> Path:
    """Encodes frames as an H.264 (yuv420p) mp4 file, atomically.

    The file appears at ``path`` only when every frame has been written; frames may come
    from a generator, so a long video never has to be in memory. yuv420p needs an even
    width and height: an odd size is padded by repeating the last row or column, so the
    file can be one pixel taller or wider than the frames.

    Args:
        path: output file; its suffix must be ``.mp4``. Missing folders are created.
        frames: (T, H, W, 3) uint8 RGB array, or an iterable of (H, W, 3) uint8 RGB frames
            that all have the same size.
        fps: frames per second, > 0.

    Returns:
        The path written.

    Raises:
        ValueError: bad suffix, fps, frame shape or dtype, or no frames.
    """
    target = Path(path)
    if target.suffix.lower() != ".mp4":
        raise ValueError(f"can only write .mp4 videos, got {target.name}")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps}")
    frame_iter = iter(frames)
    first = next(frame_iter, None)
    if first is None:
        raise ValueError(f"no frames to write to {target}")
    height, width = _check_frame(first).shape[:2]
    with (
        atomic_path(target) as tmp,
        av.open(str(tmp), "w", format="mp4", options={"movflags": "+faststart"}) as container,
    ):
        stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        stream.width, stream.height = width + width % 2, height + height % 2
        stream.pix_fmt = "yuv420p"
        stream.options = {
            "crf": str(H264_CRF),
            "preset": H264_PRESET,
            "x264-params": H264_PARAMS,
        }
        for frame in chain([first], frame_iter):
            if _check_frame(frame).shape[:2] != (height, width):
                raise ValueError(
                    f"all frames must be {width}x{height}, got {frame.shape[1]}x{frame.shape[0]}"
                )
            padded = _pad_to_even(frame)
            container.mux(stream.encode(av.VideoFrame.from_ndarray(padded, format="rgb24")))
        container.mux(stream.encode())  # flush the encoder's delayed frames
    return target


def write_image(path: str | os.PathLike[str], image: np.ndarray) -> Path:
    """Writes one (H, W, 3) uint8 RGB image (png or jpg, by suffix), atomically."""
    target = Path(path)
    if target.suffix.lower() not in IMAGE_SUFFIXES:
        raise ValueError(f"can only write {', '.join(IMAGE_SUFFIXES)} images, got {target.name}")
    bgr = cv2.cvtColor(_check_frame(image), cv2.COLOR_RGB2BGR)
    with atomic_path(target) as tmp:
        if not cv2.imwrite(str(tmp), bgr):
            raise ValueError(f"cannot write image {target}")
    return target


def natural_sort_key(name: str) -> list[int | str]:
    """Sort key that orders embedded numbers by value: ``f2`` before ``f10``."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def _declared_size(source: Path) -> tuple[int | None, int, int]:
    """(frames, height, width) from the headers only; frames is None when not stated.

    Raises:
        ValueError: a frame declares more pixels than the ``image_pixels`` limit.
    """
    if source.is_dir():
        images = _image_files(source)
        size = image_size(images[0], str(images[0]))
        return (len(images), *size) if size else (None, 0, 0)
    with _open_video(source) as container:
        stream = container.streams.video[0]
        context = stream.codec_context  # None when FFmpeg has no decoder for the stream
        height, width = (context.height, context.width) if context else (0, 0)
        limits.check("image_pixels", height * width, f"{source}: {width}x{height} frames")
        return stream.frames or None, height, width


def _iter_video(source: Path, stride: int, max_frames: int | None) -> Iterator[np.ndarray]:
    with _open_video(source) as container:
        declared = container.streams.video[0].frames
        frames = _decode(source, container, stride)
        yield _first(source, frames)
        count = 1
        for frame in islice(frames, None if max_frames is None else max_frames - 1):
            count += 1
            yield frame
    expected = -(-declared // stride)
    if declared and count != expected and (max_frames is None or count < max_frames):
        # a truncated file decodes fewer frames than its header states: never silently
        warnings.warn(
            f"{source}: decoded {count} frames where the container declares {expected}"
            + (f" (every {stride}th of {declared})" if stride > 1 else "")
            + "; the file may be truncated or damaged",
            stacklevel=2,
        )


def _check_source(path: str | os.PathLike[str]) -> Path:
    source = Path(path)
    if not source.exists():
        raise FileNotFoundError(f"video not found: {source}")
    if source.is_file() and source.suffix.lower() not in VIDEO_SUFFIXES:
        supported = ", ".join(VIDEO_SUFFIXES)
        raise ValueError(
            f"unsupported video type {source.suffix or '(none)'!r} for {source} "
            f"(supported: {supported}, or a folder of png/jpg images)"
        )
    return source


def _image_files(folder: Path) -> list[Path]:
    images = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()]
    if not images:
        raise ValueError(f"no png/jpg images in folder {folder}")
    return sorted(images, key=lambda p: natural_sort_key(p.name))


def _read_image(path: Path) -> np.ndarray:
    image_size(path, str(path))  # refuses decompression bombs before OpenCV decodes them
    # IMREAD_COLOR turns grey and RGBA images into 3 channels, so every frame is (H, W, 3).
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError(f"cannot read image {path}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def _read_images(images: list[Path]) -> Iterator[np.ndarray]:
    size = None
    for image_path in images:
        image = _read_image(image_path)
        size = size or image.shape
        if image.shape != size:
            raise ValueError(
                f"image {image_path} is {image.shape[1]}x{image.shape[0]}, "
                f"the first frame is {size[1]}x{size[0]}"
            )
        yield image


def _open_video(path: Path) -> av.container.InputContainer:
    try:
        container = av.open(str(path))
    except av.error.FFmpegError as error:
        raise ValueError(f"cannot read video {path}: {_reason(error)}") from error
    if not container.streams.video:
        container.close()
        raise ValueError(f"no video stream in {path}")
    return container


def _decode(
    path: Path, container: av.container.InputContainer, stride: int
) -> Iterator[np.ndarray]:
    stream = container.streams.video[0]
    stream.thread_type = "AUTO"  # frame threading: decoding is the slow part of reading
    try:
        # Skipped frames must still be decoded (later frames depend on them), but are never
        # converted to RGB.
        for frame in islice(container.decode(stream), 0, None, stride):
            yield rgb(frame)
    except av.error.FFmpegError as error:
        raise ValueError(f"cannot decode video {path}: {_reason(error)}") from error


def rgb(frame: av.VideoFrame) -> np.ndarray:
    """A decoded frame as (H, W, 3) uint8 RGB, turned upright."""
    # The display matrix gives the counter-clockwise turn that shows the frame upright.
    upright = np.rot90(frame.to_ndarray(format="rgb24"), k=round(frame.rotation / 90))
    return np.ascontiguousarray(upright)


def _reason(error: av.error.FFmpegError) -> str:
    """FFmpeg's message without the errno and the internal function name."""
    return (error.strerror or str(error)).lower()


def _first(path: Path, frames: Iterator[np.ndarray]) -> np.ndarray:
    first = next(frames, None)
    if first is None:
        raise ValueError(f"no frames in video {path}")
    return first


def _check_frame(frame: np.ndarray) -> np.ndarray:
    if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
        raise ValueError(f"frames must be (H, W, 3) uint8 RGB, got {frame.shape} {frame.dtype}")
    return frame


def _pad_to_even(frame: np.ndarray) -> np.ndarray:
    height, width = frame.shape[:2]
    if height % 2 == 0 and width % 2 == 0:
        return np.ascontiguousarray(frame)
    return cv2.copyMakeBorder(frame, 0, height % 2, 0, width % 2, cv2.BORDER_REPLICATE)
