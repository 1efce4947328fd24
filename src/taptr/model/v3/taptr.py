"""The TAPTRv3 module: TAPTRv2's per-frame encoding, a per-frame decoder, no frame loop.

`point_queries` builds each point's content and context on its start frame;
`decode_frame` runs the decoder on one frame. The loop over frames lives in
`taptr.model.v3.per_frame`.
"""

from __future__ import annotations

from typing import Any

from torch import Tensor

from taptr.config import ModelConfig
from taptr.model.backbone import Backbone, InputProjections
from taptr.model.decoder import DecoderOutput
from taptr.model.encoder import Encoder
from taptr.model.execution import DEFAULT_EXECUTION, Execution
from taptr.model.query_init import QueryInitializer
from taptr.model.taptr import TAPTR
from taptr.model.v3.context import ContextInitializer, centre
from taptr.model.v3.decoder import HeldFrames, V3Decoder


class TAPTRv3(TAPTR):
    """TAPTRv3: backbone, deformable encoder, point contexts, per-frame decoder.

    Inputs are ImageNet-normalised frames; positions are normalised by (W − 1, H − 1).
    It is a `TAPTR` with windows of one frame and no content hand-over between them;
    its driver is `taptr.model.v3.per_frame`, not the sliding-window one.

    Attributes:
        visibility_weights: the long-temporal attention weighs past frames by visibility.
        history_frames: the most frames held per point, the current one included (0: all).
    """

    def __init__(
        self,
        backbone: Backbone,
        input_projections: InputProjections,
        encoder: Encoder,
        query_init: ContextInitializer | QueryInitializer,
        decoder: V3Decoder,
        *,
        visibility_weights: bool,
        history_frames: int,
        config: ModelConfig | None = None,
        execution: Execution | str = DEFAULT_EXECUTION,
    ) -> None:
        super().__init__(
            backbone,
            input_projections,
            encoder,
            query_init,
            decoder,
            None,
            window_size=1,
            window_stride=1,
            long_video_frames=1,
            window_dropout=0.0,
            config=config,
            execution=execution,
        )
        self.visibility_weights = visibility_weights
        self.history_frames = history_frames

    @property
    def content_channels(self) -> int:
        """C, channels of a point's content."""
        return self.query_init.project.out_features

    @property
    def context_patch(self) -> int:
        """Side K of the point contexts (0 without the context-aware attention)."""
        return self.query_init.patch if isinstance(self.query_init, ContextInitializer) else 0

    def point_queries(
        self, memory: Tensor, spatial_shapes: list[tuple[int, int]], positions: Tensor
    ) -> tuple[Tensor, Tensor | None]:
        """Content (B, N, C) and context (B, N, K, K, C) or None of points on one frame.

        Args:
            memory: (B, S, C) the frame's encoder memory.
            spatial_shapes: (H_l, W_l) per level.
            positions: (B, N, 2) normalised (x, y).
        """
        if isinstance(self.query_init, ContextInitializer):
            context = self.query_init(memory, spatial_shapes, positions)
            return centre(context), context
        return self.query_init(memory, spatial_shapes, positions), None

    def decode_frame(
        self,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        content: Tensor,
        positions: Tensor,
        tracking: Tensor,
        update: Tensor,
        held: HeldFrames,
        context: Tensor | None,
        all_tracked: bool | None = None,
    ) -> DecoderOutput:
        """Runs the decoder on one frame (arguments as in `decoder_inputs`)."""
        inputs = self.decoder_inputs(
            memory, spatial_shapes, content, positions, tracking, update, held, context, all_tracked
        )
        return self.decoder(*inputs)

    def decoder_inputs(
        self,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        content: Tensor,
        positions: Tensor,
        tracking: Tensor,
        update: Tensor,
        held: HeldFrames,
        context: Tensor | None,
        all_tracked: bool | None = None,
    ) -> tuple[Any, ...]:
        """The decoder's arguments on one frame, in ``V3Decoder.forward``'s order.

        What a decoder step (`taptr.model.v3.per_frame.DecoderStep`) is called with.

        Args:
            memory: (B, S, C) encoder memory of the frame.
            spatial_shapes: (H_l, W_l) per level.
            content: (B, 1, N, C) initial content.
            positions: (B, 1, N, 4) position logits carried from the previous frame.
            tracking: (B, 1, N) bool, points at or after their start frame.
            update: (B, 1, N) bool, tracking points after their start frame.
            held: the points' held frames.
            context: (B, N, K, K, C) initial contexts, or None.
            all_tracked: every point is tracked (known without asking the device), or
                None to read ``tracking`` (`taptr.model.v3.decoder.V3Decoder`).
        """
        assert isinstance(self.decoder, V3Decoder)
        return (
            content,
            positions,
            memory,
            spatial_shapes,
            tracking,
            update,
            self.execution,
            held,
            context,
            all_tracked,
        )
