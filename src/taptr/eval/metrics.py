"""The TAP-Vid metrics: the one implementation in the package, and its adapter.

`compute_tapvid_metrics` has tapnet's signature, conventions and key names (TAPVID-PROTOCOL.md
§1): query points are (t, y, x), flags say *occluded*, tracks are (x, y) pixels of a 256 × 256
frame, thresholds are strict (``d < δ``) at δ ∈ {1, 2, 4, 8, 16} px, and in ``first`` mode
only frames after the query frame are scored, in ``strided`` mode every frame but the query
frame. The benchmark figure is the plain mean over videos of the per-video values
(`mean_over_videos`), not a pool over points.

`tapvid_metrics` is the only place that converts taptr's conventions ((t, x, y) queries,
(T, N) visibility, pixel centres at integers) into tapnet's.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Literal

import numpy as np

QueryMode = Literal["first", "strided"]
QUERY_MODES: tuple[QueryMode, ...] = ("first", "strided")
THRESHOLDS = (1, 2, 4, 8, 16)
"""Distance thresholds in pixels of the 256 × 256 frame."""

METRIC_NAMES = (
    "occlusion_accuracy",
    *(f"{kind}_{t}" for t in THRESHOLDS for kind in ("pts_within", "jaccard")),
    "average_jaccard",
    "average_pts_within_thresh",
)

CALIBRATION_METRICS = {"aj": "average_jaccard", "oa": "occlusion_accuracy"}
"""Metrics a visibility threshold can be calibrated for, by short name."""
"""tapnet's key names, in tapnet's order."""


def evaluation_mask(query_frames: np.ndarray, num_frames: int, query_mode: str) -> np.ndarray:
    """Which frames are scored for each track.

    Args:
        query_frames: (B, N) integer query frame of each track.
        num_frames: T, frames in the video.
        query_mode: ``"first"`` scores frames t > query; ``"strided"`` every t ≠ query.

    Returns:
        (B, N, T) bool, True where a frame is scored.
    """
    eye = np.eye(num_frames, dtype=bool)
    if query_mode == "first":
        table = np.triu(np.ones((num_frames, num_frames), dtype=bool), k=1)
    elif query_mode == "strided":
        table = ~eye
    else:
        raise ValueError(f"unknown query mode {query_mode!r}; expected one of {QUERY_MODES}")
    # Row q of the table lists the frames scored for a track queried at frame q.
    return table[query_frames]


def compute_tapvid_metrics(
    query_points: np.ndarray,
    gt_occluded: np.ndarray,
    gt_tracks: np.ndarray,
    pred_occluded: np.ndarray,
    pred_tracks: np.ndarray,
    query_mode: str,
    get_trackwise_metrics: bool = False,
) -> dict[str, np.ndarray]:
    """TAP-Vid metrics, with the official (tapnet) signature and definition.

    Per scored frame, with V = visible in the ground truth, P = predicted visible and
    W_δ = (‖pred − gt‖² < δ²): occlusion accuracy = mean of [pred_occluded == gt_occluded];
    pts_within_δ = Σ(W_δ ∧ V) / Σ V; jaccard_δ = Σ(W_δ ∧ V ∧ P) / (Σ V + Σ(P ∧ (¬V ∨ ¬W_δ)));
    the averages run over the five thresholds. A ratio over no frame is NaN, as in tapnet.

    Args:
        query_points: (B, N, 3) as (t, y, x); t is a frame index (rounded), y and x pixels
            (unused: the query frame is all the metric needs).
        gt_occluded: (B, N, T) bool, True where the point is occluded.
        gt_tracks: (B, N, T, 2) ground truth (x, y) in pixels of a 256 × 256 frame.
        pred_occluded: (B, N, T) bool, True where the point is predicted occluded.
        pred_tracks: (B, N, T, 2) predicted (x, y), same pixels.
        query_mode: ``"first"`` or ``"strided"`` (which frames are scored, see module doc).
        get_trackwise_metrics: sum over frames only and return one value per track.

    Returns:
        Every name of `METRIC_NAMES` mapped to fractions, (B,) per video, or (B, N) per
        track with ``get_trackwise_metrics``.
    """
    gt_occluded = np.asarray(gt_occluded, dtype=bool)
    pred_occluded = np.asarray(pred_occluded, dtype=bool)
    gt_tracks = np.asarray(gt_tracks, dtype=np.float64)
    pred_tracks = np.asarray(pred_tracks, dtype=np.float64)
    if gt_tracks.shape != pred_tracks.shape or gt_tracks.shape[-1] != 2 or gt_tracks.ndim != 4:
        raise ValueError(
            f"tracks must both be (B, N, T, 2); got {gt_tracks.shape} and {pred_tracks.shape}"
        )
    if gt_occluded.shape != gt_tracks.shape[:3] or pred_occluded.shape != gt_tracks.shape[:3]:
        raise ValueError(
            f"occluded flags must be (B, N, T) = {gt_tracks.shape[:3]}; "
            f"got {gt_occluded.shape} and {pred_occluded.shape}"
        )
    query_frames = np.round(np.asarray(query_points)[..., 0]).astype(np.int64)
    scored = evaluation_mask(query_frames, gt_tracks.shape[2], query_mode)
    axes = (2,) if get_trackwise_metrics else (1, 2)

    def total(flags: np.ndarray) -> np.ndarray:
        return np.sum(flags & scored, axis=axes)

    visible, pred_visible = ~gt_occluded, ~pred_occluded
    squared_distance = np.sum(np.square(pred_tracks - gt_tracks), axis=-1)
    metrics: dict[str, np.ndarray] = {}
    with np.errstate(invalid="ignore", divide="ignore"):
        metrics["occlusion_accuracy"] = total(gt_occluded == pred_occluded) / np.sum(
            scored, axis=axes
        )
        num_visible = total(visible)
        for threshold in THRESHOLDS:
            within = squared_distance < threshold**2
            metrics[f"pts_within_{threshold}"] = total(within & visible) / num_visible
            true_positives = total(within & visible & pred_visible)
            false_positives = total(pred_visible & ~(visible & within))
            metrics[f"jaccard_{threshold}"] = true_positives / (num_visible + false_positives)
    metrics["average_jaccard"] = np.mean([metrics[f"jaccard_{t}"] for t in THRESHOLDS], axis=0)
    metrics["average_pts_within_thresh"] = np.mean(
        [metrics[f"pts_within_{t}"] for t in THRESHOLDS], axis=0
    )
    return {name: metrics[name] for name in METRIC_NAMES}


def tapvid_metrics(
    queries: np.ndarray,
    gt_tracks: np.ndarray,
    gt_visible: np.ndarray,
    pred_tracks: np.ndarray,
    pred_visible: np.ndarray,
    query_mode: str,
) -> dict[str, float]:
    """Metrics of one video in taptr's conventions; adapter to `compute_tapvid_metrics`.

    Args:
        queries: (N, 3) as (t, x, y); t a frame index, x and y pixels (centres at integers)
            of the frame the metric is computed in (256 × 256 for the benchmark).
        gt_tracks: (T, N, 2) ground truth (x, y) pixels, same frame.
        gt_visible: (T, N) bool, True where the point is visible.
        pred_tracks: (T, N, 2) predicted (x, y) pixels, same frame.
        pred_visible: (T, N) bool, True where the point is predicted visible.
        query_mode: ``"first"`` or ``"strided"``.

    Returns:
        Every name of `METRIC_NAMES` mapped to a fraction (NaN where nothing is scored).
    """
    queries = np.asarray(queries, dtype=np.float64)
    # tapnet's raster pixels put pixel centres at +0.5; distances are unchanged by the shift,
    # it only makes the arrays the ones tapnet itself would receive.
    query_tyx = np.stack([queries[:, 0], queries[:, 2] + 0.5, queries[:, 1] + 0.5], axis=-1)

    def per_track(array: np.ndarray) -> np.ndarray:
        # (T, N, ...) → (1, N, T, ...)
        return np.swapaxes(np.asarray(array), 0, 1)[None]

    result = compute_tapvid_metrics(
        query_points=query_tyx[None],
        gt_occluded=per_track(~np.asarray(gt_visible, dtype=bool)),
        gt_tracks=per_track(np.asarray(gt_tracks, dtype=np.float64) + 0.5),
        pred_occluded=per_track(~np.asarray(pred_visible, dtype=bool)),
        pred_tracks=per_track(np.asarray(pred_tracks, dtype=np.float64) + 0.5),
        query_mode=query_mode,
    )
    return {name: float(value[0]) for name, value in result.items()}


def mean_over_videos(per_video: Sequence[Mapping[str, float]]) -> dict[str, float]:
    """The benchmark figure: the plain mean over videos of each per-video metric.

    Videos where a metric is NaN (nothing was scored) are left out of that metric's mean;
    every video of the TAP-Vid sets has scored points, so there this is the plain mean.
    """
    means = {}
    for name in METRIC_NAMES:
        values = np.array([video[name] for video in per_video], dtype=np.float64)
        values = values[np.isfinite(values)]
        means[name] = float(values.mean()) if values.size else float("nan")
    return means
