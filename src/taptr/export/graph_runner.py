"""Tracking with exported graphs, driven by the PyTorch model's own window driver.

The graphs hold the network; the sliding-window rules are not repeated here.
`GraphNetwork` puts a `Steps` (the three graphs, numpy in and out, `taptr.export.graph_steps`)
behind `taptr.model.sliding_window.WindowNetwork`, converting numpy ↔ torch at the boundary, and
`GraphFrames` encodes frames through the encoder graph; `track_points` hands both to
`taptr.model.sliding_window.run_windows`, so exported graphs and PyTorch model decode the same
windows by the same code. The rules, for porting the loop to another language, are
listed in ``docs/EXPORT.md``.

Shapes: T frames, N points, C channels, S memory tokens, W_t frames in a window.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
import torch
from torch import Tensor

from taptr.export.manifest import ExportManifest
from taptr.model.frame_source import FrameFeatures
from taptr.model.frame_tables import FrameTables
from taptr.model.sliding_window import WindowDecoding, run_windows
from taptr.model.trajectory import QuerySet
from taptr.task.results import TrackArrays


class Steps(Protocol):
    """The three exported graphs, called with and returning float32/bool numpy arrays."""

    def encode(self, frames: np.ndarray) -> np.ndarray:
        """Frames (F, 3, H, W) RGB in [0, 1] → memory (F, S, C)."""
        ...

    def init_points(self, memory: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """Memory (S, C) of one frame, normalised positions (N, 2) → content (N, C)."""
        ...

    def decode(
        self,
        memory: np.ndarray,
        content: np.ndarray,
        positions: np.ndarray,
        initial: np.ndarray,
        tracking: np.ndarray,
        update: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One window → position logits (W_t, N, 4), visibility logits (W_t, N, 3), content."""
        ...


def _to_numpy(batch_of_one: Tensor) -> np.ndarray:
    """(1, ...) CPU tensor → (...) contiguous array: the graphs take batch size one."""
    return np.ascontiguousarray(batch_of_one[0].numpy())


def _to_torch(array: np.ndarray) -> Tensor:
    """(...) graph output → (1, ...) tensor, sharing memory where it can."""
    return torch.from_numpy(np.asarray(array))[None]


class GraphNetwork:
    """The exported graphs as the window driver's network (batch one, float32 on the CPU).

    What the graphs give differs from the PyTorch module in three ways, all adapted here:
    ``init_points`` samples and projects in one call, so ``project_samples`` is the
    identity; ``decode_window`` returns the last layer only and no APU-updated positions
    (``num_layers`` is 1); and it computes the content handed to the next window in the
    same call, from the initial content it is given.

    Args:
        steps: the graphs (`taptr.export.graph_steps.load_steps`).
        manifest: the export's description (window rules, channels).
    """

    num_layers = 1
    has_position_update = False
    training = False

    def __init__(self, steps: Steps, manifest: ExportManifest) -> None:
        self.steps = steps
        self.window_size = manifest.window_size
        self.window_stride = manifest.window_stride
        self.long_video_frames = manifest.long_video_frames
        self.memory_efficient = manifest.memory_efficient
        self.content_channels = manifest.d_model

    def sample_points(
        self, memory: Tensor, spatial_shapes: list[tuple[int, int]], positions: Tensor
    ) -> Tensor:
        """The ``init_points`` graph: memory (1, S, C), positions (1, N, 2) → content (1, N, C)."""
        return _to_torch(self.steps.init_points(_to_numpy(memory), _to_numpy(positions)))

    def project_samples(self, samples: Tensor) -> Tensor:
        """The identity: ``sample_points`` already projected."""
        return samples

    def decode_window(
        self,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        content: Tensor,
        positions: Tensor,
        initial: Tensor,
        tracking: Tensor,
        update: Tensor,
        tables: FrameTables | None = None,
        all_tracked: bool | None = None,
    ) -> WindowDecoding:
        """The ``decode_window`` graph; shapes as in `taptr.model.sliding_window.WindowNetwork`.

        The graph projects every frame's keys and values itself and masks by ``tracking``,
        so ``tables`` and ``all_tracked`` are not read.
        """
        inputs = (memory, content, positions, initial, tracking, update)
        window_positions, visibility_logits, next_content = (
            _to_torch(output) for output in self.steps.decode(*map(_to_numpy, inputs))
        )
        # one layer: (1, 1, W_t, N, D) as (D_l, B, W_t, N, D)
        return WindowDecoding(window_positions[None], visibility_logits[None], None, next_content)


class GraphFrames:
    """Encodes frames through the encoder graph on demand, each once; a `FrameSource`.

    Frames are loaded in one call per window but go through the encoder graph one at a
    time: its ``grid_sample`` attention holds the samples of every token of a frame at once
    (a peak of 2.1 GB for one 512 × 512 frame of the paper model), so several frames per
    call multiply the peak memory without being faster on a CPU. Only frames a later window
    can read are kept.

    Args:
        steps: the graphs.
        manifest: the export's description (memory levels).
        load: returns frames first..last (inclusive), (F, 3, H, W) float32 RGB in [0, 1].
    """

    def __init__(
        self, steps: Steps, manifest: ExportManifest, load: Callable[[int, int], np.ndarray]
    ) -> None:
        self.steps = steps
        self.load = load
        self.spatial_shapes = [(h, w) for h, w in manifest.spatial_shapes]
        self.cache: dict[int, Tensor] = {}

    def __call__(self, first: int, last: int) -> FrameFeatures:
        """Memory (1, W_t, S, C) of frames first..last (windows come in increasing order)."""
        for frame in [f for f in self.cache if f < first]:
            del self.cache[frame]
        missing = [f for f in range(first, last + 1) if f not in self.cache]
        if missing:
            frames = self.load(missing[0], missing[-1])  # (F, 3, H, W)
            for frame, image in zip(missing, frames, strict=True):
                self.cache[frame] = _to_torch(self.steps.encode(image[None])[0])[0]  # (S, C)
        memory = torch.stack([self.cache[f] for f in range(first, last + 1)])[None]
        return FrameFeatures(memory, self.spatial_shapes)


def track_points(
    steps: Steps,
    manifest: ExportManifest,
    frames: Callable[[int, int], np.ndarray] | np.ndarray,
    num_frames: int,
    start_frames: np.ndarray,
    positions: np.ndarray,
    start_visible: np.ndarray | None = None,
) -> TrackArrays:
    """Tracks points through a whole video with exported graphs, window by window.

    Args:
        steps: the graphs (`taptr.export.graph_steps.load_steps`).
        manifest: the export's description (window rules, channels).
        frames: (T, 3, H, W) float32 RGB in [0, 1] at ``manifest.input_size``, or a
            function returning frames first..last (inclusive) as (F, 3, H, W).
        num_frames: T.
        start_frames: (N,) int frame where each point is given.
        positions: (N, 2) its (x, y) there, normalised by (W − 1, H − 1).
        start_visible: (N,) bool visibility at the start frame (default all visible);
            only sets the logits of frames that no window writes.
    """
    video = frames

    def load(first: int, last: int) -> np.ndarray:
        if callable(video):
            chunk = np.asarray(video(first, last), np.float32)
        else:
            chunk = np.asarray(video[first : last + 1], np.float32)  # (F, 3, H, W)
        if chunk.shape[1:] != (3, *manifest.input_size):
            raise ValueError(
                f"frames must be (F, 3, {manifest.input_size[0]}, {manifest.input_size[1]}) "
                f"for this export, got {chunk.shape}"
            )
        return chunk

    starts = np.asarray(start_frames, np.int64)
    visible = np.ones(len(starts), bool) if start_visible is None else start_visible
    queries = QuerySet(
        torch.from_numpy(starts)[None],
        torch.from_numpy(np.asarray(positions, np.float32))[None],
        torch.from_numpy(np.asarray(visible, bool))[None],
    )
    network = GraphNetwork(steps, manifest)
    with torch.no_grad():
        output = run_windows(
            network, queries, num_frames, GraphFrames(steps, manifest, load), torch.float32
        )
    return TrackArrays(output.positions[0].numpy(), output.visibility_logits[0].numpy())
