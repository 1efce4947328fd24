"""How each model family runs: windows (TAPTR v1, TAPTRv2) or frames (TAPTRv3).

`engine_for` is the one place that tells the families apart. An engine runs a whole video
(`Engine.run`: the predictor through `taptr.runtime.runner.Runner`, and `run_tracker` for
the callers that hold a model and its encoded frames) and drives a stream unit by unit
(`taptr.api.online.OnlineTracker`): it says which unit of frames can be decoded next (a
window, or one frame), decodes it, and reads the frames that became final. The engines
hold no state of their own: everything lives in the driver's state they hand out.

- `taptr.runtime.window_engine.WindowEngine`: windows, about one window of latency;
- `taptr.runtime.frame_engine.FrameEngine`: frames, one frame of latency.
"""

from __future__ import annotations

from typing import Any, Protocol

import torch
from torch import Tensor

from taptr.config import check_history_frames
from taptr.model.frame_source import FrameSource, Span
from taptr.model.sliding_window import WindowNetwork
from taptr.model.taptr import TAPTR
from taptr.model.trajectory import QuerySet, TrackOutput
from taptr.model.v3.taptr import TAPTRv3
from taptr.runtime.frame_engine import FrameEngine, StepFor
from taptr.runtime.window_engine import WindowEngine
from taptr.types import OnStep


class Engine(Protocol):
    """What a model family's loop offers; ``state`` is the driver state `start` hands out."""

    unit: str
    """What one step decodes: ``window`` or ``frame`` (progress bars count them)."""

    def steps(self, num_frames: int) -> int:
        """How many units (windows or frames) a video of ``num_frames`` decodes."""
        ...

    def run(
        self, queries: QuerySet, num_frames: int, frames: FrameSource, on_step: OnStep = None
    ) -> TrackOutput:
        """Tracks points (B, N, ·) in model units through a whole video of ``num_frames``.

        ``frames`` gives their encoded frames; ``on_step`` is called after each unit.
        """
        ...

    def start(self, queries: QuerySet, num_frames: int | None) -> Any:
        """The driver state of a new stream (``num_frames``: its length, when declared)."""
        ...

    def queries(self, state: Any) -> QuerySet:
        """The points the state tracks."""
        ...

    def add_points(self, state: Any, queries: QuerySet) -> None:
        """Appends points."""
        ...

    def keep_points(self, state: Any, keep: Tensor) -> None:
        """Keeps the points selected by the (N,) bool mask."""
        ...

    def next_span(self, state: Any, num_frames: int | None) -> Span | None:
        """The next unit to decode, or None when a declared stream has no more."""
        ...

    def remaining(self, state: Any, num_seen: int) -> list[Span]:
        """The units still to decode when the stream ends after ``num_seen`` frames."""
        ...

    def decode(self, state: Any, span: Span, frames: FrameSource) -> None:
        """Decodes one unit."""
        ...

    def final_bound(self, state: Any, num_seen: int, num_frames: int | None) -> int:
        """Frames before this index can no longer change."""
        ...

    def read(self, state: Any, first: int, bound: int) -> tuple[Tensor, Tensor]:
        """Last-layer positions (F, N, 2) normalised and logits (F, N) of frames first..bound−1."""
        ...

    def release(self, state: Any, before: int) -> None:
        """Forgets what frames before ``before`` needed."""
        ...


def engine_for(
    model: TAPTR | WindowNetwork,
    dtype: torch.dtype = torch.float32,
    *,
    history_frames: int | None = None,
    step_for: StepFor | None = None,
) -> Engine:
    """The engine of ``model``'s family.

    Args:
        model: the network (or a window network, e.g. exported graphs).
        dtype: floating dtype of the positions and content.
        history_frames: TAPTRv3: the most frames held per point (0: all); default the
            model's. Other models have no history.
        step_for: TAPTRv3: gives each run's decoder step (`taptr.runtime.frame_engine`);
            other models have no step to capture, and never ask.

    Raises:
        ValueError: ``history_frames`` for a model without a history, or against its rule
            (`taptr.config.check_history_frames`).
    """
    if not isinstance(model, TAPTRv3):
        if history_frames is not None:
            raise ValueError("history_frames applies to TAPTRv3 models only")
        return WindowEngine(model, dtype)
    if history_frames is not None:
        check_history_frames(history_frames)
    return FrameEngine(model, dtype, history_frames, step_for)


def run_tracker(
    model: TAPTR | WindowNetwork,
    queries: QuerySet,
    num_frames: int,
    frames: FrameSource,
    dtype: torch.dtype,
    on_step: OnStep = None,
    *,
    history_frames: int | None = None,
) -> TrackOutput:
    """Tracks the queries through a whole video with the model's own engine, eagerly.

    For callers that hold a model and a source of its encoded frames (the evaluation of
    the official protocol, training, the export's checks, benchmarks); the predictor runs
    through `taptr.runtime.runner.Runner`. Arguments as in `engine_for` and `Engine.run`.
    """
    engine = engine_for(model, dtype, history_frames=history_frames)
    return engine.run(queries, num_frames, frames, on_step)
