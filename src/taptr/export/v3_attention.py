"""TAPTRv3's context-aware cross-attention in a formulation onnxruntime runs fast.

The same function as `taptr.model.v3.context_attention.ContextAwareDeformableAttention`
(up to float rounding), arranged for ONNX operators, whose ``GridSample`` returns
channels-first samples:

1. **One image of all levels.** The frame's memory is packed once into one
   channels-first image (`pack_memory`), each level at its own origin with a row and a
   column of zeros around it (`packed_layout`, shelves left to right). Each layer
   projects the packed memory into its keys and values per head directly in
   ``GridSample``'s layout (the zeros kept zero), and a location's pixel in its level,
   clamped to [−1, size] per axis, is moved to its level's origin: bilinear sampling
   there reads the level's cells or the zeros around it, exactly as zero padding outside
   the level does (beyond one cell outside, both cells are zeros either way). One
   ``GridSample`` per layer for the keys and one for the values, instead of one per
   level, each followed by layout copies and a concatenation.
2. **The similarity's first layer folded into the context.** The K⁴ patch products p
   (key patch point x, context point y) enter the similarity MLP's first layer W₁:
   h = Σ_{x,y} W₁[h, x, y] Σ_d k[x, d] c[y, d] = Σ_{x,d} G[h, x, d] k[x, d] with
   G[h, x, d] = Σ_y W₁[h, x, y] c[y, d], made once per point and head. The samples are
   taken with x outermost, so that one transpose of rows of L·P contiguous samples turns
   them into a (K²·D × L·P) matrix per point and head, and the first layer is one batched
   product with G: the products are never formed.

`packed_model` swaps these in for every decoder layer of an export copy, whose frame step
(`taptr.export.v3_modules.FrameStep`) then hands the decoder the packed memory.

Shapes: B batch, Q queries, M heads, L levels, P points per level, K patch side, D
channels per head, J = L·P locations.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from taptr.model.attention import DeformableOutput, project, sampling_locations
from taptr.model.execution import Execution
from taptr.model.ops.context_patches import patch_locations
from taptr.model.v3.context_attention import ContextAwareDeformableAttention
from taptr.model.v3.taptr import TAPTRv3


class PackedLayout(NamedTuple):
    """Where each level sits in the packed image.

    Attributes:
        origins: (row, column) of each level's first cell.
        size: (H_p, W_p) of the image.
        index: (H_p · W_p,) int64 token of each pixel, S (one past the last) for the zeros.
    """

    origins: list[tuple[int, int]]
    size: tuple[int, int]
    index: list[int]


def packed_layout(spatial_shapes: list[tuple[int, int]]) -> PackedLayout:
    """Levels on shelves, left to right, each framed by zero rows and columns.

    The image is as wide as the widest level plus two zero columns; a level goes right
    of the previous one when it fits, else on a new shelf below. Neighbours share the
    zero column between them.
    """
    width = max(w for _, w in spatial_shapes) + 2
    origins, row, column, shelf = [], 1, 1, 0
    for height, level_width in spatial_shapes:
        if column + level_width + 1 > width:  # no room left on this shelf
            row, column, shelf = row + shelf + 1, 1, 0
        origins.append((row, column))
        column += level_width + 1
        shelf = max(shelf, height)
    size = (row + shelf + 1, width)
    tokens = sum(h * w for h, w in spatial_shapes)
    index = [tokens] * (size[0] * size[1])
    first = 0
    for (top, left), (height, level_width) in zip(origins, spatial_shapes, strict=True):
        for y in range(height):
            start = (top + y) * width + left
            index[start : start + level_width] = range(first, first + level_width)
            first += level_width
    return PackedLayout(origins, size, index)


def pack_memory(memory: Tensor, spatial_shapes: list[tuple[int, int]]) -> Tensor:
    """Tokens (B, S, C) → the packed image's pixels (B, H_p · W_p, C), zeros around levels."""
    layout = packed_layout(spatial_shapes)
    index = torch.tensor(layout.index, device=memory.device)
    return F.pad(memory, (0, 0, 0, 1)).index_select(1, index)  # token S is zero


def project_packed(
    layer: nn.Linear, packed: Tensor, spatial_shapes: list[tuple[int, int]]
) -> Tensor:
    """``layer`` on every pixel of a packed image, channels first: (B, C, H_p · W_p).

    Zeros around the levels stay zero. The weight multiplies the transposed pixels, a
    product onnxruntime runs without copying them.
    """
    inside = torch.tensor(packed_layout(spatial_shapes).index, device=packed.device)
    inside = (inside < sum(h * w for h, w in spatial_shapes)).to(packed.dtype)  # (H_p · W_p,)
    return (layer.weight @ packed.transpose(1, 2) + layer.bias[:, None]) * inside


class PackedGrid:
    """``GridSample`` coordinates in the packed image of locations in their levels.

    A location's pixel in its level (align_corners=False: location · size − 0.5) is
    clamped to [−1, size], moved to the level's origin and normalised by the packed
    image's size. Every step is one affine map or a clamp per column of a (R, columns)
    matrix, with constant (columns,) rows: onnxruntime runs those as fast row
    broadcasts, where the broadcasting of small per-level tables over a rank-7 tensor ran
    several times slower.

    Args:
        spatial_shapes: (H_l, W_l) per level.
        points: P, locations per level and head.
        like: a tensor of the dtype and device to make the constants in.
    """

    def __init__(self, spatial_shapes: list[tuple[int, int]], points: int, like: Tensor) -> None:
        origins, (height, width), _ = packed_layout(spatial_shapes)
        # columns (l, p, c): a level's size, and the affine map of its pixels into the image
        sizes = [xy for h, w in spatial_shapes for _ in range(points) for xy in (w, h)]
        shift = [
            value
            for r, c in origins
            for _ in range(points)
            for value in ((2 * c + 1) / width - 1, (2 * r + 1) / height - 1)
        ]
        self.sizes = like.new_tensor(sizes)  # (L·P·2,)
        self.scale = like.new_tensor([2 / width, 2 / height] * (len(sizes) // 2))
        self.shift = like.new_tensor(shift)
        self.spatial_shapes = spatial_shapes
        self.points = points

    def centres(self, locations: Tensor) -> Tensor:
        """(R, L·P·2) locations, columns (l, p, x/y) → (R, L·P·2) grid coordinates."""
        return self._normalised(locations * self.sizes - 0.5, self.sizes)

    def patches(self, locations: Tensor, patch: int) -> Tensor:
        """(R, L·P·2) patch centres → (R, K²·L·P·2) grid coordinates, columns (x, l, p, c).

        The patch points are placed by `taptr.model.ops.context_patches.patch_locations`
        (its steps of one level pixel), here in pixels: location · size + step · size.
        """
        levels = len(self.spatial_shapes)
        zero = locations.new_zeros(1, 1, 1, levels, 1, 2)
        steps = patch_locations(zero, self.spatial_shapes, patch)[0, 0, 0]  # (L, K², 2)
        sizes = self.sizes.view(levels, self.points, 2)[:, :1]  # (L, 1, 2)
        step_pixels = (steps * sizes).transpose(0, 1)[:, :, None]  # (K², L, 1, 2)
        shift = (step_pixels - 0.5).expand(-1, -1, self.points, -1).flatten()  # (K²·L·P·2,)
        columns = len(self.sizes)
        eye = torch.eye(columns, dtype=locations.dtype, device=locations.device)
        spread = (eye * self.sizes).repeat(1, patch**2)  # (L·P·2, K²·L·P·2)
        return self._normalised(locations @ spread + shift, self.sizes.repeat(patch**2))

    def _normalised(self, pixels: Tensor, sizes: Tensor) -> Tensor:
        """Pixels (R, columns) in their levels → clamped, packed, normalised coordinates."""
        repeat = pixels.shape[-1] // len(self.sizes)
        clamped = torch.minimum(pixels.clamp(min=-1.0), sizes)
        return clamped * self.scale.repeat(repeat) + self.shift.repeat(repeat)


def _sample(image: Tensor, grid: Tensor) -> Tensor:
    """``GridSample`` of (B·M, D, H_p, W_p) at (B·M, Q, J, 2) → (B·M, D, Q, J)."""
    return F.grid_sample(image, grid, mode="bilinear", padding_mode="zeros", align_corners=False)


class PackedContextAttention(ContextAwareDeformableAttention):
    """`ContextAwareDeformableAttention` through one packed image (module docstring).

    Shape:
        query (B, Q, C), reference (B, Q, 2), packed memory (B, H_p · W_p, C), context
        (B, Q, K, K, C) → output (B, Q, C).
    """

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

        Args: as `ContextAwareDeformableAttention.forward`, except ``memory``: the frame's
        memory packed by `pack_memory`, (B, H_p · W_p, C).
        """
        batch, queries, _ = query.shape
        m, lv, p = self.num_heads, self.num_levels, self.num_points
        offsets = project(self.sampling_offsets, query, execution).view(batch, queries, m, lv, p, 2)
        locations = sampling_locations(reference, offsets, spatial_shapes)  # (B, Q, M, L, P, 2)
        grid = PackedGrid(spatial_shapes, p, locations)
        flat = locations.transpose(1, 2).reshape(batch * m * queries, -1)  # (B·M·Q, L·P·2)
        (height, width), channels = packed_layout(spatial_shapes).size, memory.shape[2]
        images = (batch * m, channels // m, height, width)  # (B·M, D, H_p, W_p)
        keys = project_packed(self.key_proj, memory, spatial_shapes).view(images)
        patches = grid.patches(flat, self.patch)
        logits = self._packed_logits(patches, keys, context, execution)
        weights = logits.softmax(-1).permute(0, 2, 1, 3).reshape(batch * m, 1, queries, -1)
        values = project_packed(self.value_proj, memory, spatial_shapes).view(images)
        centres = grid.centres(flat).view(batch * m, queries, lv * p, 2)
        sampled = _sample(values, centres)  # (B·M, D, Q, J)
        output = (sampled * weights).sum(-1)  # (B·M, D, Q)
        output = output.view(batch, -1, queries).transpose(1, 2)  # (B, Q, M·D)
        return DeformableOutput(
            project(self.output_proj, output, execution), logits.view(offsets.shape[:-1]), offsets
        )

    def _packed_logits(
        self, grid: Tensor, keys: Tensor, context: Tensor, execution: Execution
    ) -> Tensor:
        """(B, Q, M, J) logits from the packed keys (module docstring).

        Args:
            grid: (B·M·Q, K²·J·2) patch points in packed grid coordinates, x outermost.
            keys: the packed key image (B·M, D, H_p, W_p).
            context: (B, Q, K, K, C) the points' initial contexts.
            execution: how the projections run.
        """
        batch, queries = context.shape[:2]
        heads, channels = keys.shape[0] // batch, keys.shape[1]
        k2 = self.patch**2
        grid = grid.view(batch * heads, queries, -1, 2)
        sampled = _sample(keys, grid).view(batch * heads, channels, queries, k2, -1)
        # (B·M, D, Q, K², J) → (B·M·Q, K²·D, J): rows of J contiguous samples move
        sampled = sampled.permute(0, 2, 3, 1, 4).reshape(batch * heads * queries, k2 * channels, -1)
        first, second = self.similarity.layers
        own = self._own(context, execution).transpose(1, 2)  # (B, M, Q, K², D)
        # G[(h, x), d] = Σ_y W₁[h, x, y] c[y, d]: (K²·K², K²) by (K², D) per point and head
        fold = first.weight.view(k2 * k2, k2) @ own.reshape(-1, k2, channels)
        hidden = fold.view(-1, k2, k2 * channels) @ sampled  # (B·M·Q, K², J)
        hidden = (hidden + first.bias[:, None]).relu()  # (B·M·Q, K², J)
        logits = (second.weight @ hidden).squeeze(1) + second.bias  # (B·M·Q, J)
        return logits.view(batch, heads, queries, -1).transpose(1, 2)  # (B, Q, M, J)


def packed_model(model: TAPTRv3) -> TAPTRv3:
    """Swaps every decoder layer's context-aware attention for `PackedContextAttention`.

    In place, on an export copy (`taptr.export.v3_graphs.prepare_v3`); the parameters are
    the same objects. A decoder without the context-aware attention keeps its own. (The
    encoder keeps its per-level sampling: one ``GridSample`` over the packed image of all
    16,320 tokens' samples ran half as fast as four over the levels' own images.)
    """
    for layer in model.decoder.layers:
        attention = layer.cross_attention
        if isinstance(attention, ContextAwareDeformableAttention):
            attention.__class__ = PackedContextAttention
    return model


def uses_packed_memory(model: TAPTRv3) -> bool:
    """Whether ``model``'s decoder reads the packed memory (`packed_model` swapped it in)."""
    return isinstance(model.decoder.layers[0].cross_attention, PackedContextAttention)
