"""The memory check of ``taptr track`` and ``taptr edit``, before the first frame is decoded.

`check_run_memory` estimates the run's peak memory (`taptr.memory_estimate`) from the
model, the input size, the frames and the points (the context points the model adds
included), refuses it with the command's own knobs when it exceeds the budget, and prints
the estimate of large runs (a dense grid, or many context points) so that a long run says
what it will take before it starts. Context points cost time as tracked points do: 10,000
of them on the paper's model took 17.8 s a frame, 12 times the 800 it was trained with,
so a run with many more than the model's own says so, with that factor.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from taptr.memory_estimate import available_memory, check_memory, estimate_tracking, gib

if TYPE_CHECKING:
    from taptr.api.predictor import Predictor

LARGE_RUN_BYTES = 2 * 1024**3
"""Runs estimated above this print their estimate first."""

LARGE_RUN_POINTS = 10_000
"""Runs with more points than this print their estimate first."""

CONTEXT_FACTOR = 2
"""Runs with more than this many times the model's own context points (and more than
`CONTEXT_NOTED` points) print their estimate first, with what the extra points cost."""

CONTEXT_NOTED = 1_000
"""Fewer points than this take little time however many are context points."""


def check_run_memory(
    args: argparse.Namespace,
    predictor: Predictor,
    *,
    num_frames: int,
    num_points: int,
    frame_size: tuple[int, int],
    whole_video: bool,
) -> None:
    """Refuses a run whose estimated peak memory exceeds the budget; notes large runs.

    Raises:
        taptr.memory_estimate.MemoryEstimateError: naming ``--input-size``, the points and
            ``--max-frames``.
    """
    config = predictor.model.config if predictor.model is not None else None
    if config is None:
        return  # a graph engine: its tracker checks its own memory (taptr.onnx.graph_memory)
    points = predictor.model_points(num_points)
    height, width = predictor.input_size
    estimate = estimate_tracking(
        config,
        input_size=(height, width),
        num_frames=num_frames,
        num_points=points,
        frame_size=frame_size,
        whole_video=whole_video,
        backward=bool(getattr(args, "backward", False)),
        history_frames=predictor.history_frames,
    )
    what = f"tracking {points:,} points through {num_frames:,} frames at {height}x{width}"
    fewer = f"track fewer points (now {num_points:,})"
    if points > num_points and predictor.chosen_support(num_points).drawn:  # context points
        fewer += f", fewer context points (--context-points, now {predictor.context_points:,})"
    knobs = (
        f"lower --input-size (now {height} {width}), {fewer} "
        f"or fewer frames (--max-frames, now {num_frames:,})"
    )
    check_memory(estimate, what, knobs, predictor.device.type)
    context = _context_note(predictor, num_points, points)
    if estimate.total > LARGE_RUN_BYTES or num_points > LARGE_RUN_POINTS or context:
        budget, source = available_memory(predictor.device.type)
        of = f" of {gib(budget)} {source}" if budget is not None else ""
        line = f"taptr: {what} needs {estimate.describe()}{of}{context}"
        print(line, file=sys.stderr, flush=True)


def _context_note(predictor: Predictor, num_points: int, points: int) -> str:
    """What the context points beyond the model's own cost in time, or "" for none to say."""
    config = predictor.model.config
    own = config.context_points if config is not None else 0
    if not predictor.chosen_support(num_points).drawn or points <= num_points:
        return ""
    usual = max(own, num_points)  # what the model's own context would track
    if points <= max(CONTEXT_FACTOR * usual, CONTEXT_NOTED):
        return ""
    return (
        f"; {points - num_points:,} of the points are context points (--context-points "
        f"{predictor.context_points}; the model's own: {own:,}): they cost time as tracked "
        f"points do, each frame up to about {points / usual:.0f}x as long as with {usual:,}"
    )
