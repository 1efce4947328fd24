"""The loop each model family runs: sliding windows (TAPTR v1, TAPTRv2) or frames (TAPTRv3).

Callers that track a whole video go through `run_tracker`, which picks the model's
driver: `taptr.model.sliding_window.run_windows` or `taptr.model.v3.per_frame.run_frames`.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from taptr.model.sliding_window import FrameSource, WindowBackend, run_windows
from taptr.model.taptr import TAPTR
from taptr.model.trajectory import QuerySet, TrackOutput
from taptr.model.v3.per_frame import DecoderStep, run_frames
from taptr.model.v3.taptr import TAPTRv3
from taptr.windows import window_ranges


def run_tracker(
    model: TAPTR | WindowBackend,
    queries: QuerySet,
    num_frames: int,
    frames: FrameSource,
    dtype: torch.dtype,
    on_step: Callable[[], object] | None = None,
    *,
    history_frames: int | None = None,
    static_shapes: bool = False,
    step: DecoderStep | None = None,
) -> TrackOutput:
    """Tracks the queries through a whole video with the model's own driver.

    Args:
        model: the network (or a window backend, e.g. exported graphs).
        queries: points in model units.
        num_frames: video length T.
        frames: source of encoded frames.
        dtype: floating dtype of the positions and content.
        on_step: called after each window or frame (progress reporting).
        history_frames: TAPTRv3: the most frames held per point (0: all); default the
            model's. Other models have no history.
        static_shapes: TAPTRv3: the decoder's shapes stay fixed from frame to frame
            (`taptr.model.v3.per_frame.FrameState.static_shapes`), for a compiled decoder.
        step: TAPTRv3: what runs its decoder on a frame (a captured step,
            `taptr.runtime.step_capture`); None: the model's decoder.

    Raises:
        ValueError: ``history_frames`` for a model without a history.
    """
    if isinstance(model, TAPTRv3):
        return run_frames(
            model,
            queries,
            num_frames,
            frames,
            dtype,
            on_step,
            history_frames=history_frames,
            static_shapes=static_shapes,
            step=step,
        )
    if history_frames is not None:
        raise ValueError("history_frames applies to TAPTRv3 models only")
    if step is not None:
        raise ValueError("a decoder step applies to TAPTRv3 models only")
    return run_windows(model, queries, num_frames, frames, dtype, on_step)


def step_count(model: TAPTR | WindowBackend, num_frames: int) -> int:
    """How many times `run_tracker` calls ``on_step`` for a video of ``num_frames``."""
    if isinstance(model, TAPTRv3):
        return num_frames
    return len(window_ranges(num_frames, model.window_size, model.window_stride))
