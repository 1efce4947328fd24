"""The reference loop over exported graphs: the sliding-window driver in plain numpy.

This mirrors `taptr.model.tracker` rule for rule, so that it can be ported to any language
next to the exported graphs (it needs numpy only; the graphs run through a `Steps`):

- windows of ``window_size`` frames every ``window_stride`` frames, the last one shifted
  back to end on the last frame, one window for videos shorter than that;
- a window where no point has a frame after its start frame is skipped entirely;
- points are initialised in the first decoded window containing their start frame, from
  the memory of that frame (TAPTR v1's memory-efficient mode: on the first window, from
  frame min(start, last frame of the window));
- positions and visibility are written back where the update mask holds (frames after a
  point's start frame), and the window's last frame is copied to every later frame;
- the content handed over is written on the whole window and copied to later frames
  after every window, or, for videos longer than ``long_video_frames``, only after every
  ⌊T / long_video_frames⌋-th window (the official long-video rule).

Shapes: T frames, N points, C channels, S memory tokens, W_t frames in a window.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple, Protocol

import numpy as np

from taptr.export.manifest import ExportManifest
from taptr.windows import content_padding_gap, window_ranges

INVERSE_SIGMOID_EPS = 1e-3
"""The official clamp of the inverse sigmoid (as `taptr.geometry.inverse_sigmoid`)."""


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


class TrackArrays(NamedTuple):
    """Tracks of a whole video in model units.

    Attributes:
        positions: (T, N, 2) float32 (x, y) normalised by (W − 1, H − 1).
        visibility_logits: (T, N, 3) float32 (channel 1 = visible).
    """

    positions: np.ndarray
    visibility_logits: np.ndarray


def inverse_sigmoid(x: np.ndarray) -> np.ndarray:
    """``log(max(x, eps) / max(1 − x, eps))`` on x clipped to [0, 1]."""
    x = np.clip(x, 0, 1)
    eps = INVERSE_SIGMOID_EPS
    return np.log(np.maximum(x, eps) / np.maximum(1 - x, eps)).astype(np.float32)


class Trajectory:
    """Per-frame (N, D) values from frame ``first`` on, plus one shared value for the rest.

    The numpy twin of `taptr.model.trajectory.Trajectory`: frames after the last held one
    all hold ``future``, so copying a frame to every later frame is free and memory stays
    bounded by the frames still in use.
    """

    def __init__(self, future: np.ndarray) -> None:
        self.first = 0
        self.frames: list[np.ndarray] = []
        self.future = future

    def _extend(self, last: int) -> None:
        self.frames.extend([self.future] * (last + 1 - self.first - len(self.frames)))

    def read(self, first: int, last: int) -> np.ndarray:
        """Values of frames first..last, (W_t, N, D)."""
        if first < self.first:
            raise IndexError(f"frame {first} was already released (first held: {self.first})")
        self._extend(last)
        return np.stack(self.frames[first - self.first : last + 1 - self.first])

    def write(self, first: int, values: np.ndarray, mask: np.ndarray) -> None:
        """Overwrites frames first.. with ``values`` (W_t, N, D) where ``mask`` (W_t, N) holds."""
        self._extend(first + len(values) - 1)
        for offset, (value, where) in enumerate(zip(values, mask, strict=True)):
            index = first + offset - self.first
            self.frames[index] = np.where(where[:, None], value, self.frames[index])

    def fill(self, select: np.ndarray, value: np.ndarray) -> None:
        """Sets every held and future frame of the selected points, (N,) and (N, D)."""
        self.frames = [np.where(select[:, None], value, f) for f in self.frames]
        self.future = np.where(select[:, None], value, self.future)

    def pad_from(self, frame: int) -> None:
        """Every frame after ``frame`` takes its value."""
        self.future = self.frames[frame - self.first]
        del self.frames[frame + 1 - self.first :]

    def release(self, before: int) -> None:
        """Drops the held frames before ``before``."""
        count = max(0, min(before - self.first, len(self.frames)))
        self.frames = self.frames[count:]
        self.first += count


class EncodedFrames:
    """Encodes frames on demand, each once, keeping only frames a later window can read.

    Frames go through the encoder graph one at a time: its ``grid_sample`` attention holds
    the samples of every token of a frame at once (a peak of 2.1 GB for one 512 × 512 frame of
    the paper model), so several frames per call multiply the peak memory without being
    faster on a CPU.
    """

    def __init__(self, steps: Steps, frames: Callable[[int, int], np.ndarray]) -> None:
        self.steps = steps
        self.load = frames
        self.cache: dict[int, np.ndarray] = {}

    def __call__(self, first: int, last: int) -> np.ndarray:
        """Memory (W_t, S, C) of frames first..last (windows come in increasing order)."""
        for frame in [f for f in self.cache if f < first]:
            del self.cache[frame]
        missing = [f for f in range(first, last + 1) if f not in self.cache]
        if missing:
            frames = self.load(missing[0], missing[-1])  # (F, 3, H, W)
            for frame, image in zip(missing, frames, strict=True):
                self.cache[frame] = self.steps.encode(image[None])[0]  # (S, C)
        return np.stack([self.cache[f] for f in range(first, last + 1)])


class PointState:
    """What the next window needs about the points; the driver's `TrackerState`, last layer.

    Attributes:
        starts: (N,) int64 start frame of each point.
        queries: (N, 2) float32 normalised (x, y) on the start frame.
        initial: (N, C) initial content (zeros until initialised).
        initialised: (N,) bool.
        content, positions, visibility: trajectories of (N, C), (N, 4) logits, (N, 3).
        next_window: index of the next window.
    """

    def __init__(
        self, starts: np.ndarray, queries: np.ndarray, visible: np.ndarray, channels: int
    ) -> None:
        points = len(starts)
        self.starts = starts
        self.queries = queries
        self.initial = np.zeros((points, channels), np.float32)
        self.initialised = np.zeros(points, bool)
        self.content = Trajectory(np.zeros((points, channels), np.float32))
        position = np.concatenate((inverse_sigmoid(queries), np.zeros((points, 2), np.float32)), 1)
        self.positions = Trajectory(position)  # (N, 4)
        self.visibility = Trajectory(np.eye(3, dtype=np.float32)[np.where(visible, 1, 2)])
        self.next_window = 0

    def initialise(
        self, steps: Steps, memory: np.ndarray, first: int, clamp_starts: bool = False
    ) -> None:
        """Content of points whose start frame lies in the window, memory (W_t, S, C)."""
        starts = np.minimum(self.starts, first + len(memory) - 1) if clamp_starts else self.starts
        new = ~self.initialised & (starts >= first) & (starts < first + len(memory))
        if not new.any():
            return
        content = np.zeros_like(self.initial)
        for offset in range(len(memory)):
            here = new & (starts == first + offset)
            if here.any():
                sampled = steps.init_points(memory[offset], self.queries)  # (N, C)
                content = np.where(here[:, None], sampled, content)
        self.initial = np.where(new[:, None], content, self.initial)
        self.initialised |= new
        self.content.fill(new, content)


def decode_window(
    steps: Steps,
    manifest: ExportManifest,
    state: PointState,
    first: int,
    last: int,
    source: Callable[[int, int], np.ndarray],
    num_frames: int,
) -> None:
    """Decodes frames first..last and updates ``state`` (`taptr.model.tracker.decode_window`)."""
    index = state.next_window
    state.next_window += 1
    if manifest.memory_efficient and index == 0:
        state.initialise(steps, source(first, last), first, clamp_starts=True)
    frames = np.arange(first, last + 1)[:, None]  # (W_t, 1)
    tracking = frames >= state.starts[None]  # (W_t, N)
    update = frames > state.starts[None]
    if not update.any():
        return  # nothing to move: the official code skips the window, padding included
    memory = source(first, last)
    state.initialise(steps, memory, first)
    content = state.content.read(first, last)
    positions, visibility, handed_over = steps.decode(
        memory,
        content,
        state.positions.read(first, last),
        state.initial,
        tracking,
        update,
    )
    state.positions.write(first, positions, update)
    state.visibility.write(first, visibility, update)
    state.positions.pad_from(last)
    state.visibility.pad_from(last)
    state.content.write(first, handed_over, np.ones_like(update))
    if index % content_padding_gap(num_frames, manifest.long_video_frames, training=False) == 0:
        state.content.pad_from(last)


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
        steps: the graphs (`taptr.export.backends.load_steps`).
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
    visible = np.ones(len(starts), bool) if start_visible is None else np.asarray(start_visible)
    queries = np.asarray(positions, np.float32)
    state = PointState(starts, queries, visible, manifest.d_model)
    source = EncodedFrames(steps, load)
    ranges = window_ranges(num_frames, manifest.window_size, manifest.window_stride)
    for (first, last), following in zip(ranges, ranges[1:] + [(num_frames, 0)], strict=True):
        decode_window(steps, manifest, state, first, last, source, num_frames)
        state.content.release(before=following[0])  # never read again
    logits = state.positions.read(0, num_frames - 1)  # (T, N, 4)
    tracks = 1 / (1 + np.exp(-logits[..., :2]))
    return TrackArrays(tracks.astype(np.float32), state.visibility.read(0, num_frames - 1))
