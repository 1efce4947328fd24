"""The point decoder: refines every point query on every frame of one window.

One TAPTRv2 layer, in the official order: deformable cross-attention to the frame's memory
with the attention-based position update (APU) → re-embedding of the moved position →
temporal self-attention across the window's frames of each point → self-attention among
the points of each frame → FFN, each post-normed. After every layer the decoder fuses the
APU displacement into the features that the per-layer position and visibility heads read.

TAPTR (v1) layers fuse the cost volume into the content first, then run temporal
attention, point attention and plain cross-attention, and apply the content updater from
the first layer on; everything else is shared.

Tracked and untracked entries (a point before its start frame) never attend to each other,
so untracked entries run through the network without affecting anything that is kept.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn

from taptr.geometry import clamp_to_unit, inverse_sigmoid
from taptr.model.attention import (
    DeformableAttention,
    KeyAwareDeformableAttention,
    MultiheadAttention,
)
from taptr.model.cost_volume import CostVolume
from taptr.model.layers import MLP
from taptr.model.position_encoding import point_embedding
from taptr.model.position_update import PositionUpdate


class LayerOutput(NamedTuple):
    """Output of one decoder layer.

    Attributes:
        content: (B, W_t, N, C) raw layer output (the next layer's input).
        reference: (B, W_t, N, 4) position in [0, 1] after the position update.
        displacement: (B, W_t, N, 2) masked APU displacement, or None without the update.
    """

    content: Tensor
    reference: Tensor
    displacement: Tensor | None


class DecoderOutput(NamedTuple):
    """Per-layer results of decoding one window (logit space for positions).

    Attributes:
        positions: (D_l, B, W_t, N, 4) position logits after each layer's head.
        visibility_logits: (D_l, B, W_t, N, 3) logits (channel 1 = visible).
        updated_positions: (D_l, B, W_t, N, 4) logits of the APU-updated positions, or
            None without the position update.
        features: (B, W_t, N, C) what the last layer's heads read (content hand-over).
    """

    positions: Tensor
    visibility_logits: Tensor
    updated_positions: Tensor | None
    features: Tensor


class AttentionMasks(NamedTuple):
    """Which entries may attend to each other: tracked and untracked ones never do.

    Attributes:
        temporal: (B·N, 1, W_t, W_t) True where frames of one point may attend, or None
            when every entry is tracked.
        spatial: (B·W_t, 1, N, N) the same for the points of one frame, built only on the
            faithful path (it is N² per frame), else None.
        frame_tracking: (B·W_t, N) which points each frame tracks.
    """

    temporal: Tensor | None
    spatial: Tensor | None
    frame_tracking: Tensor


def attention_masks(tracking: Tensor, grouped: bool) -> AttentionMasks:
    """Masks for a window's tracking pattern, (B, W_t, N) bool.

    Args:
        tracking: (B, W_t, N) entries at or after each point's start frame.
        grouped: skip the N × N spatial mask; point attention then runs on the tracked
            points of each frame only (untracked entries influence nothing and are
            discarded, so the kept outputs are the same).
    """
    batch, frames, points = tracking.shape
    per_point = tracking.transpose(1, 2).reshape(batch * points, frames)  # (B·N, W_t)
    per_frame = tracking.reshape(batch * frames, points)  # (B·W_t, N)
    everything = grouped and bool(tracking.all())
    temporal = None if everything else (per_point[:, :, None] == per_point[:, None, :]).unsqueeze(1)
    spatial = None if grouped else (per_frame[:, :, None] == per_frame[:, None, :]).unsqueeze(1)
    return AttentionMasks(temporal, spatial, per_frame)


class DecoderLayer(nn.Module):
    """Cross-attention (+ position update), temporal attention, point attention, FFN.

    Shape:
        content (B, W_t, N, C), query_pos (B, W_t, N, C), reference (B, W_t, N, 4),
        memory (B·W_t, S, C) → `LayerOutput`.
    """

    def __init__(
        self,
        cross_attention: KeyAwareDeformableAttention | DeformableAttention,
        position_update: PositionUpdate | None,
        temporal_attention: MultiheadAttention | None,
        point_attention: MultiheadAttention | None,
        d_model: int,
        ffn_dim: int,
        temperature: float,
        *,
        cross_attention_first: bool = True,
        corr_fuser: MLP | None = None,
    ) -> None:
        """Creates the layer.

        Args:
            cross_attention: deformable attention to the memory.
            position_update: the APU, or None.
            temporal_attention: attention across a point's frames, or None (ablation).
            point_attention: attention among a frame's points, or None (ablation).
            d_model: channels C.
            ffn_dim: FFN hidden width.
            temperature: sine temperature of the position re-embedding.
            cross_attention_first: TAPTRv2 order; False gives TAPTR v1's (temporal, points,
                cross).
            corr_fuser: v1's MLP that replaces the content by a fusion with the cost volume.
        """
        super().__init__()
        self.cross_attention = cross_attention
        self.norm_cross = nn.LayerNorm(d_model)
        self.position_update = position_update
        self.position_embed = MLP(2 * d_model, d_model, d_model, 2) if position_update else None
        self.temporal_attention = temporal_attention
        self.norm_temporal = nn.LayerNorm(d_model) if temporal_attention else None
        self.point_attention = point_attention
        self.norm_points = nn.LayerNorm(d_model) if point_attention else None
        self.ffn = MLP(d_model, ffn_dim, d_model, 2)
        self.norm_ffn = nn.LayerNorm(d_model)
        self.corr_fuser = corr_fuser
        self.temperature = temperature
        self.cross_attention_first = cross_attention_first

    def forward(
        self,
        content: Tensor,
        query_pos: Tensor,
        reference: Tensor,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        masks: AttentionMasks,
        update: Tensor,
        correlation: Tensor | None = None,
    ) -> LayerOutput:
        """Runs one layer.

        Args:
            content: (B, W_t, N, C) layer input.
            query_pos: (B, W_t, N, C) embedding of ``reference``.
            reference: (B, W_t, N, 4) positions (x, y, w, h) in [0, 1].
            memory: (B·W_t, S, C) encoder memory of the window's frames.
            spatial_shapes: (H_l, W_l) per level.
            masks: which entries may attend to each other.
            update: (B, W_t, N) entries whose position may change (tracked, after start).
            correlation: (B, W_t, N, K) cost-volume samples at ``reference`` (v1 only).
        """
        x = content
        if self.corr_fuser is not None and correlation is not None:
            x = self.corr_fuser(torch.cat((x, correlation), dim=-1))  # replaces the content
        displacement = None
        if self.cross_attention_first:
            x, reference, displacement, query_pos = self._cross(
                x, query_pos, reference, memory, spatial_shapes, update
            )
        x = self._temporal(x, query_pos, masks.temporal)
        x = self._points(x, query_pos, masks)
        if not self.cross_attention_first:
            x, reference, displacement, query_pos = self._cross(
                x, query_pos, reference, memory, spatial_shapes, update
            )
        x = self.norm_ffn(x + self.ffn(x))
        return LayerOutput(x, reference, displacement)

    def _cross(
        self,
        x: Tensor,
        query_pos: Tensor,
        reference: Tensor,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        update: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor | None, Tensor]:
        """Cross-attention, then the position update and re-embedding when present."""
        batch, frames, points, channels = x.shape
        flat = x.reshape(batch * frames, points, channels)  # (B·W_t, N, C)
        attended = self.cross_attention(
            flat + query_pos.reshape(batch * frames, points, channels),
            reference[..., :2].reshape(batch * frames, points, 2),
            memory,
            spatial_shapes,
        )
        x = self.norm_cross(flat + attended.output).view(batch, frames, points, channels)
        if self.position_update is None or self.position_embed is None:
            return x, reference, None, query_pos
        delta = self.position_update(attended.logits, attended.offsets, spatial_shapes)
        moved = clamp_to_unit(reference[..., :2] + delta.view(batch, frames, points, 2))
        displacement = update.unsqueeze(-1).to(moved.dtype) * (moved - reference[..., :2])
        moved = torch.where(update.unsqueeze(-1), moved, reference[..., :2])
        reference = torch.cat((moved, reference[..., 2:]), dim=-1)
        query_pos = self.position_embed(point_embedding(reference, channels // 2, self.temperature))
        return x, reference, displacement, query_pos

    def _temporal(self, x: Tensor, query_pos: Tensor, allowed: Tensor | None) -> Tensor:
        if self.temporal_attention is None or self.norm_temporal is None:
            return x
        batch, frames, points, channels = x.shape
        q = (x + query_pos).transpose(1, 2).reshape(batch * points, frames, channels)
        v = x.transpose(1, 2).reshape(batch * points, frames, channels)  # (B·N, W_t, C)
        x = self.norm_temporal(v + self.temporal_attention(q, q, v, allowed))
        return x.view(batch, points, frames, channels).transpose(1, 2)

    def _points(self, x: Tensor, query_pos: Tensor, masks: AttentionMasks) -> Tensor:
        if self.point_attention is None or self.norm_points is None:
            return x
        batch, frames, points, channels = x.shape
        q = (x + query_pos).reshape(batch * frames, points, channels)
        v = x.reshape(batch * frames, points, channels)  # (B·W_t, N, C)
        tracked = masks.frame_tracking
        if masks.spatial is not None or bool(tracked.all()):
            x = self.norm_points(v + self.point_attention(q, q, v, masks.spatial))
            return x.view(batch, frames, points, channels)
        out = v.clone()  # untracked entries are discarded: they keep their input
        for row in range(batch * frames):
            keep = tracked[row].nonzero().squeeze(1)  # (n_f,) tracked points of this frame
            if keep.numel():
                q_row, v_row = q[row, keep][None], v[row, keep][None]  # (1, n_f, C)
                attended = self.point_attention(q_row, q_row, v_row, None)
                out[row, keep] = self.norm_points(v_row + attended)[0]
        return out.view(batch, frames, points, channels)


class Decoder(nn.Module):
    """Stack of decoder layers with the shared position embedding and the per-layer heads.

    Shape:
        content (B, W_t, N, C), positions (B, W_t, N, 4) logits, memory (B·W_t, S, C),
        tracking and update masks (B, W_t, N) → `DecoderOutput`.
    """

    def __init__(
        self,
        layers: list[DecoderLayer],
        d_model: int,
        temperature: float,
        update_fuser: MLP | None,
        *,
        cost_volume: CostVolume | None = None,
        update_first_layer: bool = False,
    ) -> None:
        """Creates the decoder.

        Args:
            layers: the decoder layers.
            d_model: channels C.
            temperature: sine temperature of the query position embedding.
            update_fuser: TAPTRv2's fusion of the APU displacement into the head features.
            cost_volume: TAPTR v1's correlation module, or None.
            update_first_layer: apply the content updater before the first layer too (v1).
        """
        super().__init__()
        self.layers = nn.ModuleList(layers)
        self.position_embed = MLP(2 * d_model, d_model, d_model, 2)
        self.content_updater = MLP(2 * d_model, d_model, d_model, 2)
        self.update_fuser = update_fuser
        self.cost_volume = cost_volume
        self.position_heads = nn.ModuleList(MLP(d_model, d_model, 4, 3) for _ in layers)
        self.visibility_heads = nn.ModuleList(nn.Linear(d_model, 3) for _ in layers)
        self.temperature = temperature
        self.update_first_layer = update_first_layer
        self.grouped_attention = True

    @property
    def has_position_update(self) -> bool:
        """Whether the layers move positions inside cross-attention (APU)."""
        return self.layers[0].position_update is not None

    def fuse(self, content: Tensor, displacement: Tensor | None) -> Tensor:
        """Features for the heads: the content, fused with the displacement's embedding."""
        if self.update_fuser is None or displacement is None:
            return content
        embedded = point_embedding(displacement, content.shape[-1] // 2, self.temperature)
        return self.update_fuser(torch.cat((content, embedded), dim=-1))

    def forward(
        self,
        content: Tensor,
        positions: Tensor,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        tracking: Tensor,
        update: Tensor,
    ) -> DecoderOutput:
        """Decodes one window.

        Args:
            content: (B, W_t, N, C) content at window entry.
            positions: (B, W_t, N, 4) position logits at window entry.
            memory: (B·W_t, S, C) encoder memory of the window's frames.
            spatial_shapes: (H_l, W_l) per level.
            tracking: (B, W_t, N) entries at or after each point's start frame.
            update: (B, W_t, N) tracking entries after the start frame.
        """
        batch, frames, points, channels = content.shape
        masks = attention_masks(tracking, self.grouped_attention)
        step = update.unsqueeze(-1).to(content.dtype)
        maps = None
        if self.cost_volume is not None:
            maps = self.cost_volume.prepare(
                memory, spatial_shapes, content.reshape(batch * frames, points, channels)
            )
        reference = positions.sigmoid()
        reference_out = reference  # v1 outputs build on the undetached input reference
        out = content
        all_positions, all_visibility, all_updated = [], [], []
        for index, layer in enumerate(self.layers):
            embedded = point_embedding(reference, channels // 2, self.temperature)
            query_pos = self.position_embed(embedded)
            x = out
            if index > 0 or self.update_first_layer:
                x = out + self.content_updater(torch.cat((out, content), -1))
            correlation = None
            if self.cost_volume is not None and maps is not None:
                flat = reference[..., :2].reshape(batch * frames, points, 2)
                correlation = self.cost_volume.sample(maps, flat).view(batch, frames, points, -1)
            result = layer(
                x, query_pos, reference, memory, spatial_shapes, masks, update, correlation
            )
            out = result.content
            features = self.fuse(out, result.displacement)
            delta = self.position_heads[index](features) * step
            if result.displacement is not None:
                updated_logit = inverse_sigmoid(result.reference)
                # the official outputs re-read the updated position through one more sigmoid
                # round trip than the reference handed to the next layer (≈1e-7 apart)
                updated_output = inverse_sigmoid(updated_logit.sigmoid())
                all_positions.append(delta + updated_output)
                all_updated.append(updated_output)
                reference = (delta + updated_logit).sigmoid().detach()
            else:
                all_positions.append(delta + inverse_sigmoid(reference_out))
                reference_out = (delta + inverse_sigmoid(reference)).sigmoid()
                reference = reference_out.detach()
            all_visibility.append(self.visibility_heads[index](features))
        return DecoderOutput(
            torch.stack(all_positions),
            torch.stack(all_visibility),
            torch.stack(all_updated) if all_updated else None,
            features,
        )
