"""Context points: the seeded extra queries the official code adds to the user's points.

TAPTR's points attend to each other in every decoder layer, and the authors train and
evaluate with 800 points per clip. Their interactive demo and their TAP-Vid evaluation
therefore never run the model on a handful of points: they pad the query set to 800 with
a seeded recipe (TAPTRv2-SPEC.md §4.2 for the evaluation on 256 × 256 frames, §6 for the
demo on the 512 × 512 model input), and drop the extra points from the results.

The recipe, in the pixel space of a frame of size (H, W), with K = count − n:

1. a fresh legacy numpy generator seeded with 0 (the official code reseeds numpy's global
   one; a private generator gives the same numbers without touching anyone's state);
2. a candidate list that starts with the n real points (the official quirk: when n < K
   the last K entries kept below still include copies of them);
3. while the list is shorter than K, draw an integer (x, y) with a margin of 1/16 of the
   frame (x in [W//16, W − 1 − W//16], likewise y) and keep it when it lies at least 1 px
   from every listed point;
4. keep the last K entries: static points;
5. then draw each point's occluded prefix r from [0, prefix_limit): the point is queried
   on frame r.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from taptr.geometry import pixels_to_normalized
from taptr.model.trajectory import QuerySet

PREFIX_FRAMES = 12
"""Context points start on a frame drawn from [0, min(12, T)) (the official demo)."""


class ContextPoints(NamedTuple):
    """Extra points added to a query set.

    Attributes:
        positions: (K, 2) float64 static (x, y), whole pixels of the recipe's frame.
        start_frames: (K,) int64 frame on which each point is queried (its occluded prefix).
    """

    positions: np.ndarray
    start_frames: np.ndarray


def padding_bounds(size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Inclusive (x, y) bounds of drawn points in a frame of (H, W): a margin of 1/16.

    For 512 × 512 this is [32, 479] (the demo), for 256 × 256 [16, 239] (the evaluation).
    """
    height, width = size
    low = np.array([width // 16, height // 16])
    return low, np.array([width - 1, height - 1]) - low


def draw_context(
    real_positions: np.ndarray,
    count: int,
    size: tuple[int, int],
    prefix_limit: int,
) -> ContextPoints:
    """The official padding of n real points to ``count`` points (see the module docstring).

    Args:
        real_positions: (n, 2) the real points' (x, y) in the pixels of a (H, W) frame.
        count: size of the padded set; K = count − n points are returned (none when n ≥ count).
        size: (H, W) of the frame the recipe draws in (the model input for the demo,
            256 × 256 for the evaluation).
        prefix_limit: start frames are drawn from [0, prefix_limit).

    Returns:
        `ContextPoints` with K points.
    """
    real_positions = np.asarray(real_positions, dtype=np.float64).reshape(-1, 2)
    wanted = count - len(real_positions)
    if wanted <= 0:
        return ContextPoints(np.zeros((0, 2)), np.zeros(0, dtype=np.int64))
    if prefix_limit < 1:
        raise ValueError(f"prefix_limit must be at least 1, got {prefix_limit}")
    rng = np.random.RandomState(0)
    low, high = padding_bounds(size)
    listed = np.empty((len(real_positions) + wanted, 2))
    listed[: len(real_positions)] = real_positions
    size_now = len(real_positions)
    while size_now < wanted:
        # per-axis bounds draw the same numbers as the official scalar ones on square frames
        point = rng.randint(low, high + 1, size=2)
        if size_now == 0 or np.sqrt(np.sum((listed[:size_now] - point) ** 2, axis=1)).min() >= 1:
            listed[size_now] = point
            size_now += 1
    prefix = rng.randint(0, prefix_limit, wanted).astype(np.int64)
    return ContextPoints(listed[size_now - wanted : size_now].copy(), prefix)


def with_context(
    queries: QuerySet, count: int, input_size: tuple[int, int], num_frames: int | None
) -> QuerySet:
    """The query set with context points appended after the real ones (one draw per video).

    The recipe runs in the model input's pixels (512 × 512 for the paper model: the
    demo's space), where a normalised position p sits at p · (size − 1).

    Args:
        queries: the real points, (B, N, ·) in model units.
        count: points per video after padding; nothing is added when N ≥ count.
        input_size: (H_m, W_m) of the model input.
        num_frames: video length T (start frames are drawn from [0, min(12, T))), or None
            when unknown (a stream): [0, 12).

    Returns:
        (B, max(N, count), ·) queries; the first N are ``queries``. Context points are
        static, queried on their drawn start frame, with a visible start label.
    """
    batch, real = queries.start_frames.shape
    if count <= real:
        return queries
    height, width = input_size
    limit = PREFIX_FRAMES if num_frames is None else min(PREFIX_FRAMES, num_frames)
    scale = torch.tensor([width - 1, height - 1], dtype=torch.float64)
    drawn = [
        draw_context(
            (queries.positions[b].detach().cpu().double() * scale).numpy(),
            count,
            input_size,
            limit,
        )
        for b in range(batch)
    ]
    device, dtype = queries.positions.device, queries.positions.dtype
    # whole pixels divided in float32, as the official code divides them
    positions = torch.stack(
        [pixels_to_normalized(torch.from_numpy(d.positions).float(), height, width) for d in drawn]
    )
    starts = torch.stack([torch.from_numpy(d.start_frames) for d in drawn])
    return QuerySet(
        torch.cat((queries.start_frames, starts.to(device)), dim=1),
        torch.cat((queries.positions, positions.to(device, dtype)), dim=1),
        torch.cat((queries.start_visible, torch.ones_like(starts, dtype=torch.bool).to(device)), 1),
    )
