"""Building the TAP-Vid-Kinetics shards from the official CSV and locally downloaded clips.

TAP-Vid-Kinetics ships as labels only: a CSV with one row per track (``youtube_id, start_s,
end_s`` then 250 × ``x, y, occluded``, coordinates normalised to [0, 1], occluded ∈ {0, 1})
for clips of the Kinetics-700-2020 validation set, which users download themselves. tapnet's
``generate_tapvid.py`` turns both into 10 pickles ``0000_of_0010.pkl`` … in the layout every
TAP-Vid reader expects; this module writes the same layout without TensorFlow, absl or an
``ffmpeg`` binary (frames are decoded by PyAV, which bundles FFmpeg):

- tracks are grouped into videos by (youtube_id, start, end), in the order the CSV first
  names them; a clip is the file ``{youtube_id}_{start:06}_{end:06}.mp4`` anywhere under
  the clip root; videos without a clip are skipped (and listed);
- frames are resampled to 25 fps with FFmpeg's ``fps`` filter (what ``ffmpeg -vf fps=25``
  does), capped at 250, and stored as a numpy array of JPEG-encoded frames (bytes);
- ``points`` (N, T, 2) float64 get generate_tapvid.py's half-pixel shift, (x·W − 0.5) / W
  and (y·H − 0.5) / H, and ``points``/``occluded`` are cut to T frames for shorter clips;
- ``ceil(V / 10)`` videos go to each shard, in order. Unlike generate_tapvid.py, which writes
  only the shards it fills, every one of the 10 files is written (an empty list where no
  video is left), so that a small set still looks complete to the readers.

The JPEG bytes are PIL's at ``jpeg_quality``, not ffmpeg's MJPEG encoder's, so files differ
from tapnet's byte for byte; the decoded frames differ by JPEG noise only.
"""

from __future__ import annotations

import csv
import io
import logging
import math
import os
import pickle
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import av
import numpy as np
from PIL import Image
from tqdm import tqdm

from taptr.io.atomic import atomic_path
from taptr.io.video import open_video

logger = logging.getLogger(__name__)

FPS = 25.0
MAX_FRAMES = 250
CSV_FRAMES = 250
"""Every CSV row holds exactly this many (x, y, occluded) triples."""
NUM_SHARDS = 10


@dataclass
class KineticsVideo:
    """The tracks of one clip, as the CSV gives them.

    Attributes:
        youtube_id: the YouTube identifier.
        start: clip start in whole seconds.
        end: clip end in whole seconds.
        points: (N, 250, 2) float64 normalised raster (x, y) in [0, 1].
        occluded: (N, 250) bool, True where the point is occluded.
    """

    youtube_id: str
    start: int
    end: int
    points: np.ndarray
    occluded: np.ndarray

    @property
    def name(self) -> str:
        """The clip's file stem, ``{youtube_id}_{start:06}_{end:06}``."""
        return f"{self.youtube_id}_{self.start:06}_{self.end:06}"


@dataclass
class PrepareReport:
    """What `prepare_kinetics` did.

    Attributes:
        shards: the files written, in order.
        videos: names of the videos written, in order.
        missing: names of the CSV's videos without a clip (skipped).
        num_points: tracks written over all videos.
    """

    shards: list[Path] = field(default_factory=list)
    videos: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    num_points: int = 0


def read_kinetics_csv(path: str | os.PathLike[str]) -> list[KineticsVideo]:
    """Reads the TAP-Vid-Kinetics label CSV, grouping tracks by clip.

    Raises:
        FileNotFoundError: no such file.
        ValueError: a malformed row (the message gives the line number).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"CSV not found: {path}")
    groups: dict[tuple[str, int, int], list[list[str]]] = {}
    with path.open(newline="") as stream:
        for line, row in enumerate(csv.reader(stream), start=1):
            if not row:
                continue
            if len(row) != 3 + 3 * CSV_FRAMES:
                raise ValueError(
                    f"{path}:{line}: {len(row)} columns; expected youtube_id, start, end and "
                    f"{CSV_FRAMES} x, y, occluded triples ({3 + 3 * CSV_FRAMES} columns)"
                )
            try:
                key = (row[0], int(row[1]), int(row[2]))
            except ValueError:
                raise ValueError(f"{path}:{line}: start and end must be whole seconds") from None
            groups.setdefault(key, []).append(row[3:])
    return [_video(key, rows, path) for key, rows in groups.items()]


def _video(key: tuple[str, int, int], rows: list[list[str]], path: Path) -> KineticsVideo:
    """Parses one clip's rows of triples."""
    triples = np.array(rows, dtype=object).reshape(len(rows), CSV_FRAMES, 3)
    flags = triples[..., 2]
    if not np.isin(flags, ("0", "1")).all():
        raise ValueError(f"{path}: video {key[0]}: occluded flags must be 0 or 1")
    try:
        points = triples[..., :2].astype(np.float64)
    except ValueError:
        raise ValueError(f"{path}: video {key[0]}: coordinates must be numbers") from None
    return KineticsVideo(*key, points=points, occluded=flags == "1")


def find_clips(root: str | os.PathLike[str]) -> dict[str, Path]:
    """Every ``.mp4`` under ``root`` (any depth), by file stem.

    Raises:
        FileNotFoundError: ``root`` is not a folder.
        ValueError: two clips share a name (the message names both files).
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"clip folder not found: {root}")
    clips: dict[str, Path] = {}
    for path in sorted(root.rglob("*.mp4")):
        if path.stem in clips:
            raise ValueError(f"two clips named {path.stem}: {clips[path.stem]} and {path}")
        clips[path.stem] = path
    return clips


def extract_frames(
    path: str | os.PathLike[str],
    *,
    fps: float = FPS,
    max_frames: int = MAX_FRAMES,
    jpeg_quality: int = 95,
) -> list[bytes]:
    """The clip's frames at ``fps`` (FFmpeg's ``fps`` filter), JPEG-encoded, at most ``max_frames``.

    Raises:
        ValueError: the file cannot be decoded or has no video stream.
    """
    frames: list[bytes] = []
    for frame in _resampled_frames(Path(path), fps):
        frames.append(_jpeg(frame, jpeg_quality))
        if len(frames) == max_frames:
            break
    if not frames:
        raise ValueError(f"{path}: no frames decoded")
    return frames


def _resampled_frames(path: Path, fps: float) -> Iterator[np.ndarray]:
    """(H, W, 3) uint8 RGB frames of the first video stream, through ``fps=<fps>``.

    Opened the guarded way (`taptr.io.video.open_video`: header checked before decoding).
    """
    with open_video(path) as container:
        stream = container.streams.video[0]
        graph = av.filter.Graph()
        source = graph.add_buffer(template=stream)
        resample = graph.add("fps", f"fps={fps}")
        sink = graph.add("buffersink")
        source.link_to(resample)
        resample.link_to(sink)
        graph.configure()
        try:
            for frame in container.decode(stream):
                graph.push(frame)
                yield from _drain(graph)
            graph.push(None)  # end of stream: the filter emits what it still holds
            yield from _drain(graph)
        except av.error.FFmpegError as error:
            raise ValueError(f"{path}: cannot decode the video ({error})") from None


def _drain(graph: av.filter.Graph) -> Iterator[np.ndarray]:
    while True:
        try:
            frame = graph.pull()
        except (av.error.BlockingIOError, av.error.EOFError):
            return
        if isinstance(frame, av.VideoFrame):  # a video graph only gives video frames
            yield frame.to_ndarray(format="rgb24")


def _jpeg(frame: np.ndarray, quality: int) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(frame).save(buffer, format="JPEG", quality=quality)
    return buffer.getvalue()


def build_item(video: KineticsVideo, frames: list[bytes]) -> dict[str, np.ndarray]:
    """One pickle item ``{"video", "points", "occluded"}`` from a clip's labels and frames.

    Args:
        video: the clip's labels.
        frames: T JPEG-encoded frames (T ≤ 250); the labels are cut to T frames.

    Returns:
        ``video`` (T,) bytes array, ``points`` (N, T, 2) float64 shifted by half a pixel as
        generate_tapvid.py does, ``occluded`` (N, T) bool.
    """
    num_frames = len(frames)
    with Image.open(io.BytesIO(frames[0])) as image:
        width, height = image.size
    size = np.array([width, height], dtype=np.float64)
    points = (video.points[:, :num_frames] * size - 0.5) / size
    return {
        "video": np.array(frames),
        "points": points.astype(np.float64),
        "occluded": video.occluded[:, :num_frames].astype(bool),
    }


def shard_name(index: int, num_shards: int = NUM_SHARDS) -> str:
    """``0000_of_0010.pkl`` for shard 0 of 10."""
    return f"{index:04}_of_{num_shards:04}.pkl"


def prepare_kinetics(
    csv_path: str | os.PathLike[str],
    clip_root: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    num_shards: int = NUM_SHARDS,
    jpeg_quality: int = 95,
    progress: bool = False,
) -> PrepareReport:
    """Writes the TAP-Vid-Kinetics shards (see the module docstring for the layout).

    Args:
        csv_path: the official label CSV (``tapvid_kinetics.csv``).
        clip_root: folder holding the downloaded clips, at any depth.
        out_dir: where the shards go (created if missing).
        num_shards: number of pickle files.
        jpeg_quality: PIL JPEG quality of the stored frames.
        progress: show a progress bar over the videos (stderr).

    Raises:
        FileNotFoundError: no CSV, no clip folder, or not a single clip of the CSV found.
        ValueError: a malformed CSV row or an undecodable clip.
    """
    if num_shards < 1:
        raise ValueError(f"num_shards must be at least 1, got {num_shards}")
    labels = read_kinetics_csv(csv_path)
    clips = find_clips(clip_root)
    report = PrepareReport(missing=[v.name for v in labels if v.name not in clips])
    present = [v for v in labels if v.name in clips]
    if not present:
        raise FileNotFoundError(
            f"none of the {len(labels)} clips of {csv_path} is under {clip_root} "
            "(expected files named {youtube_id}_{start:06}_{end:06}.mp4)"
        )
    for name in report.missing:
        logger.warning("no clip %s.mp4 under %s: skipped", name, clip_root)
    per_shard = math.ceil(len(present) / num_shards)
    bar = tqdm(total=len(present), desc="clips", unit="clip", disable=not progress)
    with bar:
        for shard in range(num_shards):
            items = []
            for video in present[shard * per_shard : (shard + 1) * per_shard]:
                frames = extract_frames(clips[video.name], jpeg_quality=jpeg_quality)
                items.append(build_item(video, frames))
                report.videos.append(video.name)
                report.num_points += len(video.points)
                bar.update()
            path = Path(out_dir) / shard_name(shard, num_shards)
            with atomic_path(path) as tmp, tmp.open("wb") as stream:
                pickle.dump(items, stream)
            report.shards.append(path)
    return report
