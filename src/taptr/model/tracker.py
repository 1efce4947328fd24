"""The sliding-window driver: the one place that loops over windows.

Windows of ``window_size`` frames start every ``window_stride`` frames; the last one is
shifted back to end on the last frame, and a video shorter than one window is one window.
For each window the driver initialises the points that start inside it, decodes, writes
the results back where the update mask allows, hands the content over to the next window,
and copies the state of the window's last frame to all later frames.

All of it goes through an explicit `TrackerState`, which only holds what later windows can
still read: the trajectory of every frame from the current window on, plus one shared
value for all frames not yet reached. Encoded frames are requested from a `FrameSource`
window by window, so memory is bounded by the window, not the video.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from taptr.geometry import inverse_sigmoid
from taptr.model.taptr import TAPTR, FrameFeatures
from taptr.model.trajectory import Trajectory
from taptr.windows import content_padding_gap, window_ranges


class QuerySet(NamedTuple):
    """The points to track, in model units.

    Attributes:
        start_frames: (B, N) int64 frame where each point is given.
        positions: (B, N, 2) its (x, y) there, normalised by (W − 1, H − 1).
        start_visible: (B, N) bool visibility label at the start frame (only sets the
            visibility logits of frames the model never writes).
    """

    start_frames: Tensor
    positions: Tensor
    start_visible: Tensor


@dataclass
class TrackerState:
    """Everything the next window needs; no other state exists anywhere.

    Attributes:
        queries: the points, in model units.
        num_frames: total video length when known (decides the long-video content rule).
        initial_content: (B, N, C) each point's initial content (zeros until its start
            frame is reached).
        initialised: (B, N) bool, whether ``initial_content`` is set.
        content: the content trajectory.
        positions: per decoder layer, the position-logit trajectory (B, N, 4).
        visibility: per decoder layer, the visibility-logit trajectory (B, N, 3), float32.
        updated_positions: per decoder layer, the APU-updated position logits (B, N, 4);
            empty without the position update.
        next_window: index of the next window to decode.
    """

    queries: QuerySet
    num_frames: int | None
    initial_content: Tensor
    initialised: Tensor
    content: Trajectory
    positions: list[Trajectory]
    visibility: list[Trajectory]
    updated_positions: list[Trajectory] = field(default_factory=list)
    next_window: int = 0


class TrackOutput(NamedTuple):
    """Full-video trajectories after all windows.

    Attributes:
        positions: (B, T, N, 2) last layer's positions, normalised (x, y).
        visibility_logits: (B, T, N, 3) last layer's logits (channel 1 = visible).
        layer_positions: (D_l, B, T, N, 4) position logits of every layer.
        layer_visibility_logits: (D_l, B, T, N, 3).
        layer_updated_positions: (D_l, B, T, N, 4) APU-updated logits, or None.
    """

    positions: Tensor
    visibility_logits: Tensor
    layer_positions: Tensor
    layer_visibility_logits: Tensor
    layer_updated_positions: Tensor | None


FrameSource = Callable[[int, int], FrameFeatures]
"""Returns the features of frames first..last (inclusive), memory (B, W_t, S, C)."""


def start_state(
    model: TAPTR, queries: QuerySet, num_frames: int | None, dtype: torch.dtype
) -> TrackerState:
    """The state before the first window: every point at its query, visibility one-hot."""
    batch, points = queries.start_frames.shape
    channels = model.query_init.project.out_features
    device = queries.positions.device
    xy_logit = inverse_sigmoid(queries.positions.to(dtype))
    position = torch.cat((xy_logit, xy_logit.new_zeros(batch, points, 2)), dim=-1)  # (B, N, 4)
    one_hot = F.one_hot(torch.where(queries.start_visible, 1, 2), 3).to(torch.float32)
    layers = model.num_layers
    has_update = model.decoder.has_position_update
    return TrackerState(
        queries=queries,
        num_frames=num_frames,
        initial_content=torch.zeros(batch, points, channels, dtype=dtype, device=device),
        initialised=torch.zeros(batch, points, dtype=torch.bool, device=device),
        content=Trajectory(torch.zeros(batch, points, channels, dtype=dtype, device=device)),
        positions=[Trajectory(position) for _ in range(layers)],
        visibility=[Trajectory(one_hot) for _ in range(layers)],
        updated_positions=[Trajectory(position) for _ in range(layers)] if has_update else [],
    )


def add_points(model: TAPTR, state: TrackerState, queries: QuerySet) -> None:
    """Appends points to a running state; they start untracked and join at their start frame.

    Exact with respect to tracking them from the beginning as long as no window containing
    their start frame has been decoded yet (untracked points influence nothing).
    """
    fresh = start_state(model, queries, state.num_frames, state.initial_content.dtype)
    state.queries = QuerySet(
        *(torch.cat(pair, dim=1) for pair in zip(state.queries, queries, strict=True))
    )
    state.initial_content = torch.cat((state.initial_content, fresh.initial_content), dim=1)
    state.initialised = torch.cat((state.initialised, fresh.initialised), dim=1)
    state.content.add_points(fresh.content.future)
    for mine, new in zip(
        state.positions + state.visibility + state.updated_positions,
        fresh.positions + fresh.visibility + fresh.updated_positions,
        strict=True,
    ):
        mine.add_points(new.future)


def keep_points(state: TrackerState, keep: Tensor) -> None:
    """Drops the points not selected by the (N,) bool mask from a running state."""
    state.queries = QuerySet(*(q[:, keep] for q in state.queries))
    state.initial_content = state.initial_content[:, keep]
    state.initialised = state.initialised[:, keep]
    for trajectory in [
        state.content,
        *state.positions,
        *state.visibility,
        *state.updated_positions,
    ]:
        trajectory.keep_points(keep)


def _initialise_points(
    model: TAPTR,
    state: TrackerState,
    memory: Tensor,
    spatial_shapes: list[tuple[int, int]],
    first: int,
    clamp_starts: bool = False,
) -> None:
    """Builds the content of points whose start frame lies in the window.

    With ``clamp_starts`` (TAPTR v1's memory-efficient mode, on the first window), every
    point is initialised from frame min(start, last frame of the window) instead.
    """
    starts = state.queries.start_frames
    if clamp_starts:
        starts = starts.clamp(max=first + memory.shape[1] - 1)
    new = (~state.initialised) & (starts >= first) & (starts < first + memory.shape[1])
    if not bool(new.any()):
        return
    samples = None
    for offset in range(memory.shape[1]):
        here = new & (starts == first + offset)
        if bool(here.any()):
            frame_samples = model.query_init.sample(
                memory[:, offset], spatial_shapes, state.queries.positions
            )
            samples = (
                frame_samples
                if samples is None
                else torch.where(here[..., None], frame_samples, samples)
            )
    assert samples is not None
    content = model.query_init.project(samples)  # (B, N, C)
    state.initial_content = torch.where(new[..., None], content, state.initial_content)
    state.initialised = state.initialised | new
    state.content.fill(new, content)


def decode_window(
    model: TAPTR,
    state: TrackerState,
    first: int,
    last: int,
    frames_source: FrameSource,
) -> None:
    """Decodes frames first..last and updates ``state`` in place.

    Args:
        model: the network.
        state: the driver state; ``state.next_window`` is the index of this window.
        first: first frame of the window.
        last: last frame of the window (inclusive).
        frames_source: gives the memory (B, W_t, S, C) of frames first..last; not called
            when the window is skipped.
    """
    index = state.next_window
    state.next_window += 1
    if model.memory_efficient and not model.training and index == 0:
        # v1's memory-efficient mode initialises every query from the first 8 frames only
        _initialise_points(model, state, *frames_source(first, last), first, clamp_starts=True)
    frames = torch.arange(first, last + 1, device=state.queries.start_frames.device)
    starts = state.queries.start_frames[:, None, :]  # (B, 1, N)
    tracking = frames[None, :, None] >= starts  # (B, W_t, N)
    update = frames[None, :, None] > starts
    if not bool(update.any()):
        return  # the official code skips such windows entirely, padding included

    memory, spatial_shapes = frames_source(first, last)
    _initialise_points(model, state, memory, spatial_shapes, first)
    content = state.content.read(first, last)
    decoded = model.decode_window(
        memory, spatial_shapes, content, state.positions[-1].read(first, last), tracking, update
    )
    for layer in range(model.num_layers):
        state.positions[layer].write(first, decoded.positions[layer], update)
        state.visibility[layer].write(first, decoded.visibility_logits[layer].float(), update)
        state.positions[layer].pad_from(last)
        state.visibility[layer].pad_from(last)
        if decoded.updated_positions is not None:
            state.updated_positions[layer].write(first, decoded.updated_positions[layer], update)
            state.updated_positions[layer].pad_from(last)

    initial = state.initial_content[:, None].expand_as(content)
    new_content = model.update_content(initial, content, decoded.features, update)
    state.content.write(first, new_content, torch.ones_like(update))
    gap = content_padding_gap(state.num_frames, model.long_video_frames, model.training)
    if index % gap == 0:
        state.content.pad_from(last)


def finish(state: TrackerState, num_frames: int) -> TrackOutput:
    """Stacks the trajectories of frames 0..T−1 (requires that none was released)."""

    def stack(trajectories: list[Trajectory]) -> Tensor:
        return torch.stack([t.read(0, num_frames - 1) for t in trajectories])  # (D_l, B, T, N, D)

    positions = stack(state.positions)
    visibility = stack(state.visibility)
    updated = stack(state.updated_positions) if state.updated_positions else None
    return TrackOutput(
        positions[-1, ..., :2].sigmoid(), visibility[-1], positions, visibility, updated
    )


def run_windows(
    model: TAPTR,
    queries: QuerySet,
    num_frames: int,
    frames: FrameSource,
    dtype: torch.dtype,
    on_window: Callable[[], object] | None = None,
) -> TrackOutput:
    """Tracks the queries through a whole video, window by window.

    Args:
        model: the network.
        queries: points in model units.
        num_frames: video length T.
        frames: source of encoded frames for each window.
        dtype: floating dtype of the positions and content.
        on_window: called after each window (progress reporting).
    """
    state = start_state(model, queries, num_frames, dtype)
    ranges = window_ranges(num_frames, model.window_size, model.window_stride)
    for (first, last), following in zip(
        ranges, ranges[1:] + [(num_frames, num_frames)], strict=True
    ):
        decode_window(model, state, first, last, frames)
        state.content.release(before=following[0])  # content of earlier frames is never read again
        if on_window is not None:
            on_window()
    return finish(state, num_frames)
