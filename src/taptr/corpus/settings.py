"""A corpus video's settings digest: what a rerun compares to skip it.

The digest hashes `taptr.settings_record` (the record ``taptr track`` keeps in
``settings.json``) with the video's own queries, so that a video tracked by either command
with the same model, queries and options counts as the same result.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from taptr.corpus.inputs import CorpusVideo, QuerySpec
from taptr.settings_record import query_record, record_digest, settings_record

if TYPE_CHECKING:
    from taptr.api.predictor import Predictor


@dataclass(frozen=True)
class TrackSettings:
    """The options of a corpus run that change its results.

    Attributes:
        dtype: the autocast type asked for (``float32``, ``bfloat16``, ``float16``).
        max_frames: frames tracked at most per video (None: all).
        backward: points tracked before their query frames too.
    """

    dtype: str = "float32"
    max_frames: int | None = None
    backward: bool = False


def settings_digest(predictor: Predictor, settings: TrackSettings, spec: QuerySpec) -> str:
    """16 hex digits naming the result of ``spec``'s queries with these settings."""
    return _digest(_base(predictor, settings), spec)


def with_digests(
    videos: list[CorpusVideo], predictor: Predictor, settings: TrackSettings
) -> list[CorpusVideo]:
    """The videos with their settings digests (a corpus shares a few query specs)."""
    base = _base(predictor, settings)
    digests: dict[QuerySpec, str] = {}
    for spec in dict.fromkeys(video.queries for video in videos):
        digests[spec] = _digest(base, spec)
    return [replace(video, digest=digests[video.queries]) for video in videos]


def _base(predictor: Predictor, settings: TrackSettings) -> dict[str, Any]:
    """The record without its queries (the model's file is hashed once)."""
    return settings_record(
        predictor,
        {},
        dtype=settings.dtype,
        max_frames=settings.max_frames,
        backward=settings.backward,
    )


def _digest(base: dict[str, Any], spec: QuerySpec) -> str:
    points = None if spec.points is None else np.asarray(spec.points, np.float32)
    queries = query_record(points, spec.grid, spec.mask, spec.query_frame, spec.mask_stride)
    return record_digest({**base, "queries": queries})
