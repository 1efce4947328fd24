"""A corpus video's settings digest: what a rerun compares to skip it.

The digest hashes `taptr.settings_record` (the record ``taptr track`` keeps in
``settings.json``) with the video's own queries, so that a video tracked by either command
with the same model, queries and options counts as the same result. The record is made
from the `ModelSpec` and what its checkpoint says (`taptr.corpus.model_facts`), without a
predictor.

Fields a `ModelSpec` gains later flow into the digest by themselves: any field that is
neither in the record already (`RECORDED`) nor speed only (`SPEED_ONLY`: the same tracks
up to rounding, as the record leaves out) is added under ``spec.{name}`` when it differs
from its default, so a spec at its defaults keeps the digests of existing corpora.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from taptr.api.spec import ModelSpec
from taptr.corpus.inputs import CorpusVideo, QuerySpec
from taptr.settings_record import query_record, record_digest, settings_record

if TYPE_CHECKING:
    from taptr.api.predictor import Predictor
    from taptr.corpus.model_facts import ModelFacts

RECORDED = ("checkpoint", "dtype", "input_size", "context_points", "support", "history_frames")
"""`ModelSpec` fields `taptr.settings_record` records (as the predictor resolves them)."""

SPEED_ONLY = ("device", "kernel", "frames_per_call", "capture", "compile", "threads", "engine")
"""`ModelSpec` fields that change how fast a tracker runs, not its tracks (beyond rounding).

The graph engines' tracks are PyTorch's to 2e-3 px and their logits to 3e-5 (docs/EXPORT.md,
held by tests/test_export_v3_golden.py and tests/test_engine_option.py), as close as the
kernels are to each other, so a corpus may go on in another engine without tracking again.
"""


@dataclass(frozen=True)
class TrackSettings:
    """The options of a corpus run, besides the model, that change its results.

    Attributes:
        max_frames: frames tracked at most per video (None: all).
        backward: points tracked before their query frames too.
    """

    max_frames: int | None = None
    backward: bool = False


def with_digests(
    videos: list[CorpusVideo], spec: ModelSpec, facts: ModelFacts, settings: TrackSettings
) -> list[CorpusVideo]:
    """The videos with their settings digests (a corpus shares a few query specs).

    Args:
        videos: the corpus.
        spec: the tracker.
        facts: what its checkpoint says (`taptr.corpus.model_facts.model_facts`).
        settings: the run's other options.
    """
    base = base_record(spec, facts, settings)
    digests: dict[QuerySpec, str] = {}
    for queries in dict.fromkeys(video.queries for video in videos):
        digests[queries] = digest(base, queries)
    return [replace(video, digest=digests[video.queries]) for video in videos]


def base_record(spec: ModelSpec, facts: ModelFacts, settings: TrackSettings) -> dict[str, Any]:
    """The settings record without its queries (the model's file is hashed once)."""
    # settings_record reads the attributes a predictor and `ModelFacts` share
    described: Predictor = facts  # type: ignore[assignment]
    record = settings_record(
        described,
        {},
        dtype=spec.dtype,
        max_frames=settings.max_frames,
        backward=settings.backward,
    )
    return {**record, **_other_fields(spec)}


def digest(base: dict[str, Any], spec: QuerySpec) -> str:
    """16 hex digits naming the result of ``spec``'s queries under ``base``."""
    points = None if spec.points is None else np.asarray(spec.points, np.float32)
    queries = query_record(points, spec.grid, spec.mask, spec.query_frame, spec.mask_stride)
    return record_digest({**base, "queries": queries})


def _other_fields(spec: ModelSpec) -> dict[str, Any]:
    """The spec's fields the record does not hold, where they are not at their defaults."""
    known = set(RECORDED) | set(SPEED_ONLY)
    found = {}
    for spec_field in dataclasses.fields(spec):
        if spec_field.name in known:
            continue
        value = getattr(spec, spec_field.name)
        if value != _default(spec_field):
            found[f"spec.{spec_field.name}"] = _plain(value)
    return found


def _default(spec_field: dataclasses.Field) -> Any:
    if spec_field.default is not dataclasses.MISSING:
        return spec_field.default
    if spec_field.default_factory is not dataclasses.MISSING:
        return spec_field.default_factory()
    return dataclasses.MISSING  # a field without a default always differs


def _plain(value: Any) -> Any:
    """A JSON-ready form of a field's value (tuples as lists; anything else as text)."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (tuple, list)):
        return [_plain(item) for item in value]
    return repr(value)
