"""Queries between the user's pixels and the model, shared by the predictor and the stream.

`model_queries` turns validated (t, x, y) pixel queries (`taptr.api.inputs.query_tensor`)
into the model's point set; `on_own_frames` puts each query back on its own frame in the
results (`taptr.task.pixel_queries`'s rule), so that users get exactly the point they gave
(DESIGN.md: "the query point returned exactly on its own frame").
"""

from __future__ import annotations

import torch
from torch import Tensor

from taptr.geometry import pixels_to_normalized
from taptr.model.trajectory import QuerySet
from taptr.task.pixel_queries import on_own_frames as own_frames


def model_queries(
    queries: Tensor, height: int, width: int, device: torch.device, dtype: torch.dtype
) -> QuerySet:
    """The model's point set for one video's queries, each visible on its start frame.

    Args:
        queries: (N, 3) float (t, x, y): whole frame index and pixels of the input frames
            (pixel centres at integers), as `query_tensor` returns them.
        height: input frame height H in pixels.
        width: input frame width W in pixels.
        device: where the model runs.
        dtype: floating type of the model's positions.

    Returns:
        `QuerySet` of batch 1: start frames (1, N), positions (1, N, 2) normalised by
        (W − 1, H − 1), start labels (1, N) all True.
    """
    return QuerySet(
        queries[None, :, 0].long().to(device),
        pixels_to_normalized(queries[None, :, 1:], height, width).to(device, dtype),
        torch.ones(1, queries.shape[0], dtype=torch.bool, device=device),
    )


def on_own_frames(
    tracks: Tensor,
    logits: Tensor,
    queries: Tensor,
    first_frame: int = 0,
    *,
    hide_earlier: bool,
) -> tuple[Tensor, Tensor]:
    """Results with each query exactly where it was given, visible, on its own frame.

    `taptr.task.pixel_queries.on_own_frames` on host tensors: the model's output on a
    query frame is close to the query but not equal to it; users expect the point they
    clicked back, so it is overwritten, with logit +inf.

    Args:
        tracks: (F, N, 2) float (x, y) pixels of frames first_frame..first_frame + F − 1.
        logits: (F, N) visibility logits of the same frames.
        queries: (N, 3) (t, x, y) pixels; t a whole frame index.
        first_frame: index of the first of the F frames (a stream returns frames in parts).
        hide_earlier: also set the logits of frames before each query frame to −inf.

    Returns:
        tracks (F, N, 2) and logits (F, N), new tensors.
    """
    placed, values = own_frames(
        tracks.numpy(), logits.numpy(), queries.numpy(), first_frame, hide_earlier=hide_earlier
    )
    return torch.from_numpy(placed), torch.from_numpy(values)
