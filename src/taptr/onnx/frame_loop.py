"""TAPTRv3's frame loop over the exported graphs, in numpy: the rules of docs/EXPORT.md.

For every frame f, in order, as the PyTorch driver (`taptr.model.v3.per_frame`) does:

1. each point's logits on f before decoding ("unwritten"): the manifest's visible
   logits on its start frame and occluded ones elsewhere (or its start label on every
   frame, for a model without visibility weights);
2. f is opened in the history (`taptr.onnx.ring_history`) with each point's initial
   content and its unwritten logit (channel 1);
3. points starting on f: ``start_points`` on f's memory gives their initial content and
   context, and every frame they hold is set to that content;
4. if no point is past its start frame, f is skipped: the carried positions and the
   unwritten logits are its outputs;
5. otherwise ``decode_step`` returns the new carried positions, f's logits and the
   features f's slot then holds, with the logit (channel 1).

Everything lives in an explicit `LoopState`; points join (`add_points`) before their
start frame is decoded and leave (`keep_points`) at any time. `track_points` runs a whole
video in model units.

Shapes: N points, C channels, S memory tokens, K context side, T frames.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from taptr.onnx.graph_engines import StepGraphs
from taptr.onnx.ring_history import RingHistory
from taptr.onnx.v3_manifest import V3Manifest
from taptr.task.results import TrackArrays


@dataclass
class LoopState:
    """Everything the next frame needs, per point.

    Attributes:
        start_frames: (N,) int64.
        query_positions: (N, 2) float32 normalised (x, y) on the start frame.
        start_visible: (N,) bool start labels (read without visibility weights only).
        initial_content: (N, C) float32 (zeros until the point starts).
        context: (N, K, K, C) float32, or None for a model without contexts.
        initialised: (N,) bool, whether the point has started.
        positions: (N, 4) float32 position logits carried to the next frame.
        history: the held frames.
        next_frame: the frame to decode next.
    """

    start_frames: np.ndarray
    query_positions: np.ndarray
    start_visible: np.ndarray
    initial_content: np.ndarray
    context: np.ndarray | None
    initialised: np.ndarray
    positions: np.ndarray
    history: RingHistory
    next_frame: int = 0


class FrameResult(NamedTuple):
    """Every point's outputs on one frame.

    Attributes:
        positions: (N, 2) float32 normalised (x, y).
        visibility_logits: (N, 3) float32 (channel 1 = visible).
    """

    positions: np.ndarray
    visibility_logits: np.ndarray


def start_state(manifest: V3Manifest, history_frames: int | None = None) -> LoopState:
    """The state of a loop with no points, before its first frame.

    Args:
        manifest: the export's description.
        history_frames: the most frames held per point (0: all); default the manifest's.
    """
    channels, patch = manifest.d_model, manifest.context_patch
    limit = manifest.history_frames if history_frames is None else history_frames
    return LoopState(
        start_frames=np.zeros(0, np.int64),
        query_positions=np.zeros((0, 2), np.float32),
        start_visible=np.zeros(0, bool),
        initial_content=np.zeros((0, channels), np.float32),
        context=np.zeros((0, patch, patch, channels), np.float32) if patch else None,
        initialised=np.zeros(0, bool),
        positions=np.zeros((0, 4), np.float32),
        history=RingHistory(channels, limit),
    )


def position_logits(positions: np.ndarray, eps: float) -> np.ndarray:
    """(N, 2) normalised positions → (N, 4) logits (x, y, 0, 0), clamped as the model does."""
    x = np.clip(positions.astype(np.float32), 0, 1)
    low = np.float32(eps)
    xy = np.log(np.maximum(x, low) / np.maximum(1 - x, low))
    return np.concatenate((xy, np.zeros_like(xy)), axis=1).astype(np.float32)


def add_points(
    manifest: V3Manifest,
    state: LoopState,
    start_frames: np.ndarray,
    positions: np.ndarray,
    start_visible: np.ndarray | None = None,
) -> None:
    """Appends points; exact as long as their start frames are not decoded yet.

    Args:
        manifest: the export's description.
        state: the loop (updated in place).
        start_frames: (M,) int start frames.
        positions: (M, 2) normalised (x, y) on them.
        start_visible: (M,) bool start labels (default: visible).
    """
    count = len(start_frames)
    channels, patch = manifest.d_model, manifest.context_patch
    visible = np.ones(count, bool) if start_visible is None else np.asarray(start_visible, bool)
    xy = np.asarray(positions, np.float32).reshape(count, 2)
    state.start_frames = np.concatenate((state.start_frames, np.asarray(start_frames, np.int64)))
    state.query_positions = np.concatenate((state.query_positions, xy))
    state.start_visible = np.concatenate((state.start_visible, visible))
    zeros = np.zeros((count, channels), np.float32)
    state.initial_content = np.concatenate((state.initial_content, zeros))
    if state.context is not None:
        fresh = np.zeros((count, patch, patch, channels), np.float32)
        state.context = np.concatenate((state.context, fresh))
    state.initialised = np.concatenate((state.initialised, np.zeros(count, bool)))
    state.positions = np.concatenate((state.positions, position_logits(xy, manifest.position_eps)))
    state.history.add_points(count)


def keep_points(state: LoopState, keep: np.ndarray) -> None:
    """Drops the points not selected by the (N,) bool mask."""
    for name in (
        "start_frames",
        "query_positions",
        "start_visible",
        "initial_content",
        "initialised",
        "positions",
    ):
        setattr(state, name, np.ascontiguousarray(getattr(state, name)[keep]))
    if state.context is not None:
        state.context = np.ascontiguousarray(state.context[keep])
    state.history.keep_points(keep)


def unwritten(manifest: V3Manifest, state: LoopState, frame: int) -> np.ndarray:
    """Step 1: (N, 3) float32 logits of ``frame`` before decoding."""
    if manifest.visibility_weights:
        visible = state.start_frames == frame
    else:
        visible = state.start_visible
    rows = np.array([manifest.visible_logits, manifest.occluded_logits], np.float32)
    return rows[np.where(visible, 0, 1)]


def decode_frame(
    graphs: StepGraphs, state: LoopState, memory_of: Callable[[int], np.ndarray]
) -> FrameResult:
    """Decodes ``state.next_frame`` and updates ``state`` in place (steps 1-5).

    Args:
        graphs: the exported graphs.
        state: the loop state.
        memory_of: a frame's memory (S, C); called only for a frame that starts points or
            is decoded.

    Returns:
        Every point's outputs on the frame.
    """
    manifest = graphs.manifest
    frame = state.next_frame
    state.next_frame += 1
    visibility = unwritten(manifest, state, frame)
    state.history.open_frame(frame, state.initial_content, visibility[:, 1])
    new = ~state.initialised & (state.start_frames == frame)
    memory = memory_of(frame) if new.any() else None
    if memory is not None:
        _start_points(graphs, state, memory, new)
    if not (state.start_frames < frame).any():  # no point past its start: skipped
        return FrameResult(_sigmoid(state.positions[:, :2]), visibility)
    if memory is None:
        memory = memory_of(frame)
    positions, visibility, features = graphs.decode_step(
        _step_inputs(state, memory, frame, visibility)
    )
    state.positions = positions
    state.history.close_frame(features, visibility[:, 1])
    return FrameResult(_sigmoid(positions[:, :2]), visibility)


def _start_points(
    graphs: StepGraphs, state: LoopState, memory: np.ndarray, new: np.ndarray
) -> None:
    """Step 3: the initial content and context of the points selected by ``new`` (N,)."""
    content, context = graphs.start_points(memory, state.query_positions[new])
    state.initial_content[new] = content
    if state.context is not None and context is not None:
        state.context[new] = context
    state.initialised |= new
    state.history.restart(new, state.initial_content)


def _step_inputs(
    state: LoopState, memory: np.ndarray, frame: int, visibility: np.ndarray
) -> dict[str, np.ndarray]:
    """``decode_step``'s inputs by name (the context only for a model that has it)."""
    history = state.history
    inputs = {
        "memory": memory,
        "frame": np.array(frame, np.int64),
        "start_frames": state.start_frames,
        "initial_content": state.initial_content,
        "positions": state.positions,
        "visibility": visibility,
        "history_content": history.content,
        "history_visibility": history.visibility,
        "slot_frames": history.slot_frames,
        "slot_held": history.slot_held,
    }
    if state.context is not None:
        inputs["context"] = state.context
    return inputs


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return (1 / (1 + np.exp(-x))).astype(np.float32)


FrameLoader = Callable[[int], np.ndarray]
"""Returns frame t as (3, H, W) float32 RGB in [0, 1] at the export's input size."""


class FrameMemory:
    """Encodes frames through the encoder graph on demand, keeping the latest one.

    Frames are asked for in increasing order and each at most twice in a row (its points
    start, then it is decoded), so one frame of memory is all that is held.

    Args:
        graphs: the exported graphs.
        load: frame t → (3, H, W) float32 in [0, 1] at the input size.
    """

    def __init__(self, graphs: StepGraphs, load: FrameLoader) -> None:
        self.graphs = graphs
        self.load = load
        self.frame = -1
        self.memory = np.zeros(0, np.float32)

    def __call__(self, frame: int) -> np.ndarray:
        """Memory (S, C) of ``frame``."""
        if frame != self.frame:
            image = np.ascontiguousarray(self.load(frame), np.float32)
            self.memory = self.graphs.encode(image[None])[0]
            self.frame = frame
        return self.memory


def track_points(
    graphs: StepGraphs,
    frames: np.ndarray | FrameLoader,
    num_frames: int,
    start_frames: np.ndarray,
    positions: np.ndarray,
    start_visible: np.ndarray | None = None,
    history_frames: int | None = None,
) -> TrackArrays:
    """Tracks points through a whole video, frame by frame.

    Args:
        graphs: the exported graphs.
        frames: (T, 3, H, W) float32 RGB in [0, 1] at the input size, or a loader of one.
        num_frames: T.
        start_frames: (N,) start frames.
        positions: (N, 2) normalised (x, y) on them.
        start_visible: (N,) start labels (default: visible).
        history_frames: the most frames held per point (0: all); default the manifest's.

    Raises:
        ValueError: frames of another size than the export's.
    """
    load = frames if callable(frames) else _array_loader(frames, graphs.manifest)
    state = start_state(graphs.manifest, history_frames)
    add_points(graphs.manifest, state, start_frames, positions, start_visible)
    memory = FrameMemory(graphs, load)
    results = [decode_frame(graphs, state, memory) for _ in range(num_frames)]
    return TrackArrays(
        np.stack([r.positions for r in results]), np.stack([r.visibility_logits for r in results])
    )


def _array_loader(frames: np.ndarray, manifest: V3Manifest) -> FrameLoader:
    expected = (3, *manifest.input_size)
    if frames.ndim != 4 or frames.shape[1:] != expected:
        height, width = manifest.input_size
        raise ValueError(f"frames must be (T, 3, {height}, {width}), got {frames.shape}")
    return lambda frame: frames[frame]
