"""Plain containers shared across the package, with the shape glossary.

Shape letters: B batch, T frames, N points, H and W image height and width. Coordinates
are (x, y) pixels with pixel centres at integers (pixel (0, 0) is the centre of the
top-left pixel); queries are (t, x, y). Visibility is True where the point is visible.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # keeps torch out of the import of the data readers and the CLI
    from torch import Tensor

AUTOCAST_TYPES = ("float32", "bfloat16", "float16")
"""Names of the types a model can run in under autocast
(`taptr.runtime.precision.autocast_type`); float32 runs without autocast. Here, without
torch, for the CLI's choices."""

OnStep = Callable[[], object] | None
"""Called after each window or frame a run decodes (progress bars); None: nothing is."""

CAPTURE_CHOICES = ("auto", "on", "off")
"""Whether TAPTRv3's per-frame step is captured and replayed (`taptr.runtime.step_capture`):
``auto`` by measurement, ``on`` always, ``off`` never. Here, without torch, for the CLI."""

DTYPE_CHOICES = (*AUTOCAST_TYPES, "int8")
"""``--dtype``'s names: PyTorch's autocast types, and ``int8``, which only the graph engines
run (`taptr.onnx.precisions`: the encoder quantised). Without torch, for the CLI."""

ENGINE_CHOICES = ("torch", "onnxruntime", "openvino")
"""What runs a tracker (``--engine``): PyTorch, or TAPTRv3's exported graphs in one of
the engines of `taptr.onnx.graph_engines` (exported once per checkpoint and kept)."""


@dataclass
class TrackingSample:
    """One video with ground-truth tracks, as every dataset reader returns it.

    Attributes:
        video: (T, H, W, 3) uint8 RGB frames.
        tracks: (T, N, 2) float32 (x, y) pixels, pixel centres at integers.
        visible: (T, N) bool, True where the point is visible.
        name: identifier of the video (file or sequence name, or its index).
    """

    video: np.ndarray
    tracks: np.ndarray
    visible: np.ndarray
    name: str = ""

    def __post_init__(self) -> None:
        label, num_frames = self.name or "sample", self.video.shape[0]
        if self.video.ndim != 4 or self.video.shape[-1] != 3:
            raise ValueError(f"{label}: video must be (T, H, W, 3), got {self.video.shape}")
        if self.tracks.ndim != 3 or self.tracks.shape[0] != num_frames or self.tracks.shape[2] != 2:
            raise ValueError(f"{label}: tracks must be (T, N, 2), got {self.tracks.shape}")
        if self.visible.shape != self.tracks.shape[:2]:
            expected = self.tracks.shape[:2]
            raise ValueError(
                f"{label}: visible must be (T, N) = {expected}, got {self.visible.shape}"
            )


@dataclass
class TrackingResult:
    """What the predictor returns.

    Attributes:
        tracks: (B, T, N, 2) float32 (x, y) pixels of the input video.
        visibility: (B, T, N) bool, True where the point is predicted visible.
        visibility_logits: (B, T, N) logit of visibility (sigmoid > threshold = visible).
        queries: (B, N, 3) float32 (t, x, y) pixels, the points that were tracked.
    """

    tracks: Tensor
    visibility: Tensor
    visibility_logits: Tensor
    queries: Tensor
