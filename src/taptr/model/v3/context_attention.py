"""TAPTRv3's context-aware cross-attention: patch similarity instead of point similarity.

TAPTRv2's key-aware attention scores each sampling location by the dot product of the
query with the key sampled there. TAPTRv3 compares patches instead. For one point, head
and sampling location:

1. the K × K patch of keys around the location (`taptr.model.ops.context_patches`);
2. the point's own K × K context, its initial content's neighbourhood on its start frame
   (`taptr.model.v3.context.ContextInitializer`), through the same query projection;
3. all K⁴ dot products between the two patches, unscaled, in (key x, key y, context x,
   context y) order;
4. a small MLP (K⁴ → K² → 1) turns them into the location's logit.

The softmax of the logits over each head's L·P locations weighs the values sampled at
the locations, as in TAPTRv2; the logits also drive the position update. The current
query's content moves the sampling locations (through the offsets) but takes no part in
the scores: the official code computes its projection and never reads it, and the
released weights were trained that way.
"""

from __future__ import annotations

import torch
from torch import Tensor

from taptr.model.attention import (
    DeformableOutput,
    KeyAwareDeformableAttention,
    project,
    sampling_locations,
)
from taptr.model.execution import Execution
from taptr.model.layers import MLP
from taptr.model.ops import deform_attn, value_table
from taptr.model.ops.context_patches import (
    gather_context_attn,
    key_table,
    query_chunks,
    sample_block,
    sample_key_patches,
)
from taptr.model.ops.gather import projected_table
from taptr.model.ops.memory_values import MemoryValues, values_after_sampling


class ContextAwareDeformableAttention(KeyAwareDeformableAttention):
    """Deformable cross-attention whose weights compare key patches with the point's context.

    Attributes:
        patch: side K of the compared patches.
        similarity: the MLP from the K⁴ patch dot products to one logit.

    Shape:
        query (B, Q, C), reference (B, Q, 2), memory (B, S, C), context (B, Q, K, K, C)
        → output (B, Q, C).
    """

    def __init__(
        self, d_model: int, num_heads: int, num_levels: int, num_points: int, patch: int
    ) -> None:
        super().__init__(d_model, num_heads, num_levels, num_points)
        self.patch = patch
        self.similarity = MLP(patch**4, patch**2, 1, 2)

    def forward(  # type: ignore[override]
        self,
        query: Tensor,
        reference: Tensor,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        execution: Execution,
        context: Tensor,
    ) -> DeformableOutput:
        """Attends from each query to values weighted by patch similarity.

        Args:
            query: (B, Q, C) queries, position embedding added (they set the offsets).
            reference: (B, Q, 2) reference (x, y) in [0, 1].
            memory: (B, S, C) flattened multi-scale tokens of one frame per batch entry.
            spatial_shapes: (H_l, W_l) of the L levels.
            execution: how to run; its ``kernel`` samples the keys and values.
            context: (B, Q, K, K, C) each point's initial context, [a][b] = (dx, dy).
        """
        batch, queries, _ = query.shape
        m, lv, p = self.num_heads, self.num_levels, self.num_points
        offsets = project(self.sampling_offsets, query, execution).view(batch, queries, m, lv, p, 2)
        locations = sampling_locations(reference, offsets, spatial_shapes)
        if execution.kernel == "gather":
            output, logits = self._gathered(locations, memory, spatial_shapes, execution, context)
        else:
            logits = self.logits(locations, memory, spatial_shapes, execution, context)
            values = value_table(
                execution.kernel,
                memory,
                self.value_proj,
                spatial_shapes,
                m,
                onednn=execution.onednn_linear,
            )
            weights = logits.softmax(-1).view(batch, queries, m, lv, p)
            output = deform_attn(execution.kernel, values, spatial_shapes, locations, weights)
        return DeformableOutput(
            project(self.output_proj, output, execution), logits.view(offsets.shape[:-1]), offsets
        )

    def _own(self, context: Tensor, execution: Execution) -> Tensor:
        """Step 2: the points' contexts (B, Q, K, K, C) projected, (B, Q, M, K², D) per head."""
        batch, queries = context.shape[:2]
        own = project(self.query_proj, context.flatten(2, 3), execution)  # (B, Q, K², C)
        return own.view(batch, queries, self.patch**2, self.num_heads, -1).transpose(2, 3)

    def _gathered(
        self,
        locations: Tensor,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        execution: Execution,
        context: Tensor,
    ) -> tuple[Tensor, Tensor]:
        """Output (B, Q, C) and logits (B, Q, M, L·P) by the ``gather`` kernel's row gathers."""
        heads, onednn = self.num_heads, execution.onednn_linear
        keys = key_table("gather", memory, self.key_proj, spatial_shapes, heads, onednn=onednn)
        values: Tensor | MemoryValues
        if self._values_after_sampling(locations, memory, execution):
            values = MemoryValues(memory, self.value_proj)
        else:
            values = projected_table(
                memory,
                self.value_proj,
                spatial_shapes,
                heads,
                border=False,
                onednn=onednn,
                bfloat16_rows=False,
            )
        return gather_context_attn(
            keys,
            values,
            self._own(context, execution),
            spatial_shapes,
            locations,
            lambda products: self.similarity(products, execution).squeeze(-1),
            sample_block(execution, memory),
        )

    def _values_after_sampling(
        self, locations: Tensor, memory: Tensor, execution: Execution
    ) -> bool:
        """Whether to sample the memory before projecting the values (shapes only)."""
        if not execution.values_after_sampling:
            return False
        batch, queries, heads, levels, points = locations.shape[:5]
        return values_after_sampling(
            batch * queries,
            levels * points,
            memory.shape[0] * memory.shape[1],
            memory.shape[2],
            heads,
        )

    def logits(
        self,
        locations: Tensor,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        execution: Execution,
        context: Tensor,
    ) -> Tensor:
        """Steps 1-4: (B, Q, M, L·P) logits of the locations (B, Q, M, L, P, 2).

        Queries are taken in chunks, so that their K² samples per location (nine times
        the value samples) are never all held at once.
        """
        batch, queries, heads, levels, points = locations.shape[:5]
        k2 = self.patch**2
        keys = key_table(
            execution.kernel,
            memory,
            self.key_proj,
            spatial_shapes,
            heads,
            onednn=execution.onednn_linear,
        )
        own = self._own(context, execution)  # (B, Q, M, K², D)
        per_query = batch * heads * levels * points * k2 * own.shape[-1]
        logits = []
        for part in query_chunks(queries, per_query):
            sampled = sample_key_patches(
                execution.kernel, keys, spatial_shapes, locations[:, part], self.patch
            )
            sampled = sampled.unflatten(3, (levels * points, k2))  # (B, q, M, L·P, K², D)
            # bfloat16 key rows (`dense.bfloat16_products`) give bfloat16 samples
            sampled = sampled.to(own.dtype)
            products = torch.einsum("bqmjxd,bqmyd->bqmjxy", sampled, own[:, part])
            logits.append(self.similarity(products.flatten(-2), execution).squeeze(-1))
        return torch.cat(logits, dim=1)  # (B, Q, M, L·P)
