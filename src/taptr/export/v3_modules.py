"""Export-friendly wrappers around TAPTRv3's per-frame pieces, all state explicit.

TAPTRv3's driver (`taptr.model.v3.per_frame`) is bookkeeping around three tensor
functions; each wrapper below is one of them with plain tensor inputs and outputs and
batch size one, so that it can be exported and driven by a loop written in any language
(`taptr.export.v3_loop` is that loop in numpy):

- the frame encoder is TAPTRv2's (`taptr.export.modules.FrameEncoder`);
- `PointStarter`: the content and context of points on their start frame;
- `FrameStep`: the decoder on one frame, reading every per-point state as an input (the
  carried positions, the frame's visibility before decoding, the initial content and
  context, the start frames, the whole history buffer with its slots' frames and which
  of them hold one) and returning the new state, masked as the driver masks it.

The history is read as the static step reads it (`taptr.model.v3.per_frame.buffer_held`):
the whole buffer, slots that hold no frame out of the softmax, so that the loop keeps one
buffer and writes one slot per frame instead of handing the graph a copy.
"""

from __future__ import annotations

import torch
from torch import Tensor

from taptr.export.modules import _OnMemory
from taptr.export.v3_attention import pack_memory, uses_packed_memory
from taptr.model.execution import Execution
from taptr.model.v3.per_frame import buffer_held
from taptr.model.v3.taptr import TAPTRv3

EXPORT_EXECUTION = Execution(
    "export",
    "grid_sample",
    grouped_point_attention=False,
    row_block=None,
    history_products=True,
    sample_block=None,
)
"""How the exported graphs compute: ``grid_sample`` (``embedding_bag`` with per-sample
weights has no ONNX counterpart), the N × N point-attention mask (no data-dependent
sizes), no row or query blocks (their count would depend on the dynamic sizes), and the
long-temporal attention by query products (`taptr.model.ops.history_attention`: about 30
times fewer products than projecting every held frame)."""


class PointStarter(_OnMemory):
    """Content and context of points on their start frame.

    Shape:
        memory (S, C) of the frame, positions (N, 2) normalised → content (N, C),
        context (N, K, K, C).
    """

    def forward(self, memory: Tensor, positions: Tensor) -> tuple[Tensor, Tensor]:
        """Samples the frame's memory around each point and projects the samples.

        Args:
            memory: (S, C) encoder memory of the points' start frame.
            positions: (N, 2) normalised (x, y), i.e. pixels / (W − 1, H − 1).
        """
        model = self.model
        assert isinstance(model, TAPTRv3)
        content, context = model.point_queries(memory[None], self.spatial_shapes, positions[None])
        assert context is not None
        return content[0], context[0]  # (N, C), (N, K, K, C)


class PointStarterWithoutContext(_OnMemory):
    """`PointStarter` of a model without the context-aware attention: content only.

    Shape:
        memory (S, C), positions (N, 2) → content (N, C).
    """

    def forward(self, memory: Tensor, positions: Tensor) -> Tensor:
        """The points' initial content (N, C); see `PointStarter.forward`."""
        model = self.model
        assert isinstance(model, TAPTRv3)
        return model.point_queries(memory[None], self.spatial_shapes, positions[None])[0][0]


class FrameStep(_OnMemory):
    """The decoder on one frame with every per-point state as an input and an output.

    Shape:
        memory (S, C), frame (), start_frames (N,), initial_content (N, C), context
        (N, K, K, C), positions (N, 4), visibility (N, 3), history_content (N, H, C),
        history_visibility (N, H), slot_frames (H,), slot_held (H,) → positions (N, 4),
        visibility (N, 3), features (N, C).
    """

    def forward(
        self,
        memory: Tensor,
        frame: Tensor,
        start_frames: Tensor,
        initial_content: Tensor,
        context: Tensor | None,
        positions: Tensor,
        visibility: Tensor,
        history_content: Tensor,
        history_visibility: Tensor,
        slot_frames: Tensor,
        slot_held: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Decodes ``frame`` and returns the state after it.

        Args:
            memory: (S, C) the frame's encoder memory.
            frame: () int64 the frame's index (any origin shared with the start frames).
            start_frames: (N,) int64 each point's start frame.
            initial_content: (N, C) each point's initial content (zeros before it starts).
            context: (N, K, K, C) each point's initial context, or None without the
                context-aware attention.
            positions: (N, 4) position logits carried from the previous frame.
            visibility: (N, 3) the frame's visibility logits before decoding (those of a
                frame the model does not write).
            history_content: (N, H, C) the history buffer's content, slots in any order.
            history_visibility: (N, H) float32 the slots' last-layer logits (channel 1).
            slot_frames: (H,) int64 the frame each slot holds.
            slot_held: (H,) bool, slots that hold a frame (the decoded one included).

        Returns:
            positions (N, 4) and visibility (N, 3): the decoded last layer's where the
            point is past its start frame, the inputs elsewhere; features (N, C): the last
            layer's head features of every point, the frame's new history content.
        """
        model = self.model
        assert isinstance(model, TAPTRv3)
        starts = start_frames[None]  # (1, N)
        update = starts < frame  # (1, N)
        held = buffer_held(
            model,
            slot_frames,
            ~slot_held,
            frame,
            starts,
            history_content[None],  # (1, N, H, C)
            history_visibility[None],
        )
        packed = uses_packed_memory(model)  # the packed layers read it packed, once a frame
        decoded = model.decode_frame(
            pack_memory(memory[None], self.spatial_shapes) if packed else memory[None],
            self.spatial_shapes,
            initial_content[None, None],  # (1, 1, N, C)
            positions[None, None],
            (starts <= frame)[:, None],  # (1, 1, N)
            update[:, None],
            held,
            None if context is None else context[None],
            all_tracked=False,  # the N × N mask: which points are tracked is an input
        )
        step = update[0, :, None]  # (N, 1)
        new_positions = torch.where(step, decoded.positions[-1, 0, 0], positions)
        new_visibility = torch.where(step, decoded.visibility_logits[-1, 0, 0].float(), visibility)
        return new_positions, new_visibility, decoded.features[0, 0]


class FrameStepWithoutContext(FrameStep):
    """`FrameStep` of a model without the context-aware attention (no ``context`` input)."""

    def forward(  # type: ignore[override]
        self,
        memory: Tensor,
        frame: Tensor,
        start_frames: Tensor,
        initial_content: Tensor,
        positions: Tensor,
        visibility: Tensor,
        history_content: Tensor,
        history_visibility: Tensor,
        slot_frames: Tensor,
        slot_held: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """`FrameStep.forward` without ``context``."""
        return super().forward(
            memory,
            frame,
            start_frames,
            initial_content,
            None,
            positions,
            visibility,
            history_content,
            history_visibility,
            slot_frames,
            slot_held,
        )
