"""Point self-attention on each frame's tracked points only, frame by frame.

The reference formulation (`taptr.model.decoder.DecoderLayer`) attends among all N points
of a frame with an N × N mask that keeps tracked and untracked points apart. Untracked
entries (a point before its start frame) influence nothing that is kept and their outputs
are discarded, so attending among the tracked points alone gives the same kept outputs
without any N × N tensor.
"""

from __future__ import annotations

from collections.abc import Callable

from torch import Tensor

Attention = Callable[[Tensor, Tensor, Tensor, Tensor | None], Tensor]
"""(query, key, value, allowed mask) → attended, as `taptr.model.attention.MultiheadAttention`."""


def tracked_point_attention(
    attention: Attention,
    norm: Callable[[Tensor], Tensor],
    queries: Tensor,
    values: Tensor,
    tracked: Tensor,
) -> Tensor:
    """Post-normed residual self-attention among each frame's tracked points.

    Args:
        attention: the layer's point attention.
        norm: the LayerNorm after the residual.
        queries: (B·W_t, N, C) content plus position embedding.
        values: (B·W_t, N, C) content.
        tracked: (B·W_t, N) bool, the points each frame tracks.

    Returns:
        (B·W_t, N, C): ``norm(values + attention(...))`` on tracked entries, ``values``
        unchanged on the others (they are discarded downstream).
    """
    out = values.clone()
    for row in range(values.shape[0]):
        keep = tracked[row].nonzero().squeeze(1)  # (n_f,) tracked points of this frame
        if keep.numel():
            q_row, v_row = queries[row, keep][None], values[row, keep][None]  # (1, n_f, C)
            attended = attention(q_row, q_row, v_row, None)
            out[row, keep] = norm(v_row + attended)[0]
    return out
