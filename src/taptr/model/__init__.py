"""The networks: TAPTR v1, TAPTRv2 and TAPTRv3 (`v1/`, `v3/`), their modules and builder.

How they run on a given machine (drivers, measured choices, frame encoding) is
`taptr.runtime`; this package holds what computes.
"""

from taptr.model.build import build_model
from taptr.model.execution import EXECUTIONS, Execution, get_execution
from taptr.model.frame_source import FrameFeatures
from taptr.model.sliding_window import run_windows
from taptr.model.taptr import TAPTR, normalize_frames
from taptr.model.trajectory import QuerySet, TrackerState, TrackOutput
from taptr.windows import window_ranges

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
