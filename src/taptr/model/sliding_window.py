"""The sliding-window driver: the one place that loops over windows.

Windows of ``window_size`` frames start every ``window_stride`` frames; the last one is
shifted back to end on the last frame, and a video shorter than one window is one window.
For each window the driver initialises the points that start inside it, decodes, writes
the results back where the update mask allows, hands the content over to the next window,
and copies the state of the window's last frame to all later frames.

All of it goes through an explicit `TrackerState`, which only holds what later windows can
still read: the trajectory of every frame from the current window on, plus one shared
value for all frames not yet reached. Encoded frames are requested from a `FrameSource`
window by window (`taptr.model.frame_source`), so memory is bounded by the window, not the
video.

The network itself is reached through a `WindowNetwork`: the PyTorch `TAPTR` module (as
`TorchNetwork`, which every function here applies to a `TAPTR` it is given) or the exported
graphs (`taptr.export.graph_runner.GraphNetwork`), so both run exactly these rules.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple, Protocol

import torch
import torch.nn.functional as F
from torch import Tensor

from taptr.geometry import inverse_sigmoid
from taptr.model.frame_source import FrameFeatures, FrameSource
from taptr.model.frame_tables import FrameTables
from taptr.model.taptr import TAPTR
from taptr.model.trajectory import (
    QuerySet,
    TrackerState,
    TrackOutput,
    Trajectory,
    distinct_starts,
    finish,
    joined_starts,
)
from taptr.model.trajectory import keep_points as keep_points  # part of the driver's API
from taptr.model.v1.memory_efficient import first_window_content_frames
from taptr.windows import content_padding_gap, window_ranges


class WindowDecoding(NamedTuple):
    """One decoded window, before the write-back masks.

    Attributes:
        positions: (D_l, B, W_t, N, 4) position logits after each layer the network reports.
        visibility_logits: (D_l, B, W_t, N, 3) (channel 1 = visible).
        updated_positions: (D_l, B, W_t, N, 4) APU-updated logits, or None.
        next_content: (B, W_t, N, C) content handed to the next window.
    """

    positions: Tensor
    visibility_logits: Tensor
    updated_positions: Tensor | None
    next_content: Tensor


class WindowNetwork(Protocol):
    """What the driver asks of whatever runs the network.

    Point content is built in two steps so that samples from several start frames can be
    merged before one projection (``project_samples`` acts row by row); a network that
    cannot split them returns the content from ``sample_points`` and projects with the
    identity. Decoding and the content hand-over are one step, given the initial content,
    because the exported decoder graph computes both in one call.

    Attributes:
        window_size: frames per window.
        window_stride: frames between window starts.
        long_video_frames: above this length the content is handed over less often.
        memory_efficient: TAPTR v1's memory-efficient initialisation
            (`taptr.model.v1.memory_efficient`).
        training: training mode (content handed over after every window).
        num_layers: D_l, the decoder layers whose results ``decode_window`` returns.
        has_position_update: whether ``decode_window`` returns APU-updated positions.
        content_channels: C, channels of the point content.
    """

    window_size: int
    window_stride: int
    long_video_frames: int
    memory_efficient: bool
    training: bool
    num_layers: int
    has_position_update: bool
    content_channels: int

    def sample_points(
        self, memory: Tensor, spatial_shapes: list[tuple[int, int]], positions: Tensor
    ) -> Tensor:
        """One frame's memory (B, S, C) at normalised (x, y) positions (B, N, 2) → (B, N, K)."""
        ...

    def project_samples(self, samples: Tensor) -> Tensor:
        """Samples (B, N, K) → initial content (B, N, C)."""
        ...

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
        """Decodes one window and computes the content handed to the next one.

        Args:
            memory: (B, W_t, S, C) encoder memory of the window's frames.
            spatial_shapes: (H_l, W_l) per level.
            content: (B, W_t, N, C) content at window entry.
            positions: (B, W_t, N, 4) last layer's position logits at window entry.
            initial: (B, N, C) each point's initial content (zeros before it starts).
            tracking: (B, W_t, N) bool, entries at or after each point's start frame.
            update: (B, W_t, N) bool, tracking entries after the start frame.
            tables: the run's store of per-frame key and value tables, started for this
                window (`taptr.model.frame_tables`); a network may ignore it.
            all_tracked: every entry of ``tracking`` is set, as the host knows without
                asking the device; None to read it. A network may ignore it.
        """
        ...


class TorchNetwork:
    """`WindowNetwork` over the PyTorch `TAPTR` module, through its public methods.

    Its facts are read when it is made; the driver makes one per call.
    """

    def __init__(self, model: TAPTR) -> None:
        if model.window_updater is None:
            raise TypeError(
                "TAPTRv3 decodes frame by frame: run it with taptr.model.v3.per_frame, not "
                "the sliding-window driver"
            )
        self.model = model
        self.window_size = model.window_size
        self.window_stride = model.window_stride
        self.long_video_frames = model.long_video_frames
        self.memory_efficient = model.memory_efficient
        self.training = model.training
        self.num_layers = model.num_layers
        self.has_position_update = model.decoder.has_position_update
        self.content_channels = model.query_init.project.out_features

    def sample_points(
        self, memory: Tensor, spatial_shapes: list[tuple[int, int]], positions: Tensor
    ) -> Tensor:
        """Per-level bilinear samples, (B, S, C) and (B, N, 2) → (B, N, L·C)."""
        return self.model.query_init.sample(memory, spatial_shapes, positions)

    def project_samples(self, samples: Tensor) -> Tensor:
        """The query initialiser's projection, (B, N, L·C) → (B, N, C)."""
        return self.model.query_init.project(samples)

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
        """`TAPTR.decode_window` then `TAPTR.update_content` (as `WindowNetwork`)."""
        decoded = self.model.decode_window(
            memory, spatial_shapes, content, positions, tracking, update, tables, all_tracked
        )
        initial = initial[:, None].expand_as(content)  # (B, W_t, N, C)
        next_content = self.model.update_content(initial, content, decoded.features, update)
        return WindowDecoding(
            decoded.positions, decoded.visibility_logits, decoded.updated_positions, next_content
        )


def as_network(model: TAPTR | WindowNetwork) -> WindowNetwork:
    """The network of ``model``: a `TorchNetwork` around a `TAPTR`, any other as it is."""
    return TorchNetwork(model) if isinstance(model, TAPTR) else model


def start_state(
    model: TAPTR | WindowNetwork, queries: QuerySet, num_frames: int | None, dtype: torch.dtype
) -> TrackerState:
    """The state before the first window: every point at its query, visibility one-hot."""
    network = as_network(model)
    batch, points = queries.start_frames.shape
    channels = network.content_channels
    device = queries.positions.device
    xy_logit = inverse_sigmoid(queries.positions.to(dtype))
    position = torch.cat((xy_logit, xy_logit.new_zeros(batch, points, 2)), dim=-1)  # (B, N, 4)
    one_hot = F.one_hot(torch.where(queries.start_visible, 1, 2), 3).to(torch.float32)
    layers = network.num_layers
    return TrackerState(
        queries=queries,
        num_frames=num_frames,
        initial_content=torch.zeros(batch, points, channels, dtype=dtype, device=device),
        initialised=torch.zeros(batch, points, dtype=torch.bool, device=device),
        content=Trajectory(torch.zeros(batch, points, channels, dtype=dtype, device=device)),
        positions=[Trajectory(position) for _ in range(layers)],
        visibility=[Trajectory(one_hot) for _ in range(layers)],
        updated_positions=(
            [Trajectory(position) for _ in range(layers)] if network.has_position_update else []
        ),
        start_frames=distinct_starts(queries),
    )


def add_points(model: TAPTR | WindowNetwork, state: TrackerState, queries: QuerySet) -> None:
    """Appends points to a running state; they start untracked and join at their start frame.

    Exact with respect to tracking them from the beginning as long as no window containing
    their start frame has been decoded yet (untracked points influence nothing).
    """
    fresh = start_state(model, queries, state.num_frames, state.initial_content.dtype)
    state.queries = QuerySet(
        *(torch.cat(pair, dim=1) for pair in zip(state.queries, queries, strict=True))
    )
    state.start_frames = joined_starts(state.start_frames, fresh.start_frames)
    # the new points' start frames are asked for again (the device mask keeps earlier
    # points' content where a start frame is shared)
    state.initialised_starts = state.initialised_starts - set(fresh.start_frames)
    state.initial_content = torch.cat((state.initial_content, fresh.initial_content), dim=1)
    state.initialised = torch.cat((state.initialised, fresh.initialised), dim=1)
    state.content.add_points(fresh.content.future)
    for mine, new in zip(
        state.positions + state.visibility + state.updated_positions,
        fresh.positions + fresh.visibility + fresh.updated_positions,
        strict=True,
    ):
        mine.add_points(new.future)


def initialise_points(
    network: WindowNetwork,
    state: TrackerState,
    features: FrameFeatures,
    first: int,
    content_frames: Tensor | None = None,
) -> None:
    """Builds the content of points not yet initialised whose content frame is in the window.

    Args:
        network: runs the query initialiser.
        state: the driver state (updated in place).
        features: memory (B, W_t, S, C) of the window's frames.
        first: first frame of the window.
        content_frames: (B, N) frame each point takes its content from; default its start
            frame (TAPTR v1's memory-efficient mode passes others).
    """
    memory, spatial_shapes = features
    count = memory.shape[1]
    starts = state.queries.start_frames if content_frames is None else content_frames
    new = (~state.initialised) & (starts >= first) & (starts < first + count)
    if content_frames is None:  # the host knows which start frames may have new points
        frames = {f for f in state.start_frames if first <= f < first + count}
        frames -= state.initialised_starts
        state.initialised_starts |= frames
    else:  # TAPTR v1's memory-efficient mode: content frames the host does not hold
        frames = set(torch.unique(starts[new]).tolist())
    if not frames:
        return
    samples = None
    for offset in range(count):
        here = new & (starts == first + offset)
        if first + offset in frames:
            frame_samples = network.sample_points(
                memory[:, offset], spatial_shapes, state.queries.positions
            )
            samples = (
                frame_samples
                if samples is None
                else torch.where(here[..., None], frame_samples, samples)
            )
    assert samples is not None
    content = network.project_samples(samples)  # (B, N, C)
    state.initial_content = torch.where(new[..., None], content, state.initial_content)
    state.initialised = state.initialised | new
    state.content.fill(new, content)


def decode_window(
    model: TAPTR | WindowNetwork,
    state: TrackerState,
    first: int,
    last: int,
    frames_source: FrameSource,
    next_first: int | None = None,
) -> None:
    """Decodes frames first..last and updates ``state`` in place.

    Args:
        model: the PyTorch network, or another `WindowNetwork` (exported graphs).
        state: the driver state; ``state.next_window`` is the index of this window.
        first: first frame of the window.
        last: last frame of the window (inclusive).
        frames_source: gives the memory (B, W_t, S, C) of frames first..last; not called
            when the window is skipped.
        next_first: the first frame of the next window, or past ``last`` when there is
            none, where the caller knows it (a video of known length): the key and value
            tables of the frames from there on are kept for it. None (a stream) assumes
            the next window starts a stride later.
    """
    network = as_network(model)
    index = state.next_window
    state.next_window += 1
    content_frames = first_window_content_frames(
        network.memory_efficient, network.training, index, last, state.queries.start_frames
    )
    if content_frames is not None:  # TAPTR v1's memory-efficient mode
        initialise_points(network, state, frames_source(first, last), first, content_frames)
    frames = torch.arange(first, last + 1, device=state.queries.start_frames.device)
    starts = state.queries.start_frames[:, None, :]  # (B, 1, N)
    tracking = frames[None, :, None] >= starts  # (B, W_t, N)
    update = frames[None, :, None] > starts
    if not state.start_frames or state.start_frames[0] >= last:  # no point past its start
        return  # the official code skips such windows entirely, padding included

    memory, spatial_shapes = frames_source(first, last)
    initialise_points(network, state, FrameFeatures(memory, spatial_shapes), first)
    content = state.content.read(first, last)
    # without a known next window, the next one normally starts a stride later
    keep_from = first + network.window_stride if next_first is None else next_first
    state.tables.start_window(first, last, keep_from=keep_from if keep_from <= last else None)
    decoded = network.decode_window(
        memory,
        spatial_shapes,
        content,
        state.positions[-1].read(first, last),
        state.initial_content,
        tracking,
        update,
        state.tables,
        all_tracked=state.start_frames[-1] <= first,
    )
    for layer in range(network.num_layers):
        state.positions[layer].write(first, decoded.positions[layer], update)
        state.visibility[layer].write(first, decoded.visibility_logits[layer].float(), update)
        state.positions[layer].pad_from(last)
        state.visibility[layer].pad_from(last)
        if decoded.updated_positions is not None:
            state.updated_positions[layer].write(first, decoded.updated_positions[layer], update)
            state.updated_positions[layer].pad_from(last)

    state.content.write(first, decoded.next_content, torch.ones_like(update))
    gap = content_padding_gap(state.num_frames, network.long_video_frames, network.training)
    if index % gap == 0:
        state.content.pad_from(last)


def run_windows(
    model: TAPTR | WindowNetwork,
    queries: QuerySet,
    num_frames: int,
    frames: FrameSource,
    dtype: torch.dtype,
    on_window: Callable[[], object] | None = None,
) -> TrackOutput:
    """Tracks the queries through a whole video, window by window.

    Args:
        model: the PyTorch network, or another `WindowNetwork` (exported graphs).
        queries: points in model units.
        num_frames: video length T.
        frames: source of encoded frames for each window.
        dtype: floating dtype of the positions and content.
        on_window: called after each window (progress reporting).
    """
    network = as_network(model)
    state = start_state(network, queries, num_frames, dtype)
    ranges = window_ranges(num_frames, network.window_size, network.window_stride)
    for (first, last), following in zip(
        ranges, ranges[1:] + [(num_frames, num_frames)], strict=True
    ):
        decode_window(network, state, first, last, frames, next_first=following[0])
        state.content.release(before=following[0])  # content of earlier frames is never read again
        if on_window is not None:
            on_window()
    return finish(state, num_frames)
