"""The point decoder: refines every point query on every frame of one window.

One layer, in the official order: deformable cross-attention to the frame's memory with the
attention-based position update (APU) → re-embedding of the moved position → temporal
self-attention across the window's frames of each point → self-attention among the points
of each frame → FFN, each post-normed. After every layer the decoder fuses the APU
displacement into the features that the per-layer position and visibility heads read.

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
        temporal_attention: MultiheadAttention,
        point_attention: MultiheadAttention,
        d_model: int,
        ffn_dim: int,
        temperature: float,
    ) -> None:
        super().__init__()
        self.cross_attention = cross_attention
        self.norm_cross = nn.LayerNorm(d_model)
        self.position_update = position_update
        self.position_embed = MLP(2 * d_model, d_model, d_model, 2) if position_update else None
        self.temporal_attention = temporal_attention
        self.norm_temporal = nn.LayerNorm(d_model)
        self.point_attention = point_attention
        self.norm_points = nn.LayerNorm(d_model)
        self.ffn = MLP(d_model, ffn_dim, d_model, 2)
        self.norm_ffn = nn.LayerNorm(d_model)
        self.temperature = temperature

    def forward(
        self,
        content: Tensor,
        query_pos: Tensor,
        reference: Tensor,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        temporal_allowed: Tensor,
        spatial_allowed: Tensor,
        update: Tensor,
    ) -> LayerOutput:
        """Runs one layer.

        Args:
            content: (B, W_t, N, C) layer input.
            query_pos: (B, W_t, N, C) embedding of ``reference``.
            reference: (B, W_t, N, 4) positions (x, y, w, h) in [0, 1].
            memory: (B·W_t, S, C) encoder memory of the window's frames.
            spatial_shapes: (H_l, W_l) per level.
            temporal_allowed: (B·N, 1, W_t, W_t) which frames of a point see each other.
            spatial_allowed: (B·W_t, 1, N, N) which points of a frame see each other.
            update: (B, W_t, N) entries whose position may change (tracked, after start).
        """
        batch, frames, points, channels = content.shape
        flat = content.reshape(batch * frames, points, channels)  # (B·W_t, N, C)
        attended = self.cross_attention(
            flat + query_pos.reshape(batch * frames, points, channels),
            reference[..., :2].reshape(batch * frames, points, 2),
            memory,
            spatial_shapes,
        )
        x = self.norm_cross(flat + attended.output).view(batch, frames, points, channels)

        displacement = None
        if self.position_update is not None and self.position_embed is not None:
            delta = self.position_update(attended.logits, attended.offsets, spatial_shapes)
            moved = clamp_to_unit(reference[..., :2] + delta.view(batch, frames, points, 2))
            mask = update.unsqueeze(-1).to(moved.dtype)
            displacement = mask * (moved - reference[..., :2])
            reference = torch.cat(
                (torch.where(update.unsqueeze(-1), moved, reference[..., :2]), reference[..., 2:]),
                dim=-1,
            )
            query_pos = self.position_embed(
                point_embedding(reference, channels // 2, self.temperature)
            )

        q = (x + query_pos).transpose(1, 2).reshape(batch * points, frames, channels)
        v = x.transpose(1, 2).reshape(batch * points, frames, channels)  # (B·N, W_t, C)
        temporal = self.temporal_attention(q, q, v, temporal_allowed)
        x = self.norm_temporal(v + temporal).view(batch, points, frames, channels).transpose(1, 2)

        q = (x + query_pos).reshape(batch * frames, points, channels)
        v = x.reshape(batch * frames, points, channels)  # (B·W_t, N, C)
        x = self.norm_points(v + self.point_attention(q, q, v, spatial_allowed))
        x = self.norm_ffn(x + self.ffn(x)).view(batch, frames, points, channels)
        return LayerOutput(x, reference, displacement)


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
    ) -> None:
        super().__init__()
        self.layers = nn.ModuleList(layers)
        self.position_embed = MLP(2 * d_model, d_model, d_model, 2)
        self.content_updater = MLP(2 * d_model, d_model, d_model, 2)
        self.update_fuser = update_fuser
        self.position_heads = nn.ModuleList(MLP(d_model, d_model, 4, 3) for _ in layers)
        self.visibility_heads = nn.ModuleList(nn.Linear(d_model, 3) for _ in layers)
        self.temperature = temperature

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
        per_point = tracking.transpose(1, 2).reshape(batch * points, frames)  # (B·N, W_t)
        temporal_allowed = (per_point[:, :, None] == per_point[:, None, :]).unsqueeze(1)
        per_frame = tracking.reshape(batch * frames, points)  # (B·W_t, N)
        spatial_allowed = (per_frame[:, :, None] == per_frame[:, None, :]).unsqueeze(1)
        step = update.unsqueeze(-1).to(content.dtype)

        reference = positions.sigmoid()
        out = content
        all_positions, all_visibility, all_updated = [], [], []
        for index, layer in enumerate(self.layers):
            query_pos = self.position_embed(
                point_embedding(reference, channels // 2, self.temperature)
            )
            x = content if index == 0 else out + self.content_updater(torch.cat((out, content), -1))
            result = layer(
                x,
                query_pos,
                reference,
                memory,
                spatial_shapes,
                temporal_allowed,
                spatial_allowed,
                update,
            )
            out = result.content
            features = self.fuse(out, result.displacement)
            delta = self.position_heads[index](features) * step
            updated_logit = inverse_sigmoid(result.reference)
            reference = (delta + updated_logit).sigmoid().detach()
            # The official outputs re-read the updated position through one more sigmoid
            # round trip than the reference handed to the next layer (≈1e-7 apart).
            updated_output = inverse_sigmoid(updated_logit.sigmoid())
            all_positions.append(delta + updated_output)
            all_visibility.append(self.visibility_heads[index](features))
            if result.displacement is not None:
                all_updated.append(updated_output)
        return DecoderOutput(
            torch.stack(all_positions),
            torch.stack(all_visibility),
            torch.stack(all_updated) if all_updated else None,
            features,
        )
