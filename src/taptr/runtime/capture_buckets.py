"""How captured runs share a capture: their points padded to buckets, and its key.

A captured step (`taptr.runtime.step_capture`) is compiled for a number of points; runs
with nearby point counts replay the same one when their points are padded up to a
multiple of `BUCKET` with points that never start (they take no part in the others'
attention, so the real points' tracks are unchanged). Its timing is kept under a key
naming the machine, the model, the bucket, the input size and the precision.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from taptr.model.trajectory import QuerySet
from taptr.runtime.measured import choice_key

BUCKET = 128
"""Captured runs pad their points up to a multiple of this, so that calls with nearby
point counts replay the same captured step instead of capturing another."""

NEVER = 2**31 - 1
"""The start frame of padding points: no video reaches it, so they are never decoded."""


def pad_points(queries: QuerySet, count: int) -> QuerySet:
    """``queries`` with points appended up to ``count`` that never start.

    Points not yet started take no part in the others' attention (the decoder's N × N
    mask), so the real points' tracks are unchanged; callers drop the padding's outputs
    with the rest of what follows the user's points.
    """
    batch, points = queries.start_frames.shape
    extra = count - points
    if extra <= 0:
        return queries
    never = queries.start_frames.new_full((batch, extra), NEVER)
    centre = queries.positions.new_full((batch, extra, 2), 0.5)
    hidden = queries.start_visible.new_zeros(batch, extra)
    return QuerySet(
        torch.cat((queries.start_frames, never), 1),  # (B, count)
        torch.cat((queries.positions, centre), 1),  # (B, count, 2)
        torch.cat((queries.start_visible, hidden), 1),  # (B, count)
    )


def points_bucket(count: int) -> int:
    """``count`` points padded up to the next multiple of `BUCKET`."""
    return max(BUCKET, -(-count // BUCKET) * BUCKET)


def capture_key(
    device: torch.device, config: object, input_size: tuple[int, int], precision: str
) -> Callable[[int], str]:
    """Where a `taptr.runtime.capture_timing.CaptureTiming` is kept, for a number of points.

    The key names the machine, the model, the points' bucket (`points_bucket`), the input
    size and the precision.
    """

    def key(points: int) -> str:
        shape = f"{input_size[0]}x{input_size[1]} {points_bucket(points)} points {precision}"
        return choice_key("TAPTRv3 step capture", device, repr(config), shape)

    return key
