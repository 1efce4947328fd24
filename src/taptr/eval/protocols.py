"""The two evaluation protocols and the scoring of one video.

Both resize every video to 256 × 256 (PIL Lanczos per frame, what tapnet's mediapy resize
does; a no-op for 256 × 256 videos) and score in that frame. They differ in coordinates and
in who tracks:

- ``standard`` (any tracker): the canonical TAP-Vid scaling. Ground truth is mapped through
  raster coordinates, pixel = raster × 256 − 0.5, so pixel centres stay at integers.
- ``official`` (the TAPTR model only): TAPTR's own evaluation (TAPTRv2-SPEC.md §4), with
  coordinates raster × 255 and `OfficialTAPTR` tracking. Distances, and so the thresholds,
  are 255/256 of the standard ones; use it to reproduce the paper's numbers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, NamedTuple, Protocol

import numpy as np
from PIL import Image

from taptr.data.tapvid import pixels_to_raster, raster_to_pixels
from taptr.eval.metrics import tapvid_metrics
from taptr.eval.query_sampling import QueryPoints, sample_queries
from taptr.eval.trackers import Tracker, run_tracker
from taptr.types import TrackingSample

if TYPE_CHECKING:  # the official protocol needs torch; the standard one does not
    from taptr.eval.official_protocol import OfficialTAPTR

FRAME_SIZE = 256
"""Side of the square frame the benchmark is scored in."""


class Clip(NamedTuple):
    """A video as a protocol scores it.

    Attributes:
        video: (T, 256, 256, 3) uint8 RGB frames.
        tracks: (T, N, 2) float32 ground-truth (x, y) in the protocol's 256-frame units.
        visible: (T, N) bool ground-truth visibility.
    """

    video: np.ndarray
    tracks: np.ndarray
    visible: np.ndarray


@dataclass
class VideoResult:
    """The outcome of one video.

    Attributes:
        index: position of the video in the dataset.
        name: the video's name.
        num_points: query points scored (N).
        num_frames: frames of the video (T).
        metrics: every TAP-Vid metric name mapped to a fraction (NaN if nothing was scored).
        seconds: wall time of tracking and scoring.
    """

    index: int
    name: str
    num_points: int
    num_frames: int
    metrics: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0


class Prediction(NamedTuple):
    """What a protocol predicted for one video, for overlays.

    Attributes:
        points: the queries and their ground truth.
        tracks: (T, N, 2) float predicted (x, y) in 256-frame units.
        visible: (T, N) bool predicted visibility.
    """

    points: QueryPoints
    tracks: np.ndarray
    visible: np.ndarray


def resize_video(video: np.ndarray, size: int = FRAME_SIZE) -> np.ndarray:
    """(T, H, W, 3) uint8 → (T, size, size, 3) uint8 with PIL's Lanczos filter per frame."""
    if video.shape[1:3] == (size, size):
        return video
    return np.stack(
        [
            np.asarray(Image.fromarray(f).resize((size, size), Image.Resampling.LANCZOS))
            for f in video
        ]
    )


def _resized_with_raster(sample: TrackingSample) -> tuple[np.ndarray, np.ndarray]:
    """The (T, 256, 256, 3) video and the (T, N, 2) ground truth as normalised raster (x, y)."""
    height, width = sample.video.shape[1:3]
    return resize_video(sample.video), pixels_to_raster(sample.tracks, height, width)


class EvalProtocol(Protocol):
    """How a dataset video becomes a scored clip, and how its queries get tracked."""

    def prepare(self, sample: TrackingSample) -> Clip:
        """The 256 × 256 clip and its ground truth in this protocol's units."""
        ...

    def predict(
        self, video: np.ndarray, points: QueryPoints, query_mode: str, index: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Tracks (T, N, 2) and visibility (T, N) of ``points`` in a (T, 256, 256, 3) video.

        ``index`` is the video's position in the dataset.
        """
        ...


class StandardProtocol:
    """Canonical TAP-Vid scaling; any `Tracker`.

    Args:
        tracker: the tracker to evaluate.
    """

    def __init__(self, tracker: Tracker) -> None:
        self.tracker = tracker

    def prepare(self, sample: TrackingSample) -> Clip:
        """Resizes to 256 × 256; ground truth through raster coordinates (× 256 − 0.5)."""
        video, raster = _resized_with_raster(sample)
        tracks = raster_to_pixels(raster, FRAME_SIZE, FRAME_SIZE).astype(np.float32)
        return Clip(video, tracks, sample.visible)

    def predict(
        self, video: np.ndarray, points: QueryPoints, query_mode: str, index: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """Runs the tracker, with a reversed pass for causal trackers in ``strided`` mode."""
        return run_tracker(self.tracker, video, points.queries, query_mode)


class OfficialProtocol:
    """TAPTR's own evaluation, with its × 255 coordinates and query padding.

    Args:
        model: the model to evaluate, wrapped in the official recipe.
    """

    def __init__(self, model: OfficialTAPTR) -> None:
        self.model = model

    def prepare(self, sample: TrackingSample) -> Clip:
        """Resizes to 256 × 256; ground truth = normalised raster × 255 (the official scale)."""
        video, raster = _resized_with_raster(sample)
        return Clip(video, (raster * (FRAME_SIZE - 1)).astype(np.float32), sample.visible)

    def predict(
        self, video: np.ndarray, points: QueryPoints, query_mode: str, index: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """Runs the official recipe (padding or support points, input size, passes)."""
        return self.model.predict(video, points, query_mode, index)


def evaluate_video(
    protocol: EvalProtocol, sample: TrackingSample, query_mode: str, index: int
) -> tuple[VideoResult, Prediction]:
    """Scores one video.

    Args:
        protocol: how to prepare, track and scale.
        sample: the video with ground truth, as a reader returns it.
        query_mode: ``"first"`` or ``"strided"``.
        index: position of the video in the dataset.
    """
    start = time.perf_counter()
    check_ground_truth(sample)
    clip = protocol.prepare(sample)
    points = sample_queries(clip.tracks, clip.visible, query_mode)
    result = VideoResult(index, sample.name or str(index), len(points.queries), len(clip.video))
    if result.num_points == 0:
        tracks, visible = (
            np.zeros((result.num_frames, 0, 2)),
            np.zeros((result.num_frames, 0), bool),
        )
    else:
        tracks, visible = protocol.predict(clip.video, points, query_mode, index)
    result.metrics = tapvid_metrics(
        points.queries, points.tracks, points.visible, tracks, visible, query_mode
    )
    result.seconds = time.perf_counter() - start
    return result, Prediction(points, tracks, visible)


GROUND_TRUTH_MARGIN = 0.05
"""Visible ground truth may lie this fraction of the frame's side outside it (rounding,
points on the border); beyond, the coordinates are in other units (pixels in a file of
normalised points) or corrupt, and scoring them would give meaningless numbers."""


class UnscorableVideoError(ValueError):
    """A video's ground truth cannot be scored; the message names the video."""


def check_ground_truth(sample: TrackingSample) -> None:
    """Raises `UnscorableVideoError` when visible ground truth lies outside the frame.

    Args:
        sample: a video as a reader returns it; tracks (T, N, 2) pixels, visible (T, N).
    """
    height, width = sample.video.shape[1:3]
    low = -0.5 - GROUND_TRUTH_MARGIN * np.array([width, height])
    high = np.array([width, height]) - 0.5 + GROUND_TRUTH_MARGIN * np.array([width, height])
    outside = sample.visible & ((sample.tracks < low) | (sample.tracks > high)).any(-1)
    if outside.any():
        frame, point = (int(i) for i in np.argwhere(outside)[0])
        x, y = (float(v) for v in sample.tracks[frame, point])
        raise UnscorableVideoError(
            f"video {sample.name!r}: {int(outside.sum()):,} visible ground-truth positions lie "
            f"outside its {width}x{height} frame (e.g. point {point} on frame {frame} at "
            f"({x:.4g}, {y:.4g}) pixels); the points must be normalised to [0, 1]"
        )
