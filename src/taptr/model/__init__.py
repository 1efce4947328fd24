"""The TAPTRv2 network: modules, the window driver and the builder."""

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
