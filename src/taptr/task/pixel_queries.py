"""Queries in pixels: checked, mapped to the model's units, and put back on their frames.

Pixel centres sit at integers; the model's normalised units are x / (W − 1), y / (H − 1)
(`taptr.geometry`), so (0, 0) and (W − 1, H − 1) map onto each other across
resolutions. Users get exactly the point they gave on its own frame (DESIGN.md), with
logit +inf; a forward-only pass never tracked the frames before it, which are reported
not visible (logit −inf).

`taptr.api` (through `taptr.api.queries` and `taptr.api.inputs`) and the exported loop
(`taptr.onnx`) both take these rules from here.

Shapes: F frames, N points.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from taptr.task.query_checks import check_num_points, check_query_values


def pixel_queries(queries: Any, num_frames: int | None, height: int, width: int) -> np.ndarray:
    """Validated (N, 3) float32 (t, x, y) pixel queries of one video.

    Args:
        queries: (N, 3) array-like of real numbers (t, x, y), pixel centres at integers
            (an empty list: no queries).
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
    if array.shape == (0,):  # an empty list: no queries, as an empty (0, 3) array
        array = array.reshape(0, 3)
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
        tracks: (F, N, 2) pixels of frames first_frame..first_frame + F − 1.
        logits: (F, N) visibility logits of the same frames.
        queries: (N, 3) (t, x, y) pixels; t a whole frame index.
        first_frame: index of the first of the F frames (a stream returns frames in parts).
        hide_earlier: also set logits before each query frame to −inf: a forward-only
            pass never tracked them (their positions are meaningless).

    Returns:
        New tracks (F, N, 2) and logits (F, N), typed as the inputs.
    """
    frames = np.arange(first_frame, first_frame + tracks.shape[0])[:, None]  # (F, 1)
    starts = queries[None, :, 0].astype(np.int64)  # (1, N)
    logits = logits.copy()
    if hide_earlier:
        logits[frames < starts] = -np.inf
    at_query = frames == starts  # (F, N)
    given = queries[None, :, 1:].astype(tracks.dtype)  # (1, N, 2)
    tracks = np.where(at_query[..., None], given, tracks).astype(tracks.dtype, copy=False)
    logits[at_query] = np.inf
    return tracks, logits


def visible(logits: np.ndarray, threshold: float) -> np.ndarray:
    """(…) bool, sigmoid(logit) > ``threshold`` in float32, as the predictor decides."""
    with np.errstate(over="ignore"):
        return 1 / (1 + np.exp(-logits.astype(np.float32))) > np.float32(threshold)
