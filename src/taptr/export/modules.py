"""Export-friendly wrappers around the model's per-window pieces.

The sliding-window loop (`taptr.model.sliding_window`) is Python bookkeeping around three
tensor functions; each wrapper below is one of them with plain tensor inputs and outputs
and batch size one, so that it can be traced or exported and driven by a loop written in
any language (`taptr.export.graph_runner` drives them through the same window driver):

- `FrameEncoder`: backbone, input projections and deformable encoder of some frames.
- `PointInitializer`: the initial content of points from the memory of their start frame.
- `WindowDecoder`: the decoder over one window plus the content handed to the next one.

The wrappers hold the model as given; the exporters (`taptr.export.graphs`) switch a copy
of it to the ``grid_sample`` kernel first (4-D ``grid_sample`` only), because
``embedding_bag`` with per-sample weights has no ONNX counterpart. Both kernels compute
the same sums.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from taptr.model.position_encoding import feature_map_encoding
from taptr.model.taptr import TAPTR, normalize_frames


def feature_shapes(model: TAPTR, input_size: tuple[int, int]) -> list[tuple[int, int]]:
    """(H_l, W_l) of every memory level for frames of ``input_size`` (height, width).

    Runs the backbone once on a blank frame: the shapes follow from its strides and
    paddings, which differ between backbone kinds.
    """
    parameter = next(model.parameters())
    blank = torch.zeros(1, 3, *input_size, dtype=parameter.dtype, device=parameter.device)
    with torch.no_grad():
        maps = model.backbone(blank)
    return [(int(m.shape[-2]), int(m.shape[-1])) for m in maps]


class FrameEncoder(nn.Module):
    """Frames at the model's input size → encoder memory, frame by frame.

    Shape:
        frames (F, 3, H, W) RGB in [0, 1] → memory (F, S, C).
    """

    def __init__(self, model: TAPTR) -> None:
        super().__init__()
        self.model = model

    def forward(self, frames: Tensor) -> Tensor:
        """Normalises (ImageNet statistics) and encodes every frame independently."""
        # encode_images, not encode: encode's chunk loop over the frame count would fix F
        # to the example's value when exporting
        return self.model.encode_images(normalize_frames(frames)).memory  # (F, S, C)


class FixedSizeEncoder(FrameEncoder):
    """`FrameEncoder` for one frame size, each token's level held as a constant.

    The encoder's position encoding adds each token's level embedding to its sine
    encoding. Traced as the model computes it, the level of every token
    (``repeat_interleave`` of the levels' sizes) exports as a subgraph of constants
    (CumSum → Range → Less → GatherND) whose shapes OpenVINO's CPU plugin cannot infer
    ("the memory desc is undefined"): it compiled none of TAPTRv3's encoders. Here the
    (S,) levels are computed once, for the export's fixed input size, and the graph
    gathers the embedding with them as an initializer; the sine encoding is traced as
    before, so the graph computes what it computed, to the bit.

    Args:
        model: the network (a copy prepared for export: its encoder's
            ``position_encoding`` is replaced by this one).
        spatial_shapes: (H_l, W_l) of the memory levels at the export's input size.
    """

    def __init__(self, model: TAPTR, spatial_shapes: list[tuple[int, int]]) -> None:
        super().__init__(model)
        encoder = model.encoder
        shapes = [(int(h), int(w)) for h, w in spatial_shapes]
        sizes = torch.tensor([h * w for h, w in shapes])
        self.register_buffer("levels", torch.repeat_interleave(torch.arange(len(shapes)), sizes))
        channels = encoder.level_embed.shape[1] // 2

        def encoding(spatial: list[tuple[int, int]], dtype: torch.dtype) -> Tensor:
            """(S, C) sine encoding of every token plus its level's embedding."""
            if [(int(h), int(w)) for h, w in spatial] != shapes:
                raise ValueError(f"this encoder was fixed for levels {shapes}, got {spatial}")
            device = encoder.level_embed.device
            maps = [
                feature_map_encoding(h, w, channels, encoder.temperature, device) for h, w in shapes
            ]
            return torch.cat(maps).to(dtype) + encoder.level_embed[self.levels]

        encoder.position_encoding = encoding  # the copy's own: the model passed is not touched


class _OnMemory(nn.Module):
    """A wrapped piece that reads the flattened memory, so needs the levels' sizes."""

    def __init__(self, model: TAPTR, spatial_shapes: list[tuple[int, int]]) -> None:
        """Wraps ``model``.

        Args:
            model: the network.
            spatial_shapes: (H_l, W_l) of the memory levels (see `feature_shapes`).
        """
        super().__init__()
        self.model = model
        self.spatial_shapes = [(int(h), int(w)) for h, w in spatial_shapes]


class PointInitializer(_OnMemory):
    """Initial content of points from the memory of one frame.

    Shape:
        memory (S, C) of one frame, positions (N, 2) → content (N, C).
    """

    def forward(self, memory: Tensor, positions: Tensor) -> Tensor:
        """Samples every level at the points and projects the samples.

        Args:
            memory: (S, C) memory of the points' start frame.
            positions: (N, 2) normalised (x, y) in [0, 1], i.e. pixels / (W − 1, H − 1).
        """
        content = self.model.initial_content(memory[None], self.spatial_shapes, positions[None])
        return content[0]  # (N, C)


class WindowDecoder(_OnMemory):
    """One window of the decoder with its carried per-point state.

    Shape:
        memory (W_t, S, C), content (W_t, N, C), positions (W_t, N, 4), initial (N, C),
        tracking (W_t, N), update (W_t, N) → positions (W_t, N, 4), visibility logits
        (W_t, N, 3), next content (W_t, N, C).
    """

    def forward(
        self,
        memory: Tensor,
        content: Tensor,
        positions: Tensor,
        initial: Tensor,
        tracking: Tensor,
        update: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Decodes the window and computes the content handed to the next one.

        Args:
            memory: (W_t, S, C) encoder memory of the window's frames.
            content: (W_t, N, C) content at window entry.
            positions: (W_t, N, 4) last layer's position logits at window entry.
            initial: (N, C) each point's initial content (zeros before its start frame).
            tracking: (W_t, N) bool, frames at or after each point's start frame.
            update: (W_t, N) bool, frames after each point's start frame.

        Returns:
            the last layer's position logits (W_t, N, 4) (x, y are logits of the
            normalised position), its visibility logits (W_t, N, 3) (channel 1 =
            visible) and the next window's content (W_t, N, C), all before the write-back
            masks are applied.
        """
        decoded = self.model.decode_window(
            memory[None],
            self.spatial_shapes,
            content[None],
            positions[None],
            tracking[None],
            update[None],
        )
        entry = content[None]  # (1, W_t, N, C)
        handed_over = self.model.update_content(
            initial[None, None].expand_as(entry), entry, decoded.features, update[None]
        )
        return decoded.positions[-1, 0], decoded.visibility_logits[-1, 0], handed_over[0]
