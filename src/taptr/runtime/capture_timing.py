"""What TAPTRv3's per-frame step costs eager and captured, as kept between runs.

`taptr.runtime.step_capture` keeps a `CaptureTiming` per machine, model and shape in the
file of measured choices (`taptr.runtime.measured`), which anyone can edit. A kept value
decides whether a run stalls minutes to compile, so only a timing that could have been
measured is trusted: numbers of seconds within physical bounds (`MIN_STEP_SECONDS` to
`MAX_STEP_SECONDS` a frame, at most `MAX_CAPTURE_SECONDS` to capture). Anything else (text,
NaN, a negative time, an integer too large for a float, a step of 10**308 s) reads as
nothing kept, and the step is measured again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from taptr.runtime.measured import TOLERANCE

MIN_STEP_SECONDS = 1e-6
"""Fewest seconds a frame's decoder step can take: a CUDA graph's replay alone takes tens
of microseconds."""

MAX_STEP_SECONDS = 3600.0
"""Most seconds a frame's decoder step can take: the paper model takes 18 s with 10,000
points on a 2-core CPU (docs/BENCHMARKS.md), far from an hour."""

MAX_CAPTURE_SECONDS = 3600.0
"""Most seconds a capture can cost: Inductor compiled the step in 73-81 s on a 2-core CPU."""

FIELDS = ("eager_s", "captured_s", "capture_s")
"""The keys of a kept timing."""


@dataclass(frozen=True)
class CaptureTiming:
    """What the step costs eager and captured on one machine and shape.

    Attributes:
        eager_s: seconds per frame of the eager step.
        captured_s: seconds per frame of the captured step (infinite: capturing failed).
        capture_s: seconds the capture cost once (the latest seen: a second process
            reads Inductor's cache and pays less than the first).
    """

    eager_s: float
    captured_s: float
    capture_s: float

    def pays(self, frames: float) -> bool:
        """Whether capturing is faster per frame and saves more than it costs over ``frames``."""
        faster = self.captured_s < self.eager_s * (1 - TOLERANCE)
        return faster and frames * (self.eager_s - self.captured_s) > self.capture_s

    @staticmethod
    def read(value: Any) -> CaptureTiming | None:
        """The timing a kept value holds, or None for a value no measurement could give."""
        if not isinstance(value, dict) or set(value) != set(FIELDS):
            return None
        eager_s = _seconds(value["eager_s"], MIN_STEP_SECONDS, MAX_STEP_SECONDS)
        capture_s = _seconds(value["capture_s"], 0.0, MAX_CAPTURE_SECONDS)
        failed = isinstance(value["captured_s"], float) and value["captured_s"] == math.inf
        captured_s = (
            math.inf
            if failed
            else _seconds(value["captured_s"], MIN_STEP_SECONDS, MAX_STEP_SECONDS)
        )
        if eager_s is None or captured_s is None or capture_s is None:
            return None
        return CaptureTiming(eager_s, captured_s, capture_s)


def _seconds(value: Any, least: float, most: float) -> float | None:
    """``value`` as seconds when it is a number in [``least``, ``most``], else None."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    if isinstance(value, int) and not least <= value <= most:
        return None  # compared as an integer: float(10**400) would overflow
    seconds = float(value)
    return seconds if least <= seconds <= most else None  # NaN fails both comparisons
