"""The predictor's conventions around the model, in numpy, for the torch-free TAPTRv3 loop.

Each function is the twin of a PyTorch one and is tested against it through the
predictor and the online tracker (tests/test_export_v3_loop.py):

- `pixel_queries` validates (t, x, y) pixel queries (`taptr.api.inputs.query_tensor`,
  sharing `taptr.query_checks`; the grid is `taptr.query_checks.grid_points`, shared too);
- `normalised` maps pixels to the model's units x / (W − 1), y / (H − 1)
  (`taptr.geometry.pixels_to_normalized`);
- `support_scheme` and `support_points` surround the queries as the model's config says
  (`taptr.api.predictor.Predictor.support_scheme`, `taptr.api.support`), from the
  manifest's `taptr.export.v3_manifest.SupportRule`;
- `on_own_frames` returns each query exactly on its own frame (`taptr.api.queries`);
- `both_ways` adds the time-reversed pass before each query frame (`taptr.api.backward`).

Shapes: T frames, N points.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from taptr.config import SUPPORT_KINDS
from taptr.export.v3_manifest import SupportRule
from taptr.query_checks import check_num_points, check_query_values


def pixel_queries(queries: Any, num_frames: int | None, height: int, width: int) -> np.ndarray:
    """Validated (N, 3) float32 (t, x, y) pixel queries of one video.

    Args:
        queries: (N, 3) array-like of real numbers (t, x, y), pixel centres at integers.
        num_frames: frames T of the video, or None for a stream of unknown length.
        height: frame height H.
        width: frame width W.

    Raises:
        ValueError: not real numbers, the wrong shape, too many points, non-finite values,
            fractional frames or positions outside the video.
    """
    expected = "queries must be an (N, 3) array of real numbers (t, x, y)"
    try:
        array = np.asarray(queries)
    except (TypeError, ValueError):
        raise ValueError(f"{expected}, got rows of different lengths") from None
    if array.dtype.kind not in "iuf":
        raise ValueError(f"{expected}, got dtype {array.dtype}")
    array = array.astype(np.float64)
    if array.ndim != 2 or array.shape[-1] != 3:
        raise ValueError(f"{expected}, got shape {array.shape}")
    check_num_points(array.shape[0])
    check_query_values(array, num_frames, height, width)
    return array.astype(np.float32)


def pixel_scale(height: int, width: int) -> np.ndarray:
    """(2,) float32 (W − 1, H − 1), at least 1: a normalised unit in pixels."""
    return np.array([max(width - 1, 1), max(height - 1, 1)], np.float32)


def normalised(xy: np.ndarray, height: int, width: int) -> np.ndarray:
    """(N, 2) pixels → (N, 2) float32 normalised (x, y)."""
    return (xy.astype(np.float32) / pixel_scale(height, width)).astype(np.float32)


def support_scheme(rule: SupportRule, num_queries: int, chosen: str | None = None) -> str:
    """The support actually used for ``num_queries`` user points.

    Args:
        rule: the manifest's.
        num_queries: N.
        chosen: a scheme asked for instead of the model's (one of `SUPPORT_KINDS`).
    """
    if chosen is not None:
        return chosen
    local_points = num_queries * (1 + len(rule.local_offsets)) + len(rule.grid_positions)
    if rule.scheme == "local_and_grid" and local_points > rule.local_budget + 36:
        return "grid"
    return rule.scheme


def local_points(rule: SupportRule, starts: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, ...]:
    """The local pattern of each query, in query order: start frames (63·N,), (63·N, 2)."""
    offsets = np.array(rule.local_offsets, np.float32)  # (63, 2)
    positions = (xy[:, None] + offsets).reshape(-1, 2)  # (N·63, 2)
    return np.repeat(starts, len(offsets)), positions.astype(np.float32)


def support_points(
    rule: SupportRule, scheme: str, starts: np.ndarray, xy: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The support points of some queries: start frames (K,) and normalised (K, 2).

    Local points come first, in query order, then the grid.

    Raises:
        ValueError: ``random`` context points beyond the queries (drawn by
            `taptr.api.context`, which needs torch).
    """
    if scheme == "none" or (scheme == "random" and rule.context_points <= len(starts)):
        return np.zeros(0, np.int64), np.zeros((0, 2), np.float32)
    if scheme == "random":
        raise ValueError(
            "this model pads its queries with random context points, drawn by "
            "taptr.api.context, which needs torch: pass support_points='grid' or 'none'"
        )
    if scheme not in ("local_and_grid", "grid"):
        raise ValueError(f"unknown support {scheme!r}; use one of {', '.join(SUPPORT_KINDS)}")
    parts = [local_points(rule, starts, xy)] if scheme == "local_and_grid" else []
    grid = np.array(rule.grid_positions, np.float32)
    parts.append((np.array(rule.grid_start_frames, np.int64), grid))
    return (
        np.concatenate([p[0] for p in parts]).astype(np.int64),
        np.concatenate([p[1] for p in parts]).astype(np.float32),
    )


def on_own_frames(
    tracks: np.ndarray,
    logits: np.ndarray,
    queries: np.ndarray,
    first_frame: int = 0,
    *,
    hide_earlier: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """Each query exactly where it was given, logit +inf, on its own frame.

    Args:
        tracks: (F, N, 2) float32 pixels of frames first_frame..first_frame + F − 1.
        logits: (F, N) visibility logits of the same frames.
        queries: (N, 3) (t, x, y) pixels.
        first_frame: index of the first of the F frames.
        hide_earlier: also set logits before each query frame to −inf (forward only).

    Returns:
        New tracks (F, N, 2) and logits (F, N).
    """
    frames = np.arange(first_frame, first_frame + tracks.shape[0])[:, None]  # (F, 1)
    starts = queries[None, :, 0].astype(np.int64)  # (1, N)
    logits = logits.astype(np.float32).copy()
    if hide_earlier:
        logits[frames < starts] = -np.inf
    at_query = frames == starts  # (F, N)
    tracks = np.where(at_query[..., None], queries[None, :, 1:], tracks).astype(np.float32)
    logits[at_query] = np.inf
    return tracks, logits


def visible(logits: np.ndarray, threshold: float) -> np.ndarray:
    """(…) bool, sigmoid(logit) > ``threshold`` in float32, as the predictor decides."""
    with np.errstate(over="ignore"):
        return 1 / (1 + np.exp(-logits.astype(np.float32))) > np.float32(threshold)


PassFunction = Callable[[np.ndarray, bool], tuple[np.ndarray, np.ndarray]]
"""One forward pass: (queries (N, 3) in the pass's time, reverse) → tracks (T, N, 2) and
logits (T, N) in the pass's time."""


def both_ways(
    one_pass: PassFunction, queries: np.ndarray, num_frames: int
) -> tuple[np.ndarray, ...]:
    """A forward pass, and a time-reversed one for the frames before each query frame.

    Returns:
        tracks (T, N, 2) and logits (T, N).
    """
    tracks, logits = one_pass(queries, False)
    starts = queries[:, 0].astype(np.int64)
    if not (starts > 0).any():
        return tracks, logits
    flipped = queries.copy()
    flipped[:, 0] = num_frames - 1 - queries[:, 0]
    back_tracks, back_logits = one_pass(flipped, True)
    before = np.arange(num_frames)[:, None] < starts[None]  # (T, N)
    tracks = np.where(before[..., None], back_tracks[::-1], tracks)
    return tracks, np.where(before, back_logits[::-1], logits)
