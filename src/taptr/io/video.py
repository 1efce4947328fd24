"""Reading and writing videos: PyAV for video files, OpenCV for folders of images.

Every frame is an (H, W, 3) uint8 RGB array and a video is a (T, H, W, 3) stack of them.
Reading is lazy: `iter_frames` decodes one frame at a time and `video_info` looks at the
header and the first frame only. Files are turned upright by their display matrix (phones
store portrait videos as rotated landscape). Writing makes H.264 mp4 through PyAV's bundled
FFmpeg, because OpenCV's pip wheel cannot encode H.264.

Problems with the input are reported as one-line errors that name the file:
`FileNotFoundError` when it is missing and `ValueError` when it is not a regular file (a FIFO,
a device: refused before opening, `taptr.io.file_kind`), unsupported, unreadable, has no
frames, changes its frame size mid-stream, or would exceed a limit of `taptr.io.limits`.

Every path (`video_info`, `iter_frames`, `read_video`, `taptr.io.reverse_frames`) opens
files the same guarded way: the frame size the header states is checked against
``image_pixels`` before anything is decoded (a header that states no size is refused, not
decoded by content), FFmpeg's decoder is told the same bound (``max_pixels``) so that no
later frame can be larger, and the decoded bytes are counted against ``video_bytes``
(checked from the header when it states a frame count). Streamed reading (`iter_frames`)
holds one frame at a time, so ``video_bytes`` bounds it only when its variable is set.
Frames of image folders are read by `taptr.io.image_guard` (PNG and JPEG, header first).
A file that decodes to fewer or more frames than its container states gives a warning
with both numbers.
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from fractions import Fraction
from itertools import chain, islice
from pathlib import Path

import av
import cv2
import numpy as np

from taptr.io import limits
from taptr.io.atomic import atomic_path
from taptr.io.file_kind import is_regular_file, require_file, require_file_or_folder
from taptr.io.image_guard import image_size, read_image

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
        height, width = image_size(images[0], str(images[0]))
        return VideoInfo(num_frames=len(images), fps=None, height=height, width=width)
    with open_video(source) as container:
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
    _check_counts(stride, max_frames)
    source = _check_source(path)
    bounded = limits.is_set("video_bytes")  # streamed reading holds one frame at a time
    if bounded:
        _bounded(source, stride, max_frames)
    if source.is_dir():
        frames = _read_images(_image_files(source)[::stride][:max_frames])
    else:
        frames = _iter_video(source, stride, max_frames)
    return _counted(source, frames) if bounded else frames


def _check_counts(stride: int, max_frames: int | None) -> None:
    for name, value in (("stride", stride), ("max_frames", max_frames)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int)):
            raise ValueError(f"{name} must be a whole number, got {value!r:.40}")
        if value is not None and not 1 <= value <= MAX_COUNT:
            raise ValueError(f"{name} must lie in [1, {MAX_COUNT:,}], got {value}")


def _bounded(source: Path, stride: int, max_frames: int | None) -> int:
    """Checks the decoded bytes the headers declare against ``video_bytes``; returns them."""
    declared, height, width = _declared_size(source)
    if declared is None:
        return 0
    count = -(-declared // stride)
    count = count if max_frames is None else min(count, max_frames)
    what = f"{source}: {count} frames of {width}x{height}"
    limits.check("video_bytes", count * height * width * 3, what)
    return count * height * width * 3


def _counted(source: Path, frames: Iterator[np.ndarray]) -> Iterator[np.ndarray]:
    """``frames``, refusing to go on once their bytes exceed ``video_bytes``.

    The header can understate the count: what is really decoded is counted.
    """
    total = 0
    for count, frame in enumerate(frames):
        total += frame.nbytes
        if total > limits.limit("video_bytes"):
            what = f"{source}: more than {count} frames of {frame.shape[1]}x{frame.shape[0]}"
            limits.check("video_bytes", total, what)
        yield frame


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
    _check_counts(stride, max_frames)
    source = _check_source(path)
    _bounded(source, stride, max_frames)
    if source.is_dir():
        frames = _read_images(_image_files(source)[::stride][:max_frames])
    else:
        frames = _iter_video(source, stride, max_frames)
    decoded = list(_counted(source, frames))
    return np.stack(decoded)  # every frame was checked against the first one's size


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
        return (len(images), *image_size(images[0], str(images[0])))
    with open_video(source) as container:
        stream = container.streams.video[0]
        return stream.frames or None, stream.codec_context.height, stream.codec_context.width


def _iter_video(source: Path, stride: int, max_frames: int | None) -> Iterator[np.ndarray]:
    with open_video(source) as container:
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
            TruncatedVideoWarning,
            stacklevel=2,
        )


class TruncatedVideoWarning(UserWarning):
    """A video decoded to another number of frames than its container states."""


MAX_COUNT = 2**40
"""Largest ``stride`` or ``max_frames`` accepted: far beyond any video, within every index."""


def _check_source(path: str | os.PathLike[str]) -> Path:
    try:
        source = require_file_or_folder(path, "video")
    except FileNotFoundError:
        raise FileNotFoundError(f"video not found: {path}") from None
    if source.is_file() and source.suffix.lower() not in VIDEO_SUFFIXES:
        supported = ", ".join(VIDEO_SUFFIXES)
        raise ValueError(
            f"unsupported video type {source.suffix or '(none)'!r} for {source} "
            f"(supported: {supported}, or a folder of png/jpg images)"
        )
    return source


def _image_files(folder: Path) -> list[Path]:
    """The frames of an image folder in natural order; other entries are ignored.

    Raises:
        ValueError: no frame, or a frame name that is a FIFO, device or socket (it would
            block or never end; a folder named like a frame is refused too).
    """
    images = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES]
    for image in images:
        if not is_regular_file(image):
            require_file_or_folder(image, "frame")  # names FIFOs, devices, sockets
            raise ValueError(f"frame {image} is a folder, not an image file")
    if not images:
        raise ValueError(f"no png/jpg images in folder {folder}")
    return sorted(images, key=lambda p: natural_sort_key(p.name))


def _read_images(images: list[Path]) -> Iterator[np.ndarray]:
    size = None
    for image_path in images:
        # header first, then decoded by the library that read it (taptr.io.image_guard)
        image = read_image(image_path, str(image_path), size=size)
        size = size or image.shape[:2]
        yield image


def open_video(path: str | os.PathLike[str]) -> av.container.InputContainer:
    """Opens a video file and checks its first video stream's header before any decoding.

    The guarded way to open a video for any reader that decodes it with PyAV: the path
    must be a regular file (a FIFO would block), the stated frame size must be known and
    within ``image_pixels``, and the decoder is then told that bound (FFmpeg's
    ``max_pixels``), so no frame decoded later can exceed it.

    Raises:
        FileNotFoundError: nothing at ``path``.
        ValueError: not a regular file, not a readable video, no video stream, no stated
            frame size, or frames above the ``image_pixels`` limit.
    """
    path = require_file(path, "video")
    try:
        container = av.open(str(path))
    except av.error.FFmpegError as error:
        raise ValueError(f"cannot read video {path}: {_reason(error)}") from error
    try:
        _check_header(path, container)
    except BaseException:
        container.close()
        raise
    return container


def _check_header(path: Path, container: av.container.InputContainer) -> None:
    if not container.streams.video:
        # a muxer closed before the first frame writes no track: the file holds nothing
        if not container.streams:
            raise ValueError(
                f"no frames in video {path}: it holds no track with any data (an empty or "
                "cut-off recording)"
            )
        raise ValueError(f"no video stream in {path}")
    stream = container.streams.video[0]
    context = stream.codec_context  # None when FFmpeg has no decoder for the stream
    if context is None:
        raise ValueError(f"cannot read video {path}: FFmpeg has no decoder for its stream")
    height, width = context.height, context.width
    if height < 1 or width < 1:
        raise ValueError(
            f"cannot read video {path}: its header states no frame size (refusing to "
            "decode it to find out)"
        )
    limits.check("image_pixels", height * width, f"{path}: {width}x{height} frames")
    context.options = {"max_pixels": str(limits.limit("image_pixels"))}


def _decode(
    path: Path, container: av.container.InputContainer, stride: int
) -> Iterator[np.ndarray]:
    stream = container.streams.video[0]
    stream.thread_type = "AUTO"  # frame threading: decoding is the slow part of reading
    same_size = frame_size_check(path)
    try:
        # Skipped frames must still be decoded (later frames depend on them), but are never
        # converted to RGB.
        for index, frame in enumerate(islice(container.decode(stream), 0, None, stride)):
            yield same_size(rgb(frame), index * stride)
    except av.error.FFmpegError as error:
        raise ValueError(f"cannot decode video {path}: {_reason(error)}") from error


def frame_size_check(path: Path) -> Callable[[np.ndarray, int], np.ndarray]:
    """A check that every frame it is given has the first one's size; names the frame.

    Frames of another size mid-stream (a spliced file) would fail later with numpy's
    message and no file name; tracking needs one size per video.
    """
    first: list[tuple[int, ...]] = []

    def check(frame: np.ndarray, index: int) -> np.ndarray:
        if not first:
            first.append(frame.shape)
        elif frame.shape != first[0]:
            raise ValueError(
                f"{path}: frame {index} is {frame.shape[1]}x{frame.shape[0]}, the first "
                f"frame read is {first[0][1]}x{first[0][0]}; re-encode the video at one size"
            )
        return frame

    return check


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
