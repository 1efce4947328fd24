"""Support points as the model's point sets: `taptr.task.support_schemes` on torch queries.

The schemes, their patterns and every rule of them (counts, parents, the fallback, what
points added mid-stream bring) are the task layer's; this module only moves the queries to
the host, asks the registry, and hands the points back as a `QuerySet` in the queries'
type and device. The constants are re-exported for the callers that name them here.
"""

from __future__ import annotations

import numpy as np
import torch

from taptr.model.trajectory import QuerySet
from taptr.task.support_schemes import EVAL_SCALE as EVAL_SCALE
from taptr.task.support_schemes import GRID_POINTS as GRID_POINTS
from taptr.task.support_schemes import GRID_SEED as GRID_SEED
from taptr.task.support_schemes import LOCAL_OFFSETS as LOCAL_OFFSETS
from taptr.task.support_schemes import (
    SupportPattern,
    SupportPoints,
    SupportScheme,
    support_scheme,
)
from taptr.task.support_schemes import grid_positions as grid_positions
from taptr.task.support_schemes import grid_start_frames as grid_start_frames
from taptr.task.support_schemes import local_offsets as local_offsets

_NUMPY_TYPES = {torch.float64: np.float64, torch.float16: np.float16}
"""numpy's type for each torch type the support is computed in (others: float32, then cast)."""


def numpy_type(dtype: torch.dtype) -> type:
    """The numpy float type support points of ``dtype`` positions are computed in."""
    return _NUMPY_TYPES.get(dtype, np.float32)


def pattern_for(queries: QuerySet, context_points: int = 0) -> SupportPattern:
    """The normalised patterns in the queries' float type."""
    dtype = numpy_type(queries.positions.dtype)
    return SupportPattern.normalised(dtype, context_points=context_points)


def as_query_set(points: SupportPoints, like: QuerySet) -> QuerySet:
    """Support points as a batch-one `QuerySet` on ``like``'s device and type; start visible."""
    device, dtype = like.positions.device, like.positions.dtype
    count = len(points.start_frames)
    return QuerySet(
        torch.from_numpy(points.start_frames)[None].to(device),
        torch.from_numpy(np.ascontiguousarray(points.positions))[None].to(device, dtype),
        torch.ones(1, count, dtype=torch.bool, device=device),
    )


def scheme_points(
    queries: QuerySet, scheme: SupportScheme, pattern: SupportPattern, *, added: bool = False
) -> tuple[QuerySet, np.ndarray]:
    """The support of batch-one ``queries`` under ``scheme``: points and (K,) parents.

    ``added``: what points added to a stream after its support was drawn bring.
    """
    starts = queries.start_frames[0].cpu().numpy()
    xy = queries.positions[0].detach().cpu().numpy()
    rule = scheme.added if added else scheme.points
    points = rule(starts, xy, pattern)
    return as_query_set(points, queries), points.parents


def with_support(queries: QuerySet, scheme: str) -> QuerySet:
    """The query set with support points after the real ones.

    Args:
        queries: the real points, (B, N, ·) in model units.
        scheme: a registered scheme whose points are not drawn per video (not ``random``,
            `taptr.api.context_points`).

    Returns:
        (B, N + K, ·) queries: the scheme's points after each video's real points, static
        and visible on their start frames.

    Raises:
        ValueError: an unknown scheme, or ``random``.
    """
    chosen = support_scheme(scheme, "support scheme")
    if chosen.drawn:
        raise ValueError(f"the {scheme!r} support is drawn per video: use taptr.api.context_points")
    pattern = pattern_for(queries)
    padded = [
        scheme_points(QuerySet(*(column[b : b + 1] for column in queries)), chosen, pattern)[0]
        for b in range(queries.start_frames.shape[0])
    ]
    support = QuerySet(*(torch.cat(column) for column in zip(*padded, strict=True)))
    return QuerySet(*(torch.cat(pair, dim=1) for pair in zip(queries, support, strict=True)))
