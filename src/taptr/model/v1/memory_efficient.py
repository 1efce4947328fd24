"""TAPTR v1's memory-efficient initialisation: every point takes its content in window one.

In this mode (evaluation only) the official v1 code builds every point's initial content
before the first window, from the first window's frames only: a point starting after the
window's last frame takes its content from that last frame. It then decodes as usual.
"""

from __future__ import annotations

from torch import Tensor


def first_window_content_frames(
    memory_efficient: bool, training: bool, window_index: int, last: int, start_frames: Tensor
) -> Tensor | None:
    """The frame each point takes its content from before window 0 decodes, or None.

    None unless the model is in the memory-efficient mode, not training, and
    ``window_index`` is 0. The driver initialises the points from these frames before its
    skip check: the official code initialises here even when the first window has nothing
    to update.

    Args:
        memory_efficient: the memory-efficient mode of the window network.
        training: whether it is training.
        window_index: index of the window about to be decoded.
        last: its last frame (inclusive).
        start_frames: (B, N) each point's start frame.

    Returns:
        (B, N) min(start, ``last``), or None.
    """
    if window_index != 0 or not memory_efficient or training:
        return None
    return start_frames.clamp(max=last)
