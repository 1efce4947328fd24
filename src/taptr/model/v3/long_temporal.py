"""TAPTRv3's visibility-aware long-temporal attention over each point's past frames.

On the frame being decoded, each point's query is its layer input; the keys and values
are the point's content on the frames it holds (the history: the last layer's head
features of past frames, its initial content on the current one). In words, for one
point and head:

1. Keys are the held contents rotated by their distance in frames to the current frame
   (`taptr.model.v3.rotary`), then projected; values are projected without rotation; the
   query (distance 0) is projected as it is. There is no position embedding.
2. a = softmax(q · k / √D) over every held frame.
3. With visibility weights (the paper), a is multiplied by each frame's weight w (how
   visible the point was predicted there, 1 on its start frame, 0 before it) and
   renormalised: a · w / (Σ a · w + 1e-7) — after the softmax, as the official code does,
   so a frame's weight scales its share without entering the logits. Without them (an
   ablation), frames before the start are masked out of the softmax.
4. The output is Σ a · v through the output projection.

The projections are a packed ``nn.MultiheadAttention`` layout, so released checkpoints
map one to one. `taptr.model.ops.history_attention` computes the same sums without
projecting every held frame (the ``fast`` execution).
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor, nn

from taptr.model.attention import MultiheadAttention
from taptr.model.execution import Execution
from taptr.model.ops.dense import apply_linear, linear
from taptr.model.ops.history_attention import history_attention
from taptr.model.v3.rotary import RotaryTime, rotate

RENORMALISE_EPS = 1e-7
"""Added to the weighted attention's sum before renormalising (official value)."""


def weigh_attention(attention: Tensor, weights: Tensor) -> Tensor:
    """Step 3: softmaxed attention (..., H) scaled by frame weights and renormalised.

    ``weights`` is float (visibility weights, broadcast over heads) or bool (allowed
    frames, already applied before the softmax: returned as it is).
    """
    if weights.dtype == torch.bool:
        return attention
    weighted = attention * weights
    return weighted / (weighted.sum(-1, keepdim=True) + RENORMALISE_EPS)


def masked_scores(scores: Tensor, weights: Tensor) -> Tensor:
    """Scores (Q, M, H) with disallowed frames at −inf when ``weights`` is a bool mask.

    A query without any allowed frame (a point not tracked yet) keeps all its scores: its
    output is discarded, and a row of −inf would be NaN.
    """
    if weights.dtype != torch.bool:
        return scores
    allowed = weights | ~weights.any(-1, keepdim=True)
    return scores.masked_fill(~allowed, float("-inf"))


def shares(scores: Tensor, weights: Tensor, outside: Tensor | None = None) -> Tensor:
    """Steps 2-3: each held frame's share of the output, scores (..., H) → (..., H).

    ``outside`` (H,) marks slots holding no frame: they take no share of the softmax.
    """
    if outside is not None:
        scores = scores.masked_fill(outside, float("-inf"))
    return weigh_attention(masked_scores(scores, weights).softmax(-1), weights)


class LongTemporalAttention(nn.Module):
    """Attention from each point to its own held frames, weighted by visibility.

    Attributes:
        attention: the packed q, k, v projections and the output projection.
        rotary: the time rotation of the keys.

    Shape:
        x (Q, C), history (Q, H, C), distances (H,), weights (Q, H) → (Q, C).
    """

    def __init__(self, d_model: int, num_heads: int) -> None:
        super().__init__()
        self.attention = MultiheadAttention(d_model, num_heads)
        self.rotary = RotaryTime(d_model)

    def forward(
        self,
        x: Tensor,
        history: Tensor,
        distances: Tensor,
        weights: Tensor,
        execution: Execution,
        outside: Tensor | None = None,
    ) -> Tensor:
        """Attends from each query to its held frames.

        Args:
            x: (Q, C) queries: each point's layer input on the decoded frame.
            history: (Q, H, C) each point's content on the held frames, oldest first.
            distances: (H,) frames from each held frame to the decoded one (0 for it).
            weights: (Q, H) float visibility weights (0 where the frame does not count),
                or bool: the frames each query may attend to (the ablation).
            execution: how to run: ``history_products`` takes
                `taptr.model.ops.history_attention`'s formulation.
            outside: (H,) bool slots that hold no frame, or None (`shares`).

        Returns:
            (Q, C), after the output projection.
        """
        turns = self.rotary.turns(distances, history.dtype)
        share_of = functools.partial(shares, outside=outside)
        if execution.history_products:
            return history_attention(
                self.attention,
                x,
                history,
                weights,
                execution,
                lambda held: rotate(held, *turns),
                share_of,
            )
        keys = rotate(history, *turns)
        heads = self.attention.num_heads
        w_q, w_k, w_v = self.attention.in_proj_weight.chunk(3)
        b_q, b_k, b_v = self.attention.in_proj_bias.chunk(3)
        queries, frames, channels = history.shape
        onednn = execution.onednn_linear
        q = linear(x, w_q, b_q, onednn=onednn).view(queries, heads, -1)  # (Q, M, D)
        k = linear(keys, w_k, b_k, onednn=onednn).view(queries, frames, heads, -1)  # (Q, H, M, D)
        v = linear(history, w_v, b_v, onednn=onednn).view(queries, frames, heads, -1)
        scores = torch.einsum("qmd,qhmd->qmh", q, k) / q.shape[-1] ** 0.5
        attention = share_of(scores, weights[:, None])  # (Q, M, H)
        out = torch.einsum("qmh,qhmd->qmd", attention, v).reshape(queries, channels)
        return apply_linear(self.attention.out_proj, out, onednn=onednn)
