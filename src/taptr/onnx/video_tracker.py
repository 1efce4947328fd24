"""`OnnxTracker`: TAPTRv3 exported to ONNX, tracking whole videos without torch.

Pixels and (t, x, y) queries in, tracks and visibility out, with `taptr.Predictor`'s
conventions, whose rules it takes from `taptr.task`: frames resized to the export's input
size as the model's config says, support points as its config says (the registry's
scheme, with its fallback), each query returned exactly on its own frame, frames before
it not visible unless ``backward`` tracks them with a time-reversed pass. The frame loop
is `taptr.onnx.frame_loop`; the graphs run in the engine named by ``engine``
(`taptr.onnx.graph_engines`); streaming is `taptr.onnx.stream_tracker`. Before a video is
tracked, its peak memory is estimated and a run over the budget is refused
(`taptr.onnx.graph_memory`), as `Predictor` does. Nothing here imports torch.

Shapes: T frames, N points.
"""

from __future__ import annotations

import os
from typing import Any, NamedTuple

import numpy as np

from taptr.config import check_history_frames
from taptr.onnx.frame_loop import track_points
from taptr.onnx.graph_engines import StepGraphs, open_graphs
from taptr.onnx.graph_memory import check_run_memory, graphs_bytes
from taptr.onnx.v3_manifest import V3Manifest
from taptr.task.both_ways import both_ways
from taptr.task.pixel_queries import normalised, on_own_frames, pixel_queries, pixel_scale
from taptr.task.pixel_queries import visible as visible_where
from taptr.task.query_checks import grid_points
from taptr.task.resizing import resize_frames
from taptr.task.support_schemes import SupportPattern, SupportScheme, choose_scheme, support_scheme


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


def support_pattern(manifest: V3Manifest) -> SupportPattern:
    """The manifest's support numbers, as the loop adds them (float32, normalised)."""
    rule = manifest.support
    return SupportPattern(
        np.array(rule.local_offsets, np.float32).reshape(-1, 2),
        np.array(rule.grid_positions, np.float32).reshape(-1, 2),
        np.array(rule.grid_start_frames, np.int64),
        local_budget=rule.local_budget,
        context_points=rule.context_points,
    )


def chosen_threshold(threshold: float | None, manifest: V3Manifest) -> float:
    """The threshold asked for (0.0 included), else the manifest's.

    Raises:
        ValueError: outside (0, 1).
    """
    chosen = manifest.visibility_threshold if threshold is None else threshold
    if isinstance(chosen, bool) or not isinstance(chosen, int | float) or not 0 < chosen < 1:
        raise ValueError(f"visibility_threshold must lie in (0, 1), got {chosen!r}")
    return float(chosen)


class OnnxTracker:
    """Tracks points through videos with a TAPTRv3 ONNX export, without torch.

    Args:
        directory: the export folder (or `graphs`, already open).
        engine: the engine that runs the graphs (`taptr.onnx.graph_engines.ENGINES`:
            ``onnxruntime``, the default, or ``openvino``).
        threads: the engine's threads (default: one per core).
        history_frames: the most frames held per point (0: all; default: the manifest's).
        visibility_threshold: visible where sigmoid(logit) exceeds it (default: the
            manifest's, the model config's).
        support_points: a registered scheme (`taptr.task.support_schemes`) instead of the
            model's (default: as the model's config says, ``local_and_grid`` falling back
            to ``grid`` past 32 queries).
        graphs: open graphs to use instead of ``directory`` (tests run eager wrappers).
        **options: the engine's own: onnxruntime's ``preset`` (``cpu``, ``cuda``,
            ``cuda-graphs``, ``tensorrt``) or ``providers``; OpenVINO's ``device`` and
            ``precision``.

    Raises:
        ValueError: an unknown engine or support scheme, a threshold outside (0, 1), a
            history limit of 1, or an export folder that fails its checks.
    """

    def __init__(
        self,
        directory: str | os.PathLike[str] | None = None,
        *,
        engine: str = "onnxruntime",
        threads: int | None = None,
        history_frames: int | None = None,
        visibility_threshold: float | None = None,
        support_points: str | None = None,
        graphs: StepGraphs | None = None,
        **options: Any,
    ) -> None:
        if history_frames is not None:
            check_history_frames(history_frames)
        if support_points is not None:
            support_scheme(support_points)  # refuses unknown names, listing the schemes
        if graphs is None:
            if directory is None:
                raise ValueError("pass the export folder")
            graphs = open_graphs(directory, engine, threads=threads, **options)
        self.graph_bytes = graphs_bytes(directory)
        self.graphs = graphs
        self.manifest: V3Manifest = graphs.manifest
        self.support_points = support_points
        self.support_pattern = support_pattern(self.manifest)
        self.visibility_threshold = chosen_threshold(visibility_threshold, self.manifest)
        self.history_frames = history_frames

    def chosen_support(self, num_queries: int) -> SupportScheme:
        """The registered scheme ``num_queries`` user points get."""
        rule, pattern = self.manifest.support, self.support_pattern
        return choose_scheme(rule.scheme, num_queries, pattern, self.support_points)

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
            ValueError: invalid video or queries (the predictor's messages), or a run
                whose estimated memory exceeds the budget.
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
        points = len(query) + self.chosen_support(len(query)).count(
            len(query), self.support_pattern
        )
        check_run_memory(self.manifest, points, num_frames, self.history_frames, self.graph_bytes)

        def one_pass(pass_queries: np.ndarray, reverse: bool) -> tuple[np.ndarray, np.ndarray]:
            return self._forward_pass(video, pass_queries, reverse)

        if backward:
            tracks, logits = both_ways(one_pass, query, num_frames)
        else:
            tracks, logits = one_pass(query, False)
        tracks, logits = on_own_frames(tracks, logits, query, hide_earlier=not backward)
        return TrackResult(tracks, visible_where(logits, self.visibility_threshold), logits, query)

    def _forward_pass(
        self, video: np.ndarray, queries: np.ndarray, reverse: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """Forward-in-time tracking: (T, H, W, 3), (N, 3) → tracks (T, N, 2), logits (T, N).

        With ``reverse`` the video is read backwards (frame t of the pass is T − 1 − t).
        """
        num_frames, height, width = video.shape[:3]
        starts = queries[:, 0].astype(np.int64)
        xy = normalised(queries[:, 1:], height, width)
        support = self.chosen_support(len(starts)).points(starts, xy, self.support_pattern)
        size, method = self.manifest.input_size, self.manifest.resize

        def load(frame: int) -> np.ndarray:
            index = num_frames - 1 - frame if reverse else frame
            return resize_frames(video[index : index + 1], size, method)[0]

        result = track_points(
            self.graphs,
            load,
            num_frames,
            np.concatenate((starts, support.start_frames)),
            np.concatenate((xy, support.positions)),
            history_frames=self.history_frames,
        )
        real = len(starts)  # support points come after the user's and are dropped
        positions = result.positions[:, :real]
        logits = result.visibility_logits[:, :real, 1]
        if not np.isfinite(positions).all() or np.isnan(logits).any():
            raise ValueError("the exported model produced NaN or infinite tracks")
        return positions * pixel_scale(height, width), logits
