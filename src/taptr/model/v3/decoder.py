"""TAPTRv3's point decoder: one frame at a time, each layer looking back at the point's past.

A layer runs, in the official order: long-temporal attention from the point's content on
this frame to its held past frames (`taptr.model.v3.long_temporal`) → context-aware
deformable cross-attention with the attention-based position update
(`taptr.model.v3.context_attention`, TAPTRv2's update) → re-embedding of the moved position
→ self-attention among the points → FFN, each post-normed. There is no windowed temporal
attention and no content handed from frame to frame: every frame starts from the point's
initial content, and the past reaches it only through the long-temporal attention.

Everything else is TAPTRv2's decoder (`taptr.model.decoder`): the query position
embedding, the content updater from layer 1 on, the fusion of the displacement into the
head features, the per-layer heads and the refinement rule.
"""

from __future__ import annotations

from typing import NamedTuple

from torch import Tensor, nn

from taptr.model.attention import KeyAwareDeformableAttention, MultiheadAttention
from taptr.model.decoder import Decoder, DecoderLayer, DecoderOutput, LayerOutput
from taptr.model.execution import Execution
from taptr.model.layers import MLP
from taptr.model.masks import AttentionMasks, attention_masks
from taptr.model.position_update import PositionUpdate, refine_updated
from taptr.model.v3.context_attention import ContextAwareDeformableAttention
from taptr.model.v3.long_temporal import LongTemporalAttention


class HeldFrames(NamedTuple):
    """What the long-temporal attention of one decoded frame reads.

    Attributes:
        content: (B, N, H, C) each point's content on the held frames, oldest first.
        distances: (H,) frames from each held frame to the decoded one.
        weights: (B, N, H) float visibility weights, or bool allowed frames (ablation).
        outside: (H,) bool, slots that hold no frame (a static step reads the whole
            buffer: `taptr.model.v3.per_frame.held_frames`), left out of the softmax; or
            None when every slot is held.
    """

    content: Tensor
    distances: Tensor
    weights: Tensor
    outside: Tensor | None = None


class V3DecoderLayer(DecoderLayer):
    """TAPTRv3's layer: long-temporal attention, cross-attention (+ APU), point attention, FFN.

    Attributes:
        long_temporal: attention from each point to its held frames.
        norm_long_temporal: its post-norm.

    Shape:
        content (B, 1, N, C), query_pos (B, 1, N, C), reference (B, 1, N, 4),
        memory (B, S, C), held frames of `HeldFrames`, context (B, N, K, K, C)
        → `LayerOutput`.
    """

    def __init__(
        self,
        cross_attention: ContextAwareDeformableAttention | KeyAwareDeformableAttention,
        position_update: PositionUpdate,
        point_attention: MultiheadAttention | None,
        long_temporal: LongTemporalAttention,
        d_model: int,
        ffn_dim: int,
        temperature: float,
    ) -> None:
        """Creates the layer.

        Args:
            cross_attention: context-aware attention (the paper) or TAPTRv2's key-aware
                attention (ablation).
            position_update: the APU.
            point_attention: attention among a frame's points, or None (ablation).
            long_temporal: attention to the point's held frames.
            d_model: channels C.
            ffn_dim: FFN hidden width.
            temperature: sine temperature of the position re-embedding.
        """
        super().__init__(
            cross_attention, position_update, None, point_attention, d_model, ffn_dim, temperature
        )
        self.long_temporal = long_temporal
        self.norm_long_temporal = nn.LayerNorm(d_model)

    def forward(  # type: ignore[override]
        self,
        content: Tensor,
        query_pos: Tensor,
        reference: Tensor,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        masks: AttentionMasks,
        update: Tensor,
        execution: Execution,
        held: HeldFrames,
        context: Tensor | None,
    ) -> LayerOutput:
        """Runs one layer on one frame.

        Args:
            content: (B, 1, N, C) layer input.
            query_pos: (B, 1, N, C) embedding of ``reference``.
            reference: (B, 1, N, 4) positions (x, y, w, h) in [0, 1].
            memory: (B, S, C) encoder memory of the frame.
            spatial_shapes: (H_l, W_l) per level.
            masks: which points may attend to each other.
            update: (B, 1, N) points whose position may change (tracked, after start).
            execution: how to run.
            held: the points' held frames.
            context: (B, N, K, K, C) the points' initial contexts, or None with TAPTRv2's
                key-aware cross-attention.
        """
        x = self._long_temporal(content, held, execution)
        extra = () if context is None else (context,)
        x, attended = self._cross(
            x, query_pos, reference, memory, spatial_shapes, execution, *extra
        )
        reference, displacement, query_pos = self._move(
            x, attended, query_pos, reference, spatial_shapes, update, execution
        )
        x = self._points(x, query_pos, masks, execution)
        x = self.norm_ffn(x + self.ffn(x, execution))
        return LayerOutput(x, reference, displacement)

    def _long_temporal(self, x: Tensor, held: HeldFrames, execution: Execution) -> Tensor:
        batch, frames, points, channels = x.shape
        flat = x.reshape(batch * points, channels)  # (B·N, C), one frame
        attended = self.long_temporal(
            flat,
            held.content.flatten(0, 1),  # (B·N, H, C)
            held.distances,
            held.weights.flatten(0, 1),
            execution,
            held.outside,
        )
        return self.norm_long_temporal(flat + attended).view(batch, frames, points, channels)


class V3Decoder(Decoder):
    """TAPTRv3's stack: TAPTRv2's decoder loop and heads over `V3DecoderLayer` s.

    Shape:
        content (B, 1, N, C) initial content, positions (B, 1, N, 4) logits,
        memory (B, S, C), tracking and update masks (B, 1, N) → `DecoderOutput`.
    """

    def __init__(
        self, layers: list[V3DecoderLayer], d_model: int, temperature: float, update_fuser: MLP
    ) -> None:
        super().__init__(list(layers), d_model, temperature, update_fuser, refine_updated)

    def forward(  # type: ignore[override]
        self,
        content: Tensor,
        positions: Tensor,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        tracking: Tensor,
        update: Tensor,
        execution: Execution,
        held: HeldFrames,
        context: Tensor | None,
        all_tracked: bool | None = None,
    ) -> DecoderOutput:
        """Decodes one frame.

        Args:
            content: (B, 1, N, C) each point's initial content.
            positions: (B, 1, N, 4) position logits carried from the previous frame.
            memory: (B, S, C) encoder memory of the frame.
            spatial_shapes: (H_l, W_l) per level.
            tracking: (B, 1, N) points at or after their start frame.
            update: (B, 1, N) tracking points after their start frame.
            execution: how to run.
            held: the points' held frames (the same for every layer).
            context: (B, N, K, K, C) initial contexts, or None (TAPTRv2's cross-attention).
            all_tracked: whether every point is tracked, known to the caller without
                asking the device; then the step waits for nothing: the points attend to
                each other unmasked, or (not all tracked) with the N × N mask instead of
                grouping the tracked ones. None reads ``tracking``.
        """
        if all_tracked is None:
            masks = attention_masks(tracking, execution.grouped_point_attention)
        else:
            grouped = execution.grouped_point_attention and all_tracked
            masks = attention_masks(tracking, grouped, all_tracked)
        return self.run_layers(
            content,
            positions,
            memory,
            spatial_shapes,
            masks,
            update,
            execution,
            lambda index, reference: (held, context),
        )
