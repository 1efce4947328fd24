"""TAP-Vid evaluation: the metric, query sampling, baselines, protocols and the runner.

The metric (`compute_tapvid_metrics`, tapnet's signature) and its adapter from taptr's
conventions (`tapvid_metrics`) need numpy only; the rest is imported from its module
(``taptr.eval.runner``, ``taptr.eval.baselines``, ...). See docs/EVALUATION.md.
"""

from taptr.eval.metrics import (
    METRIC_NAMES,
    QUERY_MODES,
    THRESHOLDS,
    compute_tapvid_metrics,
    mean_over_videos,
    tapvid_metrics,
)
from taptr.eval.trackers import Tracker

__all__ = [
    "METRIC_NAMES",
    "QUERY_MODES",
    "THRESHOLDS",
    "Tracker",
    "compute_tapvid_metrics",
    "mean_over_videos",
    "tapvid_metrics",
]
