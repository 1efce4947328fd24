"""Visibility calibration: the threshold on sigmoid(visibility logit) that scores best.

The predictor calls a point visible where sigmoid(logit) exceeds a threshold; 0.5 is a
guess that suits a model whose probabilities are calibrated, which a model trained with a
focal loss (or on other data) need not be. On a labelled set, this module tracks every
video once, keeps the logits, and scores each candidate threshold on those same predictions:
the threshold changes visibility decisions only, never positions, so one tracking pass is
enough.

Scoring is the canonical TAP-Vid evaluation (`taptr.eval.protocols.StandardProtocol`: the
video resized to 256 × 256, queries sampled in ``first`` or ``strided`` mode, the metric of
`taptr.eval.metrics`), so the chosen threshold maximises the very number ``taptr eval``
reports: average Jaccard (AJ) or occlusion accuracy (OA), averaged over videos.

`write_calibrated` stores the threshold in a taptr checkpoint under
``"visibility_threshold"``; `taptr.Predictor.from_pretrained` uses it for that file.
"""

from __future__ import annotations

import itertools
import logging
import os
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from taptr.api.predictor import Predictor
from taptr.data.tapvid import PendingVideo
from taptr.eval.metrics import CALIBRATION_METRICS, tapvid_metrics
from taptr.eval.predictor_tracker import PredictorTracker
from taptr.eval.protocols import StandardProtocol
from taptr.eval.query_sampling import sample_queries
from taptr.io.atomic import atomic_path
from taptr.types import TrackingSample

logger = logging.getLogger(__name__)

METRICS = CALIBRATION_METRICS
"""Metric choices: short name → TAP-Vid metric name."""

DEFAULT_THRESHOLDS = tuple(round(0.05 * k, 2) for k in range(1, 20))
"""Candidates 0.05, 0.10, …, 0.95 (the current threshold is always scored too)."""


@dataclass
class VideoPrediction:
    """One video's ground truth and predictions, before any threshold is applied.

    Everything is in pixels of the 256 × 256 scoring frame (pixel centres at integers).

    Attributes:
        name: the video's name.
        queries: (N, 3) float32 (t, x, y) query points.
        gt_tracks: (T, N, 2) float32 ground-truth (x, y).
        gt_visible: (T, N) bool ground-truth visibility (True = visible).
        tracks: (T, N, 2) float32 predicted (x, y).
        probability: (T, N) float64 sigmoid of the visibility logit, in [0, 1].
    """

    name: str
    queries: np.ndarray
    gt_tracks: np.ndarray
    gt_visible: np.ndarray
    tracks: np.ndarray
    probability: np.ndarray


@dataclass(frozen=True)
class CalibrationResult:
    """Scores of every candidate threshold and the choice.

    Attributes:
        metric: ``"aj"`` or ``"oa"``.
        query_mode: ``"first"`` or ``"strided"``.
        num_videos: videos scored.
        thresholds: the candidates, ascending.
        scores: mean over videos of the metric at each candidate (a fraction).
        threshold: the best candidate (ties go to the one nearest ``current``).
        score: its score.
        current: the threshold the predictor had before calibration.
        current_score: the score at ``current``.
    """

    metric: str
    query_mode: str
    num_videos: int
    thresholds: tuple[float, ...]
    scores: tuple[float, ...]
    threshold: float
    score: float
    current: float
    current_score: float

    def to_dict(self) -> dict[str, Any]:
        """Plain data for a JSON report."""
        return asdict(self)


def predict_video(predictor: Predictor, sample: TrackingSample, query_mode: str) -> VideoPrediction:
    """Tracks one labelled video as ``taptr eval`` does and keeps the visibility logits.

    Args:
        predictor: the predictor to calibrate.
        sample: the video with ground truth, as a dataset reader returns it.
        query_mode: ``"first"`` or ``"strided"`` (strided also tracks backwards in time).
    """
    backward = query_mode == "strided"
    clip = StandardProtocol(PredictorTracker(predictor, backward=backward)).prepare(sample)
    points = sample_queries(clip.tracks, clip.visible, query_mode)
    num_frames, num_points = len(clip.video), len(points.queries)
    if num_points == 0:
        tracks = np.zeros((num_frames, 0, 2), np.float32)
        probability = np.zeros((num_frames, 0))
    else:
        result = predictor.track(clip.video, points.queries, backward=backward)
        tracks = result.tracks[0].cpu().numpy()
        probability = torch.sigmoid(result.visibility_logits[0].double()).cpu().numpy()
    name = sample.name or "video"
    return VideoPrediction(name, points.queries, points.tracks, points.visible, tracks, probability)


def predict_videos(
    predictor: Predictor,
    videos: Iterable[PendingVideo],
    query_mode: str,
    *,
    max_videos: int | None = None,
    progress: bool = False,
) -> list[VideoPrediction]:
    """`predict_video` over a dataset, loading one video at a time.

    Args:
        predictor: the predictor to calibrate.
        videos: the dataset's videos (`taptr.eval.datasets.open_dataset`).
        query_mode: ``"first"`` or ``"strided"``.
        max_videos: use only the first videos of the set.
        progress: show a progress bar (stderr).
    """
    chosen = itertools.islice(videos, max_videos)  # lazily: one dataset file at a time
    bar = tqdm(chosen, desc="tracking", unit="video", total=max_videos, disable=not progress)
    return [predict_video(predictor, pending.load(), query_mode) for pending in bar]


def score_thresholds(
    predictions: Sequence[VideoPrediction],
    thresholds: Sequence[float],
    metric: str,
    query_mode: str,
) -> np.ndarray:
    """The metric at each threshold, averaged over videos.

    Videos where the metric is undefined (no scored frame) are left out, as in
    `taptr.eval.metrics.mean_over_videos`.

    Args:
        predictions: per-video predictions (`predict_video`).
        thresholds: K candidate thresholds in (0, 1).
        metric: ``"aj"`` or ``"oa"``.
        query_mode: ``"first"`` or ``"strided"``.

    Returns:
        (K,) float64 mean scores (NaN where no video has a defined score).
    """
    name = _metric_name(metric)
    table = np.full((len(thresholds), len(predictions)), np.nan)
    for j, video in enumerate(predictions):
        if len(video.queries) == 0:
            continue
        for i, threshold in enumerate(thresholds):
            visible = video.probability > threshold
            metrics = tapvid_metrics(
                video.queries, video.gt_tracks, video.gt_visible, video.tracks, visible, query_mode
            )
            table[i, j] = metrics[name]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a row no video can score: NaN
        return np.nanmean(table, axis=1)


def choose_threshold(
    predictions: Sequence[VideoPrediction],
    *,
    metric: str = "aj",
    query_mode: str = "first",
    thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
    current: float = 0.5,
) -> CalibrationResult:
    """The candidate threshold with the best mean score.

    ``current`` is scored alongside the candidates, so the choice never scores worse than
    it on this set; among equal scores the candidate nearest ``current`` wins (no change
    without evidence).

    Raises:
        ValueError: a threshold outside (0, 1), an unknown metric, or no scorable video.
    """
    _metric_name(metric)
    candidates = sorted({round(float(t), 6) for t in (*thresholds, current)})
    if any(not 0 < t < 1 for t in candidates):
        raise ValueError(f"thresholds must lie in (0, 1), got {candidates}")
    scores = score_thresholds(predictions, candidates, metric, query_mode)
    if not np.isfinite(scores).any():
        raise ValueError("no video has a scorable query point: calibration needs labelled tracks")
    best_score = np.nanmax(scores)
    ties = [t for t, s in zip(candidates, scores, strict=True) if s >= best_score - 1e-12]
    best = min(ties, key=lambda t: (abs(t - current), t))
    current_index = candidates.index(round(float(current), 6))
    return CalibrationResult(
        metric=metric,
        query_mode=query_mode,
        num_videos=sum(1 for p in predictions if len(p.queries)),
        thresholds=tuple(candidates),
        scores=tuple(float(s) for s in scores),
        threshold=best,
        score=float(scores[candidates.index(best)]),
        current=float(current),
        current_score=float(scores[current_index]),
    )


def write_calibrated(
    source: str | os.PathLike[str] | None,
    destination: str | os.PathLike[str],
    threshold: float,
) -> Path:
    """Writes a taptr checkpoint holding ``threshold`` under ``"visibility_threshold"``.

    A taptr-format file is copied whole (EMA and training state included) with the entry
    added or replaced; anything else that `taptr.weights.registry.resolve_model` loads (the authors'
    release, a bundled or preset name) is written in taptr's format.

    Args:
        source: checkpoint file or model name (None: the default model,
            `taptr.weights.registry.DEFAULT_MODEL`).
        destination: the file to write (atomically); may equal ``source`` when that is a
            taptr checkpoint (another file, such as the authors' release, is never replaced).
        threshold: the calibrated threshold, in (0, 1).
    """
    from taptr.weights.checkpoint import FORMAT, read_file, save_checkpoint
    from taptr.weights.registry import resolve_model

    if not 0 < threshold < 1:
        raise ValueError(f"threshold must lie in (0, 1), got {threshold}")
    if source is not None and Path(source).is_file():
        data = read_file(source)
        if isinstance(data, dict) and data.get("format") == FORMAT:
            data = {**data, "visibility_threshold": float(threshold)}
            with atomic_path(destination) as tmp:
                torch.save(data, tmp)
            return Path(destination)
        if Path(destination).resolve() == Path(source).resolve():
            raise ValueError(
                f"{source} is not a taptr checkpoint; write the calibrated copy to another file "
                "rather than replacing it"
            )
    return save_checkpoint(resolve_model(source), destination, visibility_threshold=threshold)


def _metric_name(metric: str) -> str:
    if metric not in METRICS:
        raise ValueError(f"unknown metric {metric!r}; expected one of {', '.join(METRICS)}")
    return METRICS[metric]
