"""The demo's limits and server defaults: light to import, so ``taptr --help`` stays fast.

The CLI's parser reads these for its defaults before anything heavy (torch, Gradio) loads.
"""

from __future__ import annotations

from dataclasses import dataclass

DEFAULT_HOST = "127.0.0.1"
"""Loopback only: the demo has no authentication, so it is not put on the network unasked."""

DEFAULT_PORT = 7860

MAX_UPLOAD = "500mb"
"""Gradio refuses larger uploads before they reach the disk."""

RUN_MAX_AGE_S = 3600.0
"""Run folders older than this are removed when a new run starts (outputs stay an hour)."""


@dataclass(frozen=True)
class Limits:
    """What the demo accepts, so that one upload cannot exhaust a shared machine.

    Attributes:
        max_frames: longer videos are cut to their first ``max_frames`` frames.
        max_side: videos whose longer side exceeds this many pixels are refused.
        max_points: the most query points one run may track (clicks, region or grid).
        max_disk_bytes: the most the server's workspace (uploads, samples, run outputs)
            may hold; an upload or a run beyond it is refused until old runs expire.
    """

    max_frames: int = 150
    max_side: int = 1280
    max_points: int = 400
    max_disk_bytes: int = 4 << 30

    def __post_init__(self) -> None:
        if min(self.max_frames, self.max_side, self.max_points, self.max_disk_bytes) < 1:
            raise ValueError(f"demo limits must be >= 1, got {self}")
