"""`OnnxTracker`: TAPTRv3 exported to ONNX, tracking whole videos with numpy and onnxruntime.

Pixels and (t, x, y) queries in, tracks and visibility out, with `taptr.Predictor`'s
conventions (`taptr.export.v3_queries`): frames resized to the export's input size as the
model's config says, support points as its config says, each query returned exactly on
its own frame, frames before it not visible unless ``backward`` tracks them with a
time-reversed pass. The frame loop is `taptr.export.v3_loop`; streaming is
`taptr.export.v3_online.OnnxOnlineTracker`. Nothing here imports torch.
"""

from __future__ import annotations

import os
from typing import Any, NamedTuple

import numpy as np

from taptr.config import SUPPORT_KINDS
from taptr.export.v3_loop import V3Graphs, track_points
from taptr.export.v3_manifest import V3Manifest
from taptr.export.v3_queries import (
    both_ways,
    normalised,
    on_own_frames,
    pixel_queries,
    pixel_scale,
    support_points,
    support_scheme,
    visible,
)
from taptr.export.v3_resize import resize_frames
from taptr.query_checks import grid_points


class TrackResult(NamedTuple):
    """Tracks of one video.

    Attributes:
        tracks: (T, N, 2) float32 (x, y) pixels of the input frames.
        visibility: (T, N) bool.
        visibility_logits: (T, N) float32 (−inf before a query frame without ``backward``,
            +inf on it).
        queries: (N, 3) float32 (t, x, y) as tracked.
    """

    tracks: np.ndarray
    visibility: np.ndarray
    visibility_logits: np.ndarray
    queries: np.ndarray


def check_video(video: Any) -> np.ndarray:
    """A (T, H, W, 3) uint8 video, read from a file or folder when given a path.

    Raises:
        ValueError: another shape or type, or no frames.
    """
    if isinstance(video, (str, os.PathLike)):
        from taptr.io.video import read_video

        video = read_video(video)
    if not isinstance(video, np.ndarray) or video.ndim != 4 or video.shape[-1] != 3:
        shape = getattr(video, "shape", type(video).__name__)
        raise ValueError(f"the video must be a (T, H, W, 3) uint8 numpy array, got {shape}")
    if video.dtype != np.uint8:
        raise ValueError(f"the video must be uint8, got {video.dtype}")
    if video.shape[0] == 0:
        raise ValueError("the video has no frames")
    return video


class OnnxTracker:
    """Tracks points through videos with a TAPTRv3 ONNX export, without torch.

    Args:
        directory: the export folder (or `graphs`, already open).
        threads: onnxruntime's intra-op threads (default: one per core).
        providers: onnxruntime execution providers (default: the CPU's).
        history_frames: the most frames held per point (0: all; default: the manifest's).
        visibility_threshold: visible where sigmoid(logit) exceeds it (default: the
            manifest's, the model config's).
        support_points: one of `SUPPORT_KINDS` instead of the model's (default: as the
            model's config says, ``local_and_grid`` falling back to ``grid`` past 32
            queries).
        graphs: open graphs to use instead of ``directory`` (tests run eager wrappers).

    Raises:
        ValueError: an unknown support scheme or a threshold outside (0, 1).
    """

    def __init__(
        self,
        directory: str | os.PathLike[str] | None = None,
        *,
        threads: int | None = None,
        providers: list[Any] | None = None,
        history_frames: int | None = None,
        visibility_threshold: float | None = None,
        support_points: str | None = None,
        graphs: V3Graphs | None = None,
    ) -> None:
        if graphs is None:
            from taptr.export.v3_sessions import OnnxGraphs

            if directory is None:
                raise ValueError("pass the export folder")
            graphs = OnnxGraphs(directory, threads=threads, providers=providers)
        self.graphs = graphs
        self.manifest: V3Manifest = graphs.manifest
        if support_points is not None and support_points not in SUPPORT_KINDS:
            choices = ", ".join(SUPPORT_KINDS)
            raise ValueError(f"support_points must be one of {choices}, got {support_points!r}")
        self.support_points = support_points
        threshold = visibility_threshold or self.manifest.visibility_threshold
        if not 0 < threshold < 1:
            raise ValueError(f"visibility_threshold must lie in (0, 1), got {threshold}")
        self.visibility_threshold = threshold
        self.history_frames = history_frames

    def track(
        self,
        video: Any,
        queries: Any = None,
        *,
        grid_size: int | None = None,
        grid_query_frame: int = 0,
        backward: bool = False,
    ) -> TrackResult:
        """Tracks query points through one video.

        Args:
            video: uint8 (T, H, W, 3) RGB frames, or a path to a video file or folder.
            queries: (N, 3) (t, x, y): frame index and pixel position.
            grid_size: instead of queries, a grid_size × grid_size grid of points.
            grid_query_frame: the frame the grid is placed on.
            backward: also track the frames before each query frame (a reversed pass).

        Raises:
            ValueError: invalid video or queries (the predictor's messages).
        """
        video = check_video(video)
        num_frames, height, width = video.shape[:3]
        if (queries is None) == (grid_size is None):
            raise ValueError("pass exactly one of queries or grid_size")
        if grid_size is not None:
            if not 0 <= grid_query_frame < num_frames:
                raise ValueError(f"grid_query_frame outside [0, {num_frames})")
            queries = grid_points(grid_size, grid_query_frame, height, width)
        query = pixel_queries(queries, num_frames, height, width)

        def one_pass(pass_queries: np.ndarray, reverse: bool) -> tuple[np.ndarray, np.ndarray]:
            return self._forward_pass(video, pass_queries, reverse)

        if backward:
            tracks, logits = both_ways(one_pass, query, num_frames)
        else:
            tracks, logits = one_pass(query, False)
        tracks, logits = on_own_frames(tracks, logits, query, hide_earlier=not backward)
        return TrackResult(tracks, visible(logits, self.visibility_threshold), logits, query)

    def _forward_pass(
        self, video: np.ndarray, queries: np.ndarray, reverse: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """Forward-in-time tracking: (T, H, W, 3), (N, 3) → tracks (T, N, 2), logits (T, N).

        With ``reverse`` the video is read backwards (frame t of the pass is T − 1 − t).
        """
        num_frames, height, width = video.shape[:3]
        starts = queries[:, 0].astype(np.int64)
        xy = normalised(queries[:, 1:], height, width)
        scheme = support_scheme(self.manifest.support, len(starts), self.support_points)
        extra_starts, extra_xy = support_points(self.manifest.support, scheme, starts, xy)
        size, method = self.manifest.input_size, self.manifest.resize

        def load(frame: int) -> np.ndarray:
            index = num_frames - 1 - frame if reverse else frame
            return resize_frames(video[index : index + 1], size, method)[0]

        result = track_points(
            self.graphs,
            load,
            num_frames,
            np.concatenate((starts, extra_starts)),
            np.concatenate((xy, extra_xy)),
            history_frames=self.history_frames,
        )
        real = len(starts)  # support points come after the user's and are dropped
        positions = result.positions[:, :real]
        logits = result.visibility_logits[:, :real, 1]
        if not np.isfinite(positions).all() or np.isnan(logits).any():
            raise ValueError("the exported model produced NaN or infinite tracks")
        return positions * pixel_scale(height, width), logits
