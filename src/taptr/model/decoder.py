"""The TAPTRv2 point decoder: refines every point query on every frame of one window.

One layer, in the official order: deformable cross-attention to the frame's memory with
the attention-based position update (APU, `taptr.model.position_update`) → re-embedding
of the moved position → temporal self-attention across the window's frames of each point
→ self-attention among the points of each frame → FFN, each post-normed. After every layer
the decoder fuses the APU displacement into the features that the per-layer position and
visibility heads read.

TAPTR (v1) subclasses these modules in `taptr.model.v1`, overriding `Decoder`'s hooks.

Tracked and untracked entries (a point before its start frame) never attend to each other,
so untracked entries run through the network without affecting anything that is kept. The
execution (`taptr.model.execution.Execution`) is an argument of every forward; the code
here is the reference formulation and calls `taptr.model.ops` where the execution says so.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor, nn

from taptr.model.attention import (
    DeformableAttention,
    DeformableOutput,
    KeyAwareDeformableAttention,
    MultiheadAttention,
)
from taptr.model.execution import Execution
from taptr.model.frame_tables import FrameTables, LayerTables, window_store
from taptr.model.layers import MLP
from taptr.model.masks import AttentionMasks, attention_masks
from taptr.model.ops import tracked_point_attention
from taptr.model.position_encoding import point_embedding
from taptr.model.position_update import (
    PositionUpdate,
    Refined,
    RefinementRule,
    fuse_displacement,
    move_reference,
)


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
    """TAPTRv2's layer: cross-attention (+ APU), temporal attention, point attention, FFN.

    Attributes:
        cross_attention: deformable attention from each point to its frame's memory.
        position_update: the APU, which moves each point's reference by the displacement
            its cross-attention implies, or None (ablation, and v1).
        position_embed: re-embeds the moved reference as the query position for the rest
            of the layer (present with the APU only).
        temporal_attention: attention across a point's frames, or None (ablation).
        point_attention: attention among a frame's points, or None (ablation).
        ffn: the feed-forward block.

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
        self.temperature = temperature

    def forward(
        self,
        content: Tensor,
        query_pos: Tensor,
        reference: Tensor,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        masks: AttentionMasks,
        update: Tensor,
        execution: Execution,
        tables: LayerTables | None = None,
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
            execution: how to run.
            tables: where the key-aware cross-attention's key and value tables come from
                (`Decoder.prepare_window`), or None to make them from ``memory``.
        """
        extra = (tables,) if isinstance(self.cross_attention, KeyAwareDeformableAttention) else ()
        x, attended = self._cross(
            content, query_pos, reference, memory, spatial_shapes, execution, *extra
        )
        reference, displacement, query_pos = self._move(
            x, attended, query_pos, reference, spatial_shapes, update, execution
        )
        x = self._temporal(x, query_pos, masks.temporal, execution)
        x = self._points(x, query_pos, masks, execution)
        x = self.norm_ffn(x + self.ffn(x, execution))
        return LayerOutput(x, reference, displacement)

    def _cross(
        self,
        x: Tensor,
        query_pos: Tensor,
        reference: Tensor,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        execution: Execution,
        *extra: object,
    ) -> tuple[Tensor, DeformableOutput]:
        """Post-normed cross-attention; returns (B, W_t, N, C) and the attention's output.

        ``extra`` goes to the attention after the common arguments: the key-aware
        attention's tables (see `DecoderLayer.forward`), TAPTRv3's point contexts.
        """
        batch, frames, points, channels = x.shape
        flat = x.reshape(batch * frames, points, channels)  # (B·W_t, N, C)
        query = flat + query_pos.reshape(batch * frames, points, channels)
        reference_xy = reference[..., :2].reshape(batch * frames, points, 2)
        attended = self.cross_attention(
            query, reference_xy, memory, spatial_shapes, execution, *extra
        )
        x = self.norm_cross(flat + attended.output).view(batch, frames, points, channels)
        return x, attended

    def _move(
        self,
        x: Tensor,
        attended: DeformableOutput,
        query_pos: Tensor,
        reference: Tensor,
        spatial_shapes: list[tuple[int, int]],
        update: Tensor,
        execution: Execution,
    ) -> tuple[Tensor, Tensor | None, Tensor]:
        """The APU's steps 1-3 (`taptr.model.position_update`), then the re-embedding.

        Returns the moved reference (B, W_t, N, 4), the masked displacement (B, W_t, N, 2)
        and the new query position (B, W_t, N, C); without the APU, the inputs unchanged
        and no displacement.
        """
        if self.position_update is None or self.position_embed is None:
            return reference, None, query_pos
        delta = self.position_update(attended.logits, attended.offsets, spatial_shapes, execution)
        reference, displacement = move_reference(
            reference, delta.view(*reference.shape[:-1], 2), update
        )
        embedded = point_embedding(reference, x.shape[-1] // 2, self.temperature)
        return reference, displacement, self.position_embed(embedded, execution)

    def _temporal(
        self, x: Tensor, query_pos: Tensor, allowed: Tensor | None, execution: Execution
    ) -> Tensor:
        if self.temporal_attention is None or self.norm_temporal is None:
            return x
        batch, frames, points, channels = x.shape
        q = (x + query_pos).transpose(1, 2).reshape(batch * points, frames, channels)
        v = x.transpose(1, 2).reshape(batch * points, frames, channels)  # (B·N, W_t, C)
        attended = self.temporal_attention(q, q, v, allowed, onednn=execution.onednn_linear)
        x = self.norm_temporal(v + attended)
        return x.view(batch, points, frames, channels).transpose(1, 2)

    def _points(
        self, x: Tensor, query_pos: Tensor, masks: AttentionMasks, execution: Execution
    ) -> Tensor:
        if self.point_attention is None or self.norm_points is None:
            return x
        batch, frames, points, channels = x.shape
        q = (x + query_pos).reshape(batch * frames, points, channels)
        v = x.reshape(batch * frames, points, channels)  # (B·W_t, N, C)
        attention = functools.partial(self.point_attention, onednn=execution.onednn_linear)
        if masks.spatial is None and not masks.everything:
            x = tracked_point_attention(attention, self.norm_points, q, v, masks.frame_tracking)
        else:
            x = self.norm_points(v + attention(q, q, v, masks.spatial))
        return x.view(batch, frames, points, channels)


class Decoder(nn.Module):
    """TAPTRv2's stack of layers with the shared query embedding and the per-layer heads.

    Attributes:
        layers: the decoder layers.
        position_embed: embeds each layer's input reference as its query position.
        content_updater: U of a layer's input out + U([out, content]) from the previous
            layer's output and the window-entry content (from layer 1 on; v1 from layer 0).
        update_fuser: fuses the APU displacement's embedding into the features the heads
            read (`taptr.model.position_update.fuse_displacement`); it updates nothing.
            None without the APU.
        position_heads: per layer, δ in logit space from the head features.
        visibility_heads: per layer, 3 visibility logits from the head features.
        refine: the rule that turns δ into reported positions and the next reference.

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
        refine: RefinementRule,
    ) -> None:
        """Creates the decoder.

        Args:
            layers: the decoder layers.
            d_model: channels C.
            temperature: sine temperature of the query position embedding.
            update_fuser: TAPTRv2's fusion of the APU displacement into the head features.
            refine: `taptr.model.position_update.refine_updated` with the APU, else
                `taptr.model.v1.decoder.look_forward_twice`.
        """
        super().__init__()
        self.layers = nn.ModuleList(layers)
        self.position_embed = MLP(2 * d_model, d_model, d_model, 2)
        self.content_updater = MLP(2 * d_model, d_model, d_model, 2)
        self.update_fuser = update_fuser
        self.position_heads = nn.ModuleList(MLP(d_model, d_model, 4, 3) for _ in layers)
        self.visibility_heads = nn.ModuleList(nn.Linear(d_model, 3) for _ in layers)
        self.d_model = d_model
        self.temperature = temperature
        self.refine = refine

    @property
    def has_position_update(self) -> bool:
        """Whether the layers move positions inside cross-attention (APU)."""
        return self.layers[0].position_update is not None

    def query_position(self, reference: Tensor, execution: Execution) -> Tensor:
        """Query position embedding of a reference (B, W_t, N, 4) in [0, 1]; (B, W_t, N, C)."""
        embedded = point_embedding(reference, self.d_model // 2, self.temperature)
        return self.position_embed(embedded, execution)

    def update_layer_content(self, out: Tensor, content: Tensor, execution: Execution) -> Tensor:
        """A layer's input: the previous output plus ``content_updater``'s update."""
        return out + self.content_updater(torch.cat((out, content), -1), execution)

    def prepare_window(
        self,
        content: Tensor,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        execution: Execution,
        tables: FrameTables | None = None,
    ) -> list[Tensor] | list[FrameTables]:
        """What is prepared once per window for `layer_extras`.

        TAPTRv2 at inference with the ``gather`` kernel and ``execution.shared_tables``:
        the store of key and value tables per frame and layer, ``tables`` or a throwaway one
        (`taptr.model.frame_tables`). Otherwise (also under autocast, whose products come
        out in another dtype, and inside ``torch.compile``) nothing: each layer projects
        the whole window's memory.

        Args:
            content: (B, W_t, N, C) content at window entry.
            memory: (B·W_t, S, C) encoder memory of the window's frames.
            spatial_shapes: (H_l, W_l) per level.
            execution: how to run.
            tables: the tracking run's store, started for this window, or None.
        """
        key_aware = isinstance(self.layers[0].cross_attention, KeyAwareDeformableAttention)
        gather = execution.shared_tables and execution.kernel == "gather"
        autocast = torch.is_autocast_enabled(memory.device.type)
        # a compiled graph would not replay the store's bookkeeping (kept and reused tables)
        compiling = torch.compiler.is_compiling()
        if not gather or not key_aware or torch.is_grad_enabled() or autocast or compiling:
            return []
        return [window_store(tables, content.shape[1])]

    def layer_input(self, index: int, out: Tensor, content: Tensor, execution: Execution) -> Tensor:
        """Layer ``index``'s input (B, W_t, N, C) from the previous output and entry content.

        The first layer reads ``out`` (the window-entry content) as it is, the later ones
        ``out`` updated by `update_layer_content`.
        """
        return out if index == 0 else self.update_layer_content(out, content, execution)

    def layer_extras(
        self, index: int, prepared: list[Tensor] | list[FrameTables], reference: Tensor
    ) -> tuple[Tensor | LayerTables, ...]:
        """Layer ``index``'s arguments after the common ones: its view of the tables, if any.

        ``prepared`` is what `prepare_window` returned, ``reference`` (B, W_t, N, 4) in [0, 1].
        """
        return tuple(LayerTables(store, index) for store in prepared)

    def read_heads(
        self, index: int, result: LayerOutput, previous: Tensor, step: Tensor, execution: Execution
    ) -> tuple[Refined, Tensor, Tensor]:
        """Layer ``index``'s heads on its output.

        Args:
            index: the layer.
            result: its output.
            previous: (B, W_t, N, 4) the previous layer's undetached positions in [0, 1].
            step: (B, W_t, N, 1) 1 where positions may change, else 0.
            execution: how to run.

        Returns:
            The refined positions, (B, W_t, N, 3) visibility logits and the (B, W_t, N, C)
            features the heads read.
        """
        features = fuse_displacement(
            self.update_fuser, result.content, result.displacement, self.temperature, execution
        )
        delta = self.position_heads[index](features, execution) * step
        refined = self.refine(delta, result.reference, previous)
        return refined, self.visibility_heads[index](features), features

    def forward(
        self,
        content: Tensor,
        positions: Tensor,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        tracking: Tensor,
        update: Tensor,
        execution: Execution,
        tables: FrameTables | None = None,
        all_tracked: bool | None = None,
    ) -> DecoderOutput:
        """Decodes one window.

        Args:
            content: (B, W_t, N, C) content at window entry.
            positions: (B, W_t, N, 4) position logits at window entry.
            memory: (B·W_t, S, C) encoder memory of the window's frames.
            spatial_shapes: (H_l, W_l) per level.
            tracking: (B, W_t, N) entries at or after each point's start frame.
            update: (B, W_t, N) tracking entries after the start frame.
            execution: how to run.
            tables: the tracking run's key and value tables, started for this window
                (`taptr.model.frame_tables.FrameTables.start_window`), or None.
            all_tracked: every entry of ``tracking`` is set (known on the host), or None
                to read it.
        """
        grouped = execution.grouped_point_attention
        # ungrouped attention keeps its full masks, as before (the reference execution)
        masks = attention_masks(tracking, grouped, all_tracked if grouped else None)
        prepared = self.prepare_window(content, memory, spatial_shapes, execution, tables)
        return self.run_layers(
            content,
            positions,
            memory,
            spatial_shapes,
            masks,
            update,
            execution,
            lambda index, reference: self.layer_extras(index, prepared, reference),
        )

    def run_layers(
        self,
        content: Tensor,
        positions: Tensor,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        masks: AttentionMasks,
        update: Tensor,
        execution: Execution,
        extras: Callable[[int, Tensor], tuple[object, ...]],
    ) -> DecoderOutput:
        """The layers in turn, each reading the heads' refined reference of the last.

        Args:
            content: (B, W_t, N, C) content at window entry.
            positions: (B, W_t, N, 4) position logits at window entry.
            memory: (B·W_t, S, C) encoder memory of the window's frames.
            spatial_shapes: (H_l, W_l) per level.
            masks: which entries may attend to each other.
            update: (B, W_t, N) tracking entries after the start frame.
            execution: how to run.
            extras: (layer index, its input reference (B, W_t, N, 4) in [0, 1]) → the
                layer's arguments after the common ones.
        """
        step = update.unsqueeze(-1).to(content.dtype)
        reference = positions.sigmoid()
        previous = reference
        out, features = content, content
        outputs = LayerOutputs()
        for index, layer in enumerate(self.layers):
            query_pos = self.query_position(reference, execution)
            x = self.layer_input(index, out, content, execution)
            result = layer(
                x,
                query_pos,
                reference,
                memory,
                spatial_shapes,
                masks,
                update,
                execution,
                *extras(index, reference),
            )
            out = result.content
            refined, visibility, features = self.read_heads(
                index, result, previous, step, execution
            )
            outputs.add(refined, visibility)
            reference, previous = refined.reference, refined.previous
        return outputs.stacked(features)


class LayerOutputs:
    """Collects the per-layer outputs of one window."""

    def __init__(self) -> None:
        self.positions: list[Tensor] = []
        self.visibility: list[Tensor] = []
        self.updated: list[Tensor] = []

    def add(self, refined: Refined, visibility: Tensor) -> None:
        """Appends one layer's refined positions and (B, W_t, N, 3) visibility logits."""
        self.positions.append(refined.positions)
        self.visibility.append(visibility)
        if refined.updated is not None:
            self.updated.append(refined.updated)

    def stacked(self, features: Tensor) -> DecoderOutput:
        """The window's `DecoderOutput`, with the last layer's head ``features``."""
        return DecoderOutput(
            torch.stack(self.positions),
            torch.stack(self.visibility),
            torch.stack(self.updated) if self.updated else None,
            features,
        )
