"""Peak memory of a tracking run, estimated before it allocates anything, and the budget.

The model holds about one window of frames at a time, so a run's peak is set by the input
size, the number of points and (for in-memory runs) the video, not by the weights. With
h × w the model's input size, S = Σ_l ⌈h/s_l⌉·⌈w/s_l⌉ the encoder tokens of a frame
(strides s_l = 4, 8, 16, 32), C = d_model, D decoder layers, W frames per window, N points
(context points included), T frames, H × W_v the video's frame size, and 4-byte floats:

    features     = 4 · S · C · W · (2 + 2·D) · FEATURE_SHARE
                   (a window's encoded frames, their stacked copy, and each decoder layer's
                   key and value tables of the window's frames)
    backbone     = 4 · h · w · BACKBONE_FLOATS[kind] · F (the trunk activations of the F
                   frames of one encoder call, `taptr.runtime.encode_choice`)
    read ahead   = 4 · S · C · (F − 1) (frames encoded ahead of the window)
    points       = 4 · N · W · (5 · M·L·P·4 + POINT_CHANNELS · C + ffn)
                   (per point and window frame: the deformable sampling's corner indices,
                   weights and combined weights for M heads, L levels, P points and 4
                   corners, the decoder's activations and its FFN)
    trajectories = 4 · N · T · (11 · D + 3)  (per-frame positions and visibility of every
                   layer, kept until the end)
    history      = 4 · N · T_h · (C + 1)  (TAPTRv3 only: each point's content and visibility
                   on the T_h held frames, T_h = min(T, the history limit))
    encoder      = 4 · S · (4 · C + 5 · M·L·P_e) · F  (TAPTRv3 only: the encoder's working set
                   per token, projected values and outputs, sampling offsets and weights of
                   P_e encoder points; TAPTRv2's 8-frame window absorbs it in
                   FEATURE_SHARE, TAPTRv3's window of one frame does not: at 1024 × 1024
                   its run peaked at 1,388 MiB RSS against 867 MiB estimated without it)
    frames       = 3 · H · W_v · (T if the whole video is held else the window + a segment)
                   + 4 · 3 · H · W_v · W · 2 (a window of frames as floats while resizing)
    total        = OVERHEAD + the above

`FEATURE_SHARE`, `POINT_CHANNELS`, `BACKBONE_FLOATS` and `OVERHEAD` were fitted to peak
RSS measured on CPU (tests/test_memory_estimate.py compares the estimate with a measured
run); on the cases measured the estimate lies within a factor of 1.5 of the measurement
(docs/FAQ.md lists the measurements).

`check_memory` compares an estimate with the budget: ``TAPTR_MAX_MEMORY`` when set (it
replaces what the machine reports: lower to be careful, higher to run anyway), else the
least of the machine's available memory, the container's memory limit and the
address-space limit (``ulimit -v``), and free GPU memory for the model's part on a GPU.
Over budget, it raises `MemoryEstimateError`, a one-line ValueError naming the knobs to
turn. `allocator_failure` words an allocator's own failure (``MemoryError``, PyTorch's
"not enough memory") the same way.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from taptr.io import limits

if TYPE_CHECKING:
    from taptr.config import ModelConfig

STRIDES = (4, 8, 16, 32)
"""Strides of the encoder's feature levels."""

FEATURE_SHARE = 0.75
"""Fraction of the window's frame tensors alive at the peak (fitted)."""

BACKBONE_FLOATS = {"resnet50": 160, "resnet18": 40, "convnet": 12}
"""Floats per input pixel of one frame's trunk activations (fitted for ResNet-50, which
keeps 256 channels at a quarter of the resolution, several at once; ResNet-18's 64
channels there scaled from it)."""

POINT_CHANNELS = 12
"""Per point and window frame, activations of the decoder of C floats each (fitted)."""

OVERHEAD = 64 * 1024**2
"""What any run allocates whatever its size: thread pools, kernels, allocator caches."""

SEGMENT_FRAMES = 32
"""Frames a backward read holds (`taptr.io.reverse_frames.SEGMENT_FRAMES`)."""

ALLOCATOR_WORDS = (
    "not enough memory",
    "out of memory",
    "cannot allocate memory",
    "can't allocate memory",
    "bad_alloc",
)
"""Phrases of allocators' failure messages (PyTorch's CPU and CUDA allocators, glibc)."""


class MemoryEstimateError(ValueError):
    """A run would need more memory than the budget; the message names the knobs."""


@dataclass(frozen=True)
class Estimate:
    """Estimated peak bytes of one run, by part.

    Attributes:
        parts: bytes of each part (``features``, ``backbone``, ``points``,
            ``trajectories``, ``frames``, ``overhead``).
        host_parts: the parts held in host memory when the model runs on a GPU.
    """

    parts: dict[str, int] = field(default_factory=dict)
    host_parts: tuple[str, ...] = ("frames", "trajectories")

    @property
    def total(self) -> int:
        """All parts together (what a CPU run needs)."""
        return sum(self.parts.values())

    @property
    def host(self) -> int:
        """The parts that stay in host memory on a GPU run."""
        return sum(v for k, v in self.parts.items() if k in self.host_parts)

    def describe(self) -> str:
        """``about 3.1 GiB (features 2.0 GiB, points 0.8 GiB, ...)``, largest parts first."""
        shown = sorted(self.parts.items(), key=lambda item: -item[1])[:3]
        return f"about {gib(self.total)} (" + ", ".join(f"{k} {gib(v)}" for k, v in shown) + ")"


def gib(nbytes: int) -> str:
    """Bytes as ``1.2 GiB`` (or MiB below one GiB)."""
    if nbytes >= 1024**3:
        return f"{nbytes / 1024**3:.1f} GiB"
    return f"{nbytes / 1024**2:.0f} MiB"


def encoder_tokens(height: int, width: int) -> int:
    """S: tokens of one frame over the four feature levels."""
    return sum(math.ceil(height / s) * math.ceil(width / s) for s in STRIDES)


def trunk_bytes(kind: str, height: int, width: int) -> int:
    """One frame's trunk activations at an h × w input (``backbone`` above, F = 1)."""
    return 4 * height * width * BACKBONE_FLOATS.get(kind, 160)


def estimate_tracking(
    config: ModelConfig,
    *,
    input_size: tuple[int, int],
    num_frames: int,
    num_points: int,
    frame_size: tuple[int, int],
    whole_video: bool,
    backward: bool = False,
    history_frames: int | None = None,
    frames_per_call: int = 1,
) -> Estimate:
    """Estimates the peak memory of tracking (see the module's formula).

    Args:
        config: the model's configuration.
        input_size: (h, w) the model sees.
        num_frames: T frames tracked.
        num_points: N points the model tracks, context points included.
        frame_size: (H, W) of the video's frames.
        whole_video: whether the video is held in memory (``Predictor.track``) or
            streamed (``taptr track`` on a file that states its length).
        backward: whether a time-reversed pass runs too (a segment of frames held).
        history_frames: TAPTRv3's history limit (0: the whole video; None: the config's).
        frames_per_call: frames per encoder call (`taptr.runtime.encode_choice`): the
            backbone's activations are those of this many frames, and up to this many
            encoded frames beyond the window are held ahead of it.
    """
    height, width = input_size
    window = config.window_size
    layers = config.decoder_layers
    channels = config.d_model
    samples = config.num_heads * config.num_levels * config.decoder_points * 4
    tokens = encoder_tokens(height, width)
    frame_pixels = frame_size[0] * frame_size[1]
    held = num_frames if whole_video else min(num_frames, 2 * window + backward * SEGMENT_FRAMES)
    parts = {
        "features": int(4 * tokens * channels * window * (2 + 2 * layers) * FEATURE_SHARE),
        "backbone": trunk_bytes(config.backbone.kind, height, width) * frames_per_call,
        "read ahead": 4 * tokens * channels * (frames_per_call - 1),
        "points": 4
        * num_points
        * window
        * (5 * samples + POINT_CHANNELS * channels + config.ffn_dim),
        "trajectories": 4 * num_points * num_frames * (11 * layers + 3),
        "frames": 3 * frame_pixels * held + 4 * 3 * frame_pixels * min(window, num_frames) * 2,
        "overhead": OVERHEAD,
    }
    if config.version == 3:
        limit = config.history_frames if history_frames is None else history_frames
        kept = min(num_frames, limit) if limit else num_frames
        parts["history"] = 4 * num_points * kept * (channels + 1)
        encoder_samples = config.num_heads * config.num_levels * config.encoder_points
        per_token = 4 * channels + 5 * encoder_samples
        parts["encoder"] = 4 * tokens * per_token * frames_per_call
    return Estimate(parts)


def available_memory(device: str = "cpu") -> tuple[int | None, str]:
    """(bytes, where the figure comes from) of the budget for a run on ``device``.

    ``TAPTR_MAX_MEMORY`` when set; else the least of the machine's available memory, the
    container's limit and the address-space limit; on a CUDA device, its free memory. None
    when nothing can be read (then nothing is refused).
    """
    if limits.is_set("memory"):
        return limits.limit("memory"), limits.LIMITS["memory"].variable
    if device.startswith("cuda"):
        import torch

        return int(torch.cuda.mem_get_info(torch.device(device))[0]), "free GPU memory"
    figures = [f for f in (_meminfo(), _cgroup(), _address_space()) if f[0] is not None]
    if not figures:
        return None, "unknown"
    return min(figures, key=lambda f: f[0] or 0)


def _meminfo() -> tuple[int | None, str]:
    try:
        with open("/proc/meminfo", encoding="ascii") as stream:
            for line in stream:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024, "available memory"
    except (OSError, ValueError, IndexError):
        pass
    try:
        pages = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        return (pages, "free memory") if pages > 0 else (None, "")
    except (ValueError, OSError, AttributeError):
        return None, ""


def _cgroup() -> tuple[int | None, str]:
    for limit_file, usage_file in (
        ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
        (
            "/sys/fs/cgroup/memory/memory.limit_in_bytes",
            "/sys/fs/cgroup/memory/memory.usage_in_bytes",
        ),
    ):
        try:
            with open(limit_file, encoding="ascii") as stream:
                text = stream.read().strip()
            with open(usage_file, encoding="ascii") as stream:
                usage = int(stream.read().strip())
        except (OSError, ValueError):
            continue
        if text.isdigit() and int(text) < 2**60:
            return max(0, int(text) - usage), "the container's memory limit"
    return None, ""


def _address_space() -> tuple[int | None, str]:
    try:
        import resource
    except ImportError:  # not on POSIX
        return None, ""
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY:
        return None, ""
    used = 0
    try:
        with open("/proc/self/status", encoding="ascii") as stream:
            for line in stream:
                if line.startswith("VmSize:"):
                    used = int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return max(0, soft - used), "the address-space limit (ulimit -v)"


def check_memory(estimate: Estimate, what: str, knobs: str, device: str = "cpu") -> None:
    """Raises `MemoryEstimateError` when ``estimate`` exceeds the budget for ``device``.

    Args:
        estimate: the run's estimate.
        what: the run, for the message (``"tracking 99,856 points through 48 frames"``).
        knobs: what to turn, for the message (``"lower --input-size, ..."``).
        device: where the model runs.
    """
    budget, source = available_memory(device)
    needed = estimate.total if not device.startswith("cuda") else estimate.total - estimate.host
    if budget is not None and needed > budget:
        variable = limits.LIMITS["memory"].variable
        hint = "" if source == variable else f", or set {variable} to run anyway"
        raise MemoryEstimateError(
            f"{what} needs {estimate.describe()}, more than the {gib(budget)} of {source}; "
            f"{knobs}{hint}"
        )


def allocator_failure(error: BaseException) -> str | None:
    """A one-line message for an allocator's failure, naming the knobs; None otherwise."""
    text = " ".join(str(error).split())
    if not isinstance(error, MemoryError) and not any(w in text.lower() for w in ALLOCATOR_WORDS):
        return None
    asked = text[:200] + (" ..." if len(text) > 200 else "")
    return (
        f"out of memory ({type(error).__name__}: {asked}); lower --input-size, track fewer "
        "points or read fewer frames (--max-frames)"
    )
