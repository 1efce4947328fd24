"""Which entries of a window may attend to each other: tracked and untracked ones never do.

An entry is one point on one frame; it is tracked at and after the point's start frame.
"""

from __future__ import annotations

from typing import NamedTuple

from torch import Tensor


class AttentionMasks(NamedTuple):
    """Which entries may attend to each other: tracked and untracked ones never do.

    Attributes:
        temporal: (B·N, 1, W_t, W_t) True where frames of one point may attend, or None
            when every entry is tracked.
        spatial: (B·W_t, 1, N, N) the same for the points of one frame, built only without
            grouped point attention (it is N² per frame), else None.
        frame_tracking: (B·W_t, N) which points each frame tracks.
        everything: every entry is tracked and ``spatial`` is None: point attention
            needs no mask and no grouping.
    """

    temporal: Tensor | None
    spatial: Tensor | None
    frame_tracking: Tensor
    everything: bool = False


def attention_masks(
    tracking: Tensor, grouped: bool, all_tracked: bool | None = None
) -> AttentionMasks:
    """Masks for a window's tracking pattern, (B, W_t, N) bool.

    Args:
        tracking: (B, W_t, N) entries at or after each point's start frame.
        grouped: skip the N × N spatial mask; point attention then runs on the tracked
            points of each frame only (untracked entries influence nothing and are
            discarded, so the kept outputs are the same).
        all_tracked: whether every entry is tracked, where the caller knows it without
            reading ``tracking`` (which waits for the device); None reads it when grouped.
    """
    batch, frames, points = tracking.shape
    per_point = tracking.transpose(1, 2).reshape(batch * points, frames)  # (B·N, W_t)
    per_frame = tracking.reshape(batch * frames, points)  # (B·W_t, N)
    if all_tracked is None:
        all_tracked = grouped and bool(tracking.all())
    if all_tracked:
        return AttentionMasks(None, None, per_frame, everything=True)
    temporal = (per_point[:, :, None] == per_point[:, None, :]).unsqueeze(1)
    spatial = None if grouped else (per_frame[:, :, None] == per_frame[:, None, :]).unsqueeze(1)
    return AttentionMasks(temporal, spatial, per_frame)
