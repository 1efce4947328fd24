"""TAPTRv3's driver: decodes a video frame by frame, each frame once, in order.

For every frame f, as the official streaming evaluation does:

1. the frame's slot is opened in the history (`taptr.model.v3.history`);
2. points starting on f take their content and context from f's memory, and every
   frame they hold is set to that content;
3. if no point is past its start frame, f is skipped: nothing is decoded or written;
4. otherwise the decoder runs on f: initial content, the position carried from f − 1,
   the held frames with their weights (`taptr.model.v3.decoder`);
5. write-back: each layer's position (and position-update output) replaces the carried
   one where the point was updated and is carried to the next frame; visibility logits
   are reported for f only; the last layer's head features become f's held content.

Points not yet started are carried at their query position, with the initial visibility
logits (visible on their start frame, occluded elsewhere, in inverse-sigmoid form): what
the official outputs hold on frames the model never writes.

All of it goes through an explicit `FrameState`; `decode_frame` returns each frame's
outputs as soon as it is decoded (one frame of latency), and `run_frames` stacks them for
a whole video. Encoded frames come from a `taptr.model.frame_source.FrameSource` asked
for one frame at a time.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import torch
from torch import Tensor, nn

from taptr.geometry import inverse_sigmoid
from taptr.model.decoder import DecoderOutput
from taptr.model.frame_source import FrameFeatures, FrameSource
from taptr.model.ops.constants import kept
from taptr.model.trajectory import QuerySet, TrackOutput, distinct_starts, joined_starts
from taptr.model.v3.decoder import HeldFrames
from taptr.model.v3.history import History, frame_weights
from taptr.model.v3.taptr import TAPTRv3


class FrameOutput(NamedTuple):
    """Every point's outputs on one frame, per decoder layer.

    Attributes:
        frame: the frame.
        positions: (D_l, B, N, 4) position logits.
        visibility_logits: (D_l, B, N, 3) (channel 1 = visible).
        updated_positions: (D_l, B, N, 4) position-update outputs (logits).
    """

    frame: int
    positions: Tensor
    visibility_logits: Tensor
    updated_positions: Tensor


class DecoderStep(Protocol):
    """Runs ``model.decoder`` on a frame, called with its arguments.

    The module as it is (`ModuleStep`), or a step captured for replay
    (`taptr.runtime.step_capture`).
    """

    @property
    def static_shapes(self) -> bool:
        """Whether the next call needs the decoder's shapes to stay fixed from frame to frame.

        So does a compiled or captured step; the history is then read as its whole buffer
        (`held_frames`).
        """
        ...

    def __call__(self, *args: Any) -> DecoderOutput:
        """The decoder's outputs on one frame (the arguments of ``V3Decoder.forward``)."""
        ...


@dataclass(frozen=True)
class ModuleStep:
    """The model's own decoder as the step of every frame.

    Attributes:
        decoder: ``model.decoder``, eager or compiled in place.
        asked_static: read the whole history buffer even when the decoder is eager.
    """

    decoder: nn.Module
    asked_static: bool = False

    @property
    def static_shapes(self) -> bool:
        """As asked, and always for a compiled decoder (`compiled`)."""
        return self.asked_static or compiled(self.decoder)

    def __call__(self, *args: Any) -> DecoderOutput:
        """The decoder's outputs on one frame (the arguments of ``V3Decoder.forward``)."""
        return self.decoder(*args)


@dataclass
class FrameState:
    """Everything the next frame needs; no other state exists anywhere.

    Attributes:
        queries: the points, in model units.
        initial_content: (B, N, C) each point's initial content (zeros until it starts).
        context: (B, N, K, K, C) its initial context, or None without the context-aware
            attention.
        initialised: (B, N) bool, whether the point has started.
        positions: per layer, the (B, N, 4) logits carried to the next frame.
        updated_positions: per layer, the (B, N, 4) position-update logits carried.
        history: the points' held frames.
        start_frames: the points' distinct start frames, in order, on the host: which
            frames start points, whether any point is past its start and whether all
            are tracked are decided without asking the device (a step that waits for
            nothing can be captured and replayed).
        step: what runs the decoder on a frame, and whether its shapes must stay the
            same from frame to frame (`DecoderStep.static_shapes`).
        next_frame: the frame to decode next.
    """

    queries: QuerySet
    initial_content: Tensor
    context: Tensor | None
    initialised: Tensor
    positions: list[Tensor]
    updated_positions: list[Tensor]
    history: History
    step: DecoderStep
    start_frames: tuple[int, ...] = ()
    next_frame: int = 0


def compiled(module: nn.Module) -> bool:
    """Whether ``module`` runs through ``torch.compile`` (``module.compile()`` or wrapped).

    Such a decoder needs static shapes (`DecoderStep.static_shapes`): it would otherwise
    be traced again for every history length.
    """
    # torch.compile(module) wraps it (the original as ``_orig_mod``); module.compile()
    # sets ``_compiled_call_impl``; looking for either imports nothing of dynamo
    wrapped = getattr(module, "_orig_mod", None) is not None
    return wrapped or getattr(module, "_compiled_call_impl", None) is not None


def query_logits(queries: QuerySet, dtype: torch.dtype) -> Tensor:
    """(B, N, 4) start positions (logit x, logit y, 0, 0): w = h = 0.5, as the official code."""
    xy = inverse_sigmoid(queries.positions.to(dtype))
    return torch.cat((xy, xy.new_zeros(*xy.shape[:-1], 2)), dim=-1)


def initial_visibility(model: TAPTRv3, queries: QuerySet, frame: int) -> Tensor:
    """(B, N, 3) float32 logits of frames the model does not write.

    With visibility weights: visible on the point's start frame and occluded elsewhere,
    whatever the start label; without (the ablation): the start label on every frame.
    Both as inverse_sigmoid(one-hot), ±6.9078.
    """
    visible = queries.start_frames == frame if model.visibility_weights else queries.start_visible
    table = kept(  # (2, 3): the logits of "visible" and of "occluded"
        ("initial visibility", visible.device),
        lambda: inverse_sigmoid(torch.eye(3, device=visible.device)[1:]),
    )
    return torch.where(visible[..., None], table[0], table[1])


def start_state(
    model: TAPTRv3,
    queries: QuerySet,
    dtype: torch.dtype,
    history_frames: int | None = None,
    static_shapes: bool = False,
    step: DecoderStep | None = None,
) -> FrameState:
    """The state before the first frame.

    Args:
        model: the network.
        queries: the points, in model units.
        dtype: floating dtype of positions and content.
        history_frames: the most frames held per point (0: all); default the model's.
        static_shapes: without a ``step``, read the history's whole buffer on every frame
            (`ModuleStep`); always so when the decoder is compiled (``nn.Module.compile``,
            `taptr.runtime.compile.compile_model`), which would otherwise trace it again for every
            history length.
        step: `FrameState.step`; None: the model's decoder (`ModuleStep`).

    Raises:
        ValueError: ``static_shapes`` beside a ``step``, which decides its own.
    """
    if step is None:
        step = ModuleStep(model.decoder, static_shapes)
    elif static_shapes:
        raise ValueError("a decoder step decides its own static shapes")
    batch, points = queries.start_frames.shape
    channels = model.content_channels
    like = queries.positions.new_zeros(1, dtype=dtype)
    limit = model.history_frames if history_frames is None else history_frames
    history = History(batch, channels, limit, like)
    history.add_points(points)
    logits = query_logits(queries, dtype)
    patch = model.context_patch
    return FrameState(
        queries=queries,
        initial_content=like.new_zeros(batch, points, channels),
        context=like.new_zeros(batch, points, patch, patch, channels) if patch else None,
        initialised=torch.zeros(batch, points, dtype=torch.bool, device=like.device),
        positions=[logits] * model.num_layers,
        updated_positions=[logits] * model.num_layers,
        history=history,
        step=step,
        start_frames=distinct_starts(queries),
    )


def add_points(model: TAPTRv3, state: FrameState, queries: QuerySet) -> None:
    """Appends points to a running state; they join at their start frame.

    Exact with respect to tracking them from the beginning as long as their start frame
    is not decoded yet (a point influences nothing before it starts).
    """
    fresh = start_state(model, queries, state.initial_content.dtype, state.history.limit)
    state.queries = QuerySet(
        *(torch.cat(pair, dim=1) for pair in zip(state.queries, queries, strict=True))
    )
    state.initial_content = torch.cat((state.initial_content, fresh.initial_content), dim=1)
    if state.context is not None and fresh.context is not None:
        state.context = torch.cat((state.context, fresh.context), dim=1)
    state.initialised = torch.cat((state.initialised, fresh.initialised), dim=1)
    state.positions = [torch.cat(p, 1) for p in zip(state.positions, fresh.positions, strict=True)]
    state.updated_positions = [
        torch.cat(p, 1) for p in zip(state.updated_positions, fresh.updated_positions, strict=True)
    ]
    state.history.add_points(queries.start_frames.shape[1])
    state.start_frames = joined_starts(state.start_frames, fresh.start_frames)


def keep_points(state: FrameState, keep: Tensor) -> None:
    """Drops the points not selected by the (N,) bool mask from a running state."""
    state.queries = QuerySet(*(q[:, keep] for q in state.queries))
    state.initial_content = state.initial_content[:, keep]
    if state.context is not None:
        state.context = state.context[:, keep]
    state.initialised = state.initialised[:, keep]
    state.positions = [p[:, keep] for p in state.positions]
    state.updated_positions = [p[:, keep] for p in state.updated_positions]
    state.history.keep_points(keep)
    state.start_frames = distinct_starts(state.queries)


def start_points(model: TAPTRv3, state: FrameState, features: FrameFeatures, frame: int) -> None:
    """Step 2: content and context of the points starting on ``frame``, (B, 1, S, C) memory."""
    new = (~state.initialised) & (state.queries.start_frames == frame)
    memory, spatial_shapes = features
    content, context = model.point_queries(memory[:, 0], spatial_shapes, state.queries.positions)
    state.initial_content = torch.where(new[..., None], content, state.initial_content)
    if state.context is not None and context is not None:
        state.context = torch.where(new[..., None, None, None], context, state.context)
    state.initialised = state.initialised | new
    state.history.restart(new, state.initial_content)


def decode_frame(model: TAPTRv3, state: FrameState, frames: FrameSource) -> FrameOutput:
    """Decodes the next frame and updates ``state`` in place (steps 1-5).

    Args:
        model: the network.
        state: the driver state; ``state.next_frame`` is decoded.
        frames: gives the memory (B, 1, S, C) of one frame; not called when no point
            starts on the frame or is past its start.

    Returns:
        Every point's outputs on the frame.
    """
    frame = state.next_frame
    state.next_frame += 1
    starts = state.queries.start_frames
    unwritten = initial_visibility(model, state.queries, frame)
    state.history.open_frame(frame, state.initial_content, unwritten[..., 1])
    features = None
    if frame in state.start_frames:
        features = frames(frame, frame)
        start_points(model, state, features, frame)
    update = starts < frame  # (B, N)
    if not state.start_frames or state.start_frames[0] >= frame:  # no point past its start
        return _carried(model, state, frame, unwritten)
    if features is None:
        features = frames(frame, frame)
    memory, spatial_shapes = features
    held = held_frames(model, state, frame)
    decoded = state.step(
        *model.decoder_inputs(
            memory[:, 0],
            spatial_shapes,
            state.initial_content[:, None],
            state.positions[-1][:, None],
            (starts <= frame)[:, None],
            update[:, None],
            held,
            state.context,
            all_tracked=state.start_frames[-1] <= frame,
        )
    )
    step = update[..., None]
    state.positions = [
        torch.where(step, p[:, 0], old)
        for p, old in zip(decoded.positions, state.positions, strict=True)
    ]
    assert decoded.updated_positions is not None
    state.updated_positions = [
        torch.where(step, p[:, 0], old)
        for p, old in zip(decoded.updated_positions, state.updated_positions, strict=True)
    ]
    visibility = torch.where(step, decoded.visibility_logits[:, :, 0].float(), unwritten)
    state.history.close_frame(decoded.features[:, 0], visibility[-1, ..., 1], update)
    return FrameOutput(
        frame, torch.stack(state.positions), visibility, torch.stack(state.updated_positions)
    )


def held_frames(model: TAPTRv3, state: FrameState, frame: int) -> HeldFrames:
    """What the long-temporal attention reads on ``frame``: the held frames, or the buffer.

    With static shapes (`DecoderStep.static_shapes`) every slot of the history's buffer is
    read, those that hold no frame left out of the softmax (`HeldFrames.outside`) and
    weighted zero: the shapes then change only when the buffer grows (by doubling), so a
    compiled or captured step is reused from frame to frame. The result is the same up to
    float rounding.
    """
    history, starts = state.history, state.queries.start_frames
    if not state.step.static_shapes:
        frames = history.frames()  # (H,)
        weights = frame_weights(frames, starts, history.visibility_logits, model.visibility_weights)
        return HeldFrames(history.content, frame - frames, weights)
    frames = history.slot_frames()  # (capacity,)
    outside = (frames < history.first) | (frames > frame)  # (capacity,)
    return buffer_held(
        model,
        frames,
        outside,
        frame,
        starts,
        history.slot_content,
        history.slot_visibility_logits,
    )


def buffer_held(
    model: TAPTRv3,
    slot_frames: Tensor,
    outside: Tensor,
    frame: int | Tensor,
    start_frames: Tensor,
    slot_content: Tensor,
    slot_visibility_logits: Tensor,
) -> HeldFrames:
    """What the long-temporal attention reads from a whole history buffer on ``frame``.

    Shared by the static step and the exported one (`taptr.export.v3_modules`), whose
    buffer is an input.

    Args:
        model: the network (whether it weighs frames by visibility).
        slot_frames: (capacity,) int64 frame each buffer slot holds or would hold.
        outside: (capacity,) bool, slots that hold no frame read on ``frame``.
        frame: the frame being decoded (an int, or a 0-d int64 tensor in a graph).
        start_frames: (B, N) each point's start frame.
        slot_content: (B, N, capacity, C) the buffer's content.
        slot_visibility_logits: (B, N, capacity) float32 last-layer logits of the slots.
    """
    weights = frame_weights(
        slot_frames, start_frames, slot_visibility_logits, model.visibility_weights
    )
    weights = weights & ~outside if weights.dtype == torch.bool else weights.masked_fill(outside, 0)
    return HeldFrames(slot_content, frame - slot_frames, weights, outside)


def _carried(model: TAPTRv3, state: FrameState, frame: int, unwritten: Tensor) -> FrameOutput:
    """A skipped frame's outputs: carried positions, unwritten visibility."""
    layers = model.num_layers
    return FrameOutput(
        frame,
        torch.stack(state.positions),
        unwritten.expand(layers, *unwritten.shape),
        torch.stack(state.updated_positions),
    )


def stack_outputs(outputs: list[FrameOutput]) -> TrackOutput:
    """Frame outputs of frames 0..T−1, in order, as one `TrackOutput` (B, T, ...)."""
    positions = torch.stack([o.positions for o in outputs], dim=2)  # (D_l, B, T, N, 4)
    visibility = torch.stack([o.visibility_logits for o in outputs], dim=2)
    updated = torch.stack([o.updated_positions for o in outputs], dim=2)
    return TrackOutput(
        positions[-1, ..., :2].sigmoid(), visibility[-1], positions, visibility, updated
    )


def run_frames(
    model: TAPTRv3,
    queries: QuerySet,
    num_frames: int,
    frames: FrameSource,
    dtype: torch.dtype,
    on_frame: Callable[[], object] | None = None,
    history_frames: int | None = None,
    static_shapes: bool = False,
    step: DecoderStep | None = None,
) -> TrackOutput:
    """Tracks the queries through a whole video, frame by frame.

    Args:
        model: the network.
        queries: points in model units.
        num_frames: video length T.
        frames: source of encoded frames.
        dtype: floating dtype of the positions and content.
        on_frame: called after each frame (progress reporting).
        history_frames: the most frames held per point (0: all); default the model's.
        static_shapes: `start_state`'s.
        step: `FrameState.step`.
    """
    state = start_state(model, queries, dtype, history_frames, static_shapes, step)
    outputs = []
    for _ in range(num_frames):
        outputs.append(decode_frame(model, state, frames))
        if on_frame is not None:
            on_frame()
    return stack_outputs(outputs)
