"""Peak memory of a run over exported graphs, estimated before it starts, and the refusal.

`Predictor` refuses a run whose estimated peak exceeds the budget
(`taptr.memory_estimate`); the exported loop does the same with what its manifest says.
With S tokens and C channels per frame, N points the graphs track (support included),
H history slots (the held frames, rounded up to the buffer's doubling), K the context's
side and 4-byte floats:

    encoder  = 4 · S · C · ENCODER_FLOATS          (one frame's encoding at its peak: the
                                                    deformable sampling of every token)
    points   = 4 · N · C · (K² + 1) · POINT_FLOATS (per point, the step's sampled key and
                                                    value patches of every head and level)
    pairs    = PAIR_BYTES · N²                      (the step's point attention: every
                                                    pair's scores, softmax and mask)
    history  = 4 · N · H · (C + 1)
    overhead = OVERHEAD + 2 · the graphs' bytes    (Python, numpy, the engine, its copy of
                                                    the weights)

The graphs compute all points of a frame at once (their sizes are the graph's inputs),
so a frame's working set grows with N and N², unlike PyTorch's step, which works in
blocks of points. The constants were fitted to the peak resident memory of the torch-free
loop on TAPTRv3-R18 at 384 × 512 through onnxruntime (N = 50, 800, 2,000 and 4,000: 1.8,
2.8, 5.0 and 10.5 GiB, each within 2 % of the estimate; OpenVINO peaked within 3 % of
onnxruntime at 2,000). The pairs' cost assumes the released models' 8 heads, so models with
fewer are overestimated (the tiny test model by 2 to 3 times; tests/test_export_folders.py
holds a measured run under the estimate). 100,000 points, the documented limit, would ask
the step for 3 TB at once and are refused up front.
"""

from __future__ import annotations

import os

from taptr.memory_estimate import Estimate, check_memory
from taptr.onnx.v3_manifest import V3Manifest
from taptr.onnx.v3_tensors import FILES

ENCODER_FLOATS = 90
"""Floats per token and channel of one frame's encoding at its peak (fitted)."""

POINT_FLOATS = 117
"""Floats per point, channel and context cell (K² + 1) of the step's working set (fitted)."""

PAIR_BYTES = 300
"""Bytes per pair of points in the step's point attention (fitted on 8 heads)."""

OVERHEAD = 160 * 1024**2
"""What any run holds whatever its size: Python, numpy, the engine's libraries."""

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
    manifest: V3Manifest,
    num_points: int,
    num_frames: int | None,
    history_frames: int | None,
    graph_bytes: int = 0,
) -> Estimate:
    """The run's estimated peak, by part (module docstring).

    Args:
        manifest: the export's.
        num_points: N points the graphs track, support included.
        num_frames: T frames, or None for a stream of unknown length (its history is
            counted at the limit, or at the first buffer without one).
        history_frames: the loop's history limit (None: the manifest's).
        graph_bytes: the graphs' files together (their weights).
    """
    tokens, channels = manifest.num_tokens, manifest.d_model
    limit = manifest.history_frames if history_frames is None else history_frames
    slots = history_slots(num_frames, limit)
    cells = manifest.context_patch**2 + 1
    return Estimate(
        {
            "encoder": 4 * tokens * channels * ENCODER_FLOATS,
            "points": 4 * num_points * channels * cells * POINT_FLOATS,
            "pairs": PAIR_BYTES * num_points * num_points,
            "history": 4 * num_points * slots * (channels + 1),
            "overhead": OVERHEAD + 2 * graph_bytes,
        },
        host_parts=(),
    )


def graphs_bytes(directory: str | os.PathLike[str] | None) -> int:
    """The graphs' files in ``directory`` together (0 where there are none to look at)."""
    if directory is None:
        return 0
    sizes = (os.stat(os.path.join(directory, name)).st_size for name in FILES.values())
    try:
        return sum(sizes)
    except OSError:
        return 0


def check_run_memory(
    manifest: V3Manifest,
    num_points: int,
    num_frames: int | None,
    history_frames: int | None,
    graph_bytes: int = 0,
) -> None:
    """Refuses a run over exported graphs whose estimated peak exceeds the memory budget.

    A reversed pass (``backward``) runs after the forward one: the same peak.

    Args:
        manifest: the export's.
        num_points: N points the graphs track, support included.
        num_frames: T frames, or None for a stream.
        history_frames: the loop's history limit (None: the manifest's).
        graph_bytes: the graphs' files together (`graphs_bytes`).

    Raises:
        taptr.memory_estimate.MemoryEstimateError: a one-line ValueError naming the knobs.
    """
    estimate = estimate_run(manifest, num_points, num_frames, history_frames, graph_bytes)
    frames = "a stream" if num_frames is None else f"{num_frames:,} frames"
    what = f"tracking {num_points:,} points (support included) through {frames} of this export"
    knobs = "track fewer points, or export at a smaller input size"
    check_memory(estimate, what, knobs)
