"""The TAPTR module: per-frame encoding and per-window decoding, no loop over windows.

`encode` turns frames into multi-scale memory; `initial_content` builds point queries;
`decode_window` runs the decoder over one window; `update_content` computes the content
handed to the next window. The sliding-window loop lives in `taptr.model.sliding_window`.

How the model runs (`taptr.model.execution`) is this module's ``execution``, the only
mode anywhere in the model: every method here hands it down as an argument.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from taptr.config import ModelConfig
from taptr.model.backbone import Backbone, InputProjections, ResNetBody
from taptr.model.decoder import Decoder, DecoderOutput
from taptr.model.encoder import Encoder
from taptr.model.execution import (
    CHANNELS_LAST_MIN_PIXELS,
    DEFAULT_EXECUTION,
    Execution,
    get_execution,
)
from taptr.model.frame_source import FrameFeatures
from taptr.model.frame_tables import FrameTables
from taptr.model.layers import MLP
from taptr.model.query_init import QueryInitializer

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def normalize_frames(frames: Tensor) -> Tensor:
    """ImageNet normalisation of RGB frames in [0, 1], (..., 3, H, W)."""
    mean = frames.new_tensor(IMAGENET_MEAN).view(3, 1, 1)
    std = frames.new_tensor(IMAGENET_STD).view(3, 1, 1)
    return (frames - mean) / std


class TAPTR(nn.Module):
    """TAPTRv2: backbone, deformable encoder, point-query initialiser, windowed decoder.

    Inputs are ImageNet-normalised frames; positions are normalised by (W − 1, H − 1).

    Attributes:
        execution: how the model runs (`taptr.model.execution.Execution`); set by
            `taptr.model.build.build_model` and changed only by `set_execution`.
        window_updater: updates the content handed from one window to the next from the
            point's initial content, its window-entry content and the last layer's head
            features (`update_content`); None in TAPTRv3, which hands no content over.
    """

    def __init__(
        self,
        backbone: Backbone,
        input_projections: InputProjections,
        encoder: Encoder,
        query_init: QueryInitializer,
        decoder: Decoder,
        window_updater: MLP | None,
        *,
        window_size: int,
        window_stride: int,
        long_video_frames: int,
        window_dropout: float,
        memory_efficient: bool = False,
        config: ModelConfig | None = None,
        execution: Execution | str = DEFAULT_EXECUTION,
    ) -> None:
        super().__init__()
        self.backbone = backbone
        self.input_projections = input_projections
        self.encoder = encoder
        self.query_init = query_init
        self.decoder = decoder
        self.window_updater = window_updater
        self.window_size = window_size
        self.window_stride = window_stride
        self.long_video_frames = long_video_frames
        self.window_dropout = window_dropout
        self.memory_efficient = memory_efficient
        self.config = config
        self.execution = get_execution(execution)

    def set_execution(self, execution: Execution | str) -> TAPTR:
        """Switches how the model runs; returns the model (``model.set_execution("reference")``).

        Args:
            execution: a name of `taptr.model.execution.EXECUTIONS` or an `Execution`.

        Raises:
            ValueError: for an unknown name.
        """
        self.execution = get_execution(execution)
        return self

    @property
    def num_layers(self) -> int:
        """Decoder depth."""
        return len(self.decoder.layers)

    def encode_images(self, images: Tensor) -> FrameFeatures:
        """Backbone, input projections and encoder on a batch of independent images.

        Args:
            images: (N, 3, H, W) ImageNet-normalised frames.

        Returns:
            `FrameFeatures` whose memory is (N, S, C) (one image per row).
        """
        maps = self.feature_maps(images)
        spatial_shapes = [(m.shape[-2], m.shape[-1]) for m in maps]
        return FrameFeatures(self.encoder(maps, self.execution), spatial_shapes)

    def feature_maps(self, images: Tensor) -> list[Tensor]:
        """Backbone and input projections the way the execution says.

        Shape:
            (N, 3, H, W) ImageNet-normalised frames → L maps (N, C, H_l, W_l).
        """
        height, width = images.shape[-2:]
        if self.execution.channels_last and height * width >= CHANNELS_LAST_MIN_PIXELS:
            images = images.contiguous(memory_format=torch.channels_last)
        # a trunk stored in bfloat16 (`bfloat16_trunk`) hands its maps on in the frames' type;
        # otherwise both conversions return their input
        trunk = next(self.backbone.parameters()).dtype
        maps = self.backbone(images.to(trunk), self.execution.in_place_norms)
        return self.input_projections([m.to(images.dtype) for m in maps])

    def bfloat16_trunk(self) -> TAPTR:
        """Stores the backbone in bfloat16, for `taptr.model.ops.dense.bfloat16_products`.

        A ResNet's frozen norms are first folded into its convolutions
        (`taptr.model.backbone.ResNetBody.fold_norms`). Its convolutions then run through
        oneDNN's bfloat16 kernels (about twice float32 where the CPU multiplies bfloat16
        natively, docs/BENCHMARKS.md) and its weights take half the memory; the maps it
        hands on are float32. For inference only: the folded trunk has other parameter
        names. Returns the model.
        """
        if isinstance(self.backbone.body, ResNetBody):
            self.backbone.body.fold_norms()
        self.backbone.to(torch.bfloat16)
        return self

    def encode(self, frames: Tensor, chunk_size: int | None = None) -> FrameFeatures:
        """Encodes every frame of a batch of videos independently.

        Args:
            frames: (B, T, 3, H, W) ImageNet-normalised frames.
            chunk_size: frames per backbone call (memory only; the result is the same).

        Returns:
            `FrameFeatures` with memory (B, T, S, C).
        """
        batch, num_frames = frames.shape[:2]
        flat = frames.flatten(0, 1)  # (B·T, 3, H, W)
        step = chunk_size or flat.shape[0]
        chunks = [
            self.encode_images(flat[start : start + step])
            for start in range(0, flat.shape[0], step)
        ]
        memory = torch.cat([c.memory for c in chunks]).unflatten(
            0, (batch, num_frames)
        )  # (B, T, S, C)
        return FrameFeatures(memory, chunks[0].spatial_shapes)

    def initial_content(
        self, memory: Tensor, spatial_shapes: list[tuple[int, int]], positions: Tensor
    ) -> Tensor:
        """Point-query content from one frame's memory, (B, S, C) and (B, N, 2) → (B, N, C)."""
        return self.query_init(memory, spatial_shapes, positions)

    def decode_window(
        self,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        content: Tensor,
        positions: Tensor,
        tracking: Tensor,
        update: Tensor,
        tables: FrameTables | None = None,
        all_tracked: bool | None = None,
    ) -> DecoderOutput:
        """Runs the decoder over one window.

        Args:
            memory: (B, W_t, S, C) encoder memory of the window's frames.
            spatial_shapes: (H_l, W_l) per level.
            content: (B, W_t, N, C) content at window entry.
            positions: (B, W_t, N, 4) position logits at window entry.
            tracking: (B, W_t, N) bool, entries at or after each point's start frame.
            update: (B, W_t, N) bool, tracking entries after the start frame.
            tables: the run's key and value tables, started for this window, or None
                (`taptr.model.frame_tables`).
            all_tracked: every entry of ``tracking`` is set (known on the host), or None
                to read it (`taptr.model.masks.attention_masks`).
        """
        return self.decoder(
            content,
            positions,
            memory.flatten(0, 1),
            spatial_shapes,
            tracking,
            update,
            self.execution,
            tables,
            all_tracked,
        )

    def update_content(
        self, initial: Tensor, content: Tensor, features: Tensor, update: Tensor
    ) -> Tensor:
        """Content handed to the next window: entry content plus a masked learned update.

        Args:
            initial: (B, W_t, N, C) each point's initial content.
            content: (B, W_t, N, C) content at window entry.
            features: (B, W_t, N, C) what the last layer's heads read.
            update: (B, W_t, N) bool.

        Returns:
            (B, W_t, N, C).
        """
        if self.window_updater is None:
            raise TypeError("this model hands no content between windows (TAPTRv3)")
        joined = torch.cat((initial, content, features), dim=-1)
        delta = self.window_updater(joined, self.execution)
        delta = delta * update.unsqueeze(-1).to(delta.dtype)
        return content + F.dropout(delta, self.window_dropout, self.training)
