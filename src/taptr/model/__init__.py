"""The networks: TAPTR v1, TAPTRv2 and TAPTRv3 (`v1/`, `v3/`), their modules and builder.

How they run on a given machine (drivers, measured choices, frame encoding) is
`taptr.runtime`; this package holds what computes.
"""

from taptr.model.build import build_model
from taptr.model.execution import EXECUTIONS, Execution, get_execution
from taptr.model.sliding_window import (
    QuerySet,
    TrackerState,
    TrackOutput,
    run_windows,
    window_ranges,
)
from taptr.model.taptr import TAPTR, FrameFeatures, normalize_frames

__all__ = [
    "EXECUTIONS",
    "TAPTR",
    "Execution",
    "FrameFeatures",
    "QuerySet",
    "TrackOutput",
    "TrackerState",
    "build_model",
    "get_execution",
    "normalize_frames",
    "run_windows",
    "window_ranges",
]
