"""TAPTR v1's memory-efficient initialisation: every point takes its content in window one.

In this mode (evaluation only) the official v1 code builds every point's initial content
before the first window, from the first window's frames only: a point starting after the
window's last frame takes its content from that last frame. It then decodes as usual.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from taptr.model.sliding_window import FrameSource, WindowBackend
    from taptr.model.trajectory import TrackerState


def initialise_in_first_window(
    backend: WindowBackend,
    state: TrackerState,
    window_index: int,
    first: int,
    last: int,
    frames: FrameSource,
) -> None:
    """Initialises every point from frame min(start, ``last``) before window 0 decodes.

    Does nothing unless ``backend`` is in the memory-efficient mode, not training, and
    ``window_index`` is 0. Runs before the driver's skip check: the official code
    initialises here even when the first window has nothing to update.

    Args:
        backend: the network (`taptr.model.sliding_window.WindowBackend`).
        state: the driver state (updated in place).
        window_index: index of the window about to be decoded.
        first: its first frame.
        last: its last frame (inclusive).
        frames: gives the memory (B, W_t, S, C) of frames first..last.
    """
    if window_index != 0 or not backend.memory_efficient or backend.training:
        return
    # imported here: the driver imports this module
    from taptr.model.sliding_window import initialise_points

    content_frames = state.queries.start_frames.clamp(max=last)  # (B, N)
    initialise_points(backend, state, frames(first, last), first, content_frames)
