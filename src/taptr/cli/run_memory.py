"""The memory check of ``taptr track`` and ``taptr edit``, before the first frame is decoded.

`check_run_memory` estimates the run's peak memory (`taptr.memory_estimate`) from the
model, the input size, the frames and the points, refuses it with the command's own knobs
when it exceeds the budget, and prints the estimate of large runs (a dense grid) so that
a long run says what it will take before it starts.
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
    config = predictor.model.config
    if config is None:
        return
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
    knobs = (
        f"lower --input-size (now {height} {width}), track fewer points (now {num_points:,}) "
        f"or fewer frames (--max-frames, now {num_frames:,})"
    )
    check_memory(estimate, what, knobs, predictor.device.type)
    if estimate.total > LARGE_RUN_BYTES or num_points > LARGE_RUN_POINTS:
        budget, source = available_memory(predictor.device.type)
        of = f" of {gib(budget)} {source}" if budget is not None else ""
        print(f"taptr: {what} needs {estimate.describe()}{of}", file=sys.stderr, flush=True)
