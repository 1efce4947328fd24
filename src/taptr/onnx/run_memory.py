"""Peak memory of a run over exported graphs, estimated before it starts, and the refusal.

`Predictor` refuses a run whose estimated peak exceeds the budget
(`taptr.memory_estimate`); the exported loop does the same with what its manifest says.
With S tokens and C channels per frame, N points the graphs track (support included),
H history slots (the held frames, rounded up to the buffer's doubling) and K the
context's side, in 4-byte floats:

    encoder  = 4 · S · C · ENCODER_FLOATS          (one frame's encoding, its working set)
    points   = 4 · N · C · (POINT_FLOATS + K²)     (each point's content, context and the
                                                    step's activations)
    pairs    = PAIR_BYTES · N²                      (the step's point attention: every
                                                    pair's scores and mask, all heads)
    history  = 4 · N · H · (C + 1)
    total    = OVERHEAD + the above

The constants were fitted to the peak resident memory of runs of the tiny export and of
TAPTRv3-R18 at 384 × 512 through onnxruntime on a CPU (tests/test_onnx_memory.py compares
the estimate with a measured run); the pairs' term is what refuses 100,000 points, which
would ask the step for about 40 GB of attention scores at once.
"""

from __future__ import annotations

from taptr.memory_estimate import Estimate, check_memory
from taptr.onnx.v3_manifest import V3Manifest

ENCODER_FLOATS = 24
"""Floats per token and channel of one frame's encoding at its peak (fitted)."""

POINT_FLOATS = 24
"""Floats per point and channel of the step's activations (fitted)."""

PAIR_BYTES = 40
"""Bytes per pair of points in the step's point attention (fitted: scores of every head,
their softmax and the N × N mask)."""

OVERHEAD = 192 * 1024**2
"""What any run holds whatever its size: the engine, its thread pools, the weights."""

FIRST_SLOTS = 8
"""The history buffer's first size (`taptr.onnx.ring_history.MIN_SLOTS`); it doubles."""


def history_slots(frames: int | None, limit: int) -> int:
    """Slots the history buffer reaches for ``frames`` frames (None: a stream) and a limit."""
    held = limit if frames is None else (min(frames, limit) if limit else frames)
    slots = FIRST_SLOTS
    while slots < held:
        slots *= 2
    return min(slots, limit) if limit else slots


def estimate_run(
    manifest: V3Manifest, num_points: int, num_frames: int | None, history_frames: int | None
) -> Estimate:
    """The run's estimated peak, by part (module docstring).

    Args:
        manifest: the export's.
        num_points: N points the graphs track, support included.
        num_frames: T frames, or None for a stream of unknown length (its history is
            counted at the limit, or at the first buffer without one).
        history_frames: the loop's history limit (None: the manifest's).
    """
    tokens, channels = manifest.num_tokens, manifest.d_model
    limit = manifest.history_frames if history_frames is None else history_frames
    slots = history_slots(num_frames, limit)
    patch = manifest.context_patch
    return Estimate(
        {
            "encoder": 4 * tokens * channels * ENCODER_FLOATS,
            "points": 4 * num_points * channels * (POINT_FLOATS + patch * patch),
            "pairs": PAIR_BYTES * num_points * num_points,
            "history": 4 * num_points * slots * (channels + 1),
            "overhead": OVERHEAD,
        },
        host_parts=(),
    )


def check_run_memory(
    manifest: V3Manifest,
    num_points: int,
    num_frames: int | None,
    history_frames: int | None,
    backward: bool = False,
) -> None:
    """Refuses a run over exported graphs whose estimated peak exceeds the memory budget.

    Args:
        manifest: the export's.
        num_points: N points the graphs track, support included.
        num_frames: T frames, or None for a stream.
        history_frames: the loop's history limit (None: the manifest's).
        backward: a reversed pass runs too (one after the other: the same peak).

    Raises:
        taptr.memory_estimate.MemoryEstimateError: a one-line ValueError naming the knobs.
    """
    estimate = estimate_run(manifest, num_points, num_frames, history_frames)
    frames = "a stream" if num_frames is None else f"{num_frames:,} frames"
    what = f"tracking {num_points:,} points (support included) through {frames} of this export"
    knobs = "track fewer points, or export at a smaller input size"
    check_memory(estimate, what, knobs)
