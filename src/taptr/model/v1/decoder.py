"""TAPTR (v1)'s decoder: the TAPTRv2 modules in v1's order, with the cost volume.

What differs from TAPTRv2 (`taptr.model.decoder`):

- layer order: the cost-volume fusion replaces the content, then temporal attention, point
  attention, and plain deformable cross-attention (no position update), then the FFN;
- the cost volume (`taptr.model.v1.cost_volume`) is prepared once per window from the
  window-entry content and sampled around each layer's input reference;
- the content updater applies from the first layer on;
- reported positions follow DINO's "look forward twice" rule (`look_forward_twice`).

Parameter names are those of the v2 modules plus ``decoder.cost_volume`` and
``decoder.layers.{i}.corr_fuser``, in the official order.
"""

from __future__ import annotations

import torch
from torch import Tensor

from taptr.geometry import inverse_sigmoid
from taptr.model.attention import DeformableAttention, MultiheadAttention
from taptr.model.decoder import Decoder, DecoderLayer, LayerOutput
from taptr.model.execution import Execution
from taptr.model.frame_tables import FrameTables
from taptr.model.layers import MLP
from taptr.model.masks import AttentionMasks
from taptr.model.position_update import Refined
from taptr.model.v1.cost_volume import CostVolume


def look_forward_twice(delta: Tensor, reference: Tensor, previous: Tensor) -> Refined:
    """v1's positions: δ on the previous layer's undetached positions (DINO's rule).

    The reported positions build on the previous layer's output before it was detached
    (so a layer's loss also trains the layer before), the next reference on the detached
    input reference. The TAPTRv2 ablation without the APU uses the same rule.

    Args:
        delta: (B, W_t, N, 4) the position head's output, zero where not updated.
        reference: (B, W_t, N, 4) the layer's (detached) input reference in [0, 1].
        previous: (B, W_t, N, 4) the previous layer's undetached positions in [0, 1] (the
            window-entry reference for the first layer).
    """
    positions = delta + inverse_sigmoid(previous)
    output = (delta + inverse_sigmoid(reference)).sigmoid()
    return Refined(positions, None, output.detach(), output)


class V1DecoderLayer(DecoderLayer):
    """v1's layer: cost-volume fusion, temporal attention, point attention, cross-attention, FFN.

    Attributes:
        corr_fuser: replaces the content by an MLP of [content, cost-volume samples], or
            None without the cost volume (ablation).

    Shape:
        content (B, W_t, N, C), query_pos (B, W_t, N, C), reference (B, W_t, N, 4),
        memory (B·W_t, S, C), correlation (B, W_t, N, K) → `LayerOutput`.
    """

    def __init__(
        self,
        cross_attention: DeformableAttention,
        temporal_attention: MultiheadAttention | None,
        point_attention: MultiheadAttention | None,
        d_model: int,
        ffn_dim: int,
        temperature: float,
        corr_fuser: MLP | None,
    ) -> None:
        """Creates the layer.

        Args:
            cross_attention: plain deformable attention to the memory.
            temporal_attention: attention across a point's frames, or None (ablation).
            point_attention: attention among a frame's points, or None (ablation).
            d_model: channels C.
            ffn_dim: FFN hidden width.
            temperature: sine temperature (unused without the position update).
            corr_fuser: the MLP fusing the content with the cost-volume samples, or None.
        """
        super().__init__(
            cross_attention,
            None,
            temporal_attention,
            point_attention,
            d_model,
            ffn_dim,
            temperature,
        )
        self.corr_fuser = corr_fuser

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
            update: (B, W_t, N) entries whose position may change (unused: no APU in v1).
            execution: how to run.
            correlation: (B, W_t, N, K) cost-volume samples at ``reference``, or None.
        """
        x = content
        if self.corr_fuser is not None and correlation is not None:
            fused = torch.cat((x, correlation), dim=-1)
            x = self.corr_fuser(fused, execution)  # replaces the content
        x = self._temporal(x, query_pos, masks.temporal, execution)
        x = self._points(x, query_pos, masks, execution)
        x, _ = self._cross(x, query_pos, reference, memory, spatial_shapes, execution)
        x = self.norm_ffn(x + self.ffn(x, execution))
        return LayerOutput(x, reference, None)


class V1Decoder(Decoder):
    """v1's stack: the v2 decoder's loop, embeddings and heads, plus the cost volume.

    `Decoder.forward` runs the layers; v1 overrides its hooks `prepare_window` (the cost
    volume's maps), `layer_input` (the updater from the first layer on) and `layer_extras`
    (the cost-volume samples at each layer's reference), and reports by `look_forward_twice`.

    Attributes:
        cost_volume: correlation of each point with its frame, or None (ablation).

    Shape:
        content (B, W_t, N, C), positions (B, W_t, N, 4) logits, memory (B·W_t, S, C),
        tracking and update masks (B, W_t, N) → `DecoderOutput`.
    """

    def __init__(
        self,
        layers: list[V1DecoderLayer],
        d_model: int,
        temperature: float,
        cost_volume: CostVolume | None,
    ) -> None:
        """Creates the decoder.

        Args:
            layers: the v1 decoder layers.
            d_model: channels C.
            temperature: sine temperature of the query position embedding.
            cost_volume: the correlation module, or None.
        """
        super().__init__(list(layers), d_model, temperature, None, look_forward_twice)
        self.cost_volume = cost_volume
        # the official module order puts the cost volume before the heads: it orders the
        # state dict and the optimiser's parameters, so existing training checkpoints resume
        for name in ("position_heads", "visibility_heads"):
            self._modules[name] = self._modules.pop(name)

    def prepare_window(
        self,
        content: Tensor,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        execution: Execution,
        tables: FrameTables | None = None,
    ) -> list[Tensor]:
        """v1: the cost volume's L maps (B·W_t, N, H_l, W_l) from the window-entry content.

        None without the cost volume. See `Decoder.prepare_window` for the arguments; v1's
        standard cross-attention has no key tables, so ``tables`` is not read.
        """
        if self.cost_volume is None:
            return []
        batch, frames, points, channels = content.shape
        flat_content = content.reshape(batch * frames, points, channels)
        return self.cost_volume.prepare(memory, spatial_shapes, flat_content, execution)

    def layer_input(self, index: int, out: Tensor, content: Tensor, execution: Execution) -> Tensor:
        """v1 applies the content updater from the first layer on (the index is unused)."""
        return self.update_layer_content(out, content, execution)

    def layer_extras(
        self, index: int, prepared: list[Tensor], reference: Tensor
    ) -> tuple[Tensor, ...]:
        """v1: the (B, W_t, N, K) cost-volume samples around the layer's input reference.

        Args:
            index: the layer (unused: every layer samples the same maps).
            prepared: the maps of `prepare_window` (none without the cost volume).
            reference: (B, W_t, N, 4) the layer's input reference in [0, 1].

        Returns:
            ``(correlation,)`` for `V1DecoderLayer.forward`, or nothing without the maps.
        """
        if self.cost_volume is None or not prepared:
            return ()
        batch, frames, points = reference.shape[:3]
        flat = reference[..., :2].reshape(batch * frames, points, 2)
        return (self.cost_volume.sample(prepared, flat).view(batch, frames, points, -1),)
