"""How a model runs on this machine, decided once for the predictor and its streams.

A `Runner` holds everything about running a model that is not the task itself: the device,
the weights' type and the precision every call runs in (`taptr.runtime.precision`), the
deformable-attention kernel and the CPU's execution (timed once per machine and shape),
frames per encoder call, and TAPTRv3's captured step (`taptr.runtime.step_capture`), which
also decides whether the decoder's shapes stay static. It holds the model family's engine
(`taptr.runtime.engines.engine_for`: windows or frames, chosen here once) and makes the
frame caches (`taptr.runtime.frames`), so that a whole video (`Runner.track`) and a stream
(its engine, `Runner.decode`; `taptr.api.online.OnlineTracker`) run the same way.

Pixels, queries and support points are the predictor's (`taptr.api.predictor`): a runner
takes points in model units and frames prepared for the model.
"""

from __future__ import annotations

import contextlib
import warnings
from typing import Any

import torch

from taptr.model.frame_source import FrameSource, Span
from taptr.model.ops.dense import native_bfloat16
from taptr.model.taptr import TAPTR
from taptr.model.trajectory import QuerySet, TrackOutput
from taptr.model.v3.taptr import TAPTRv3
from taptr.runtime.capture_buckets import capture_key
from taptr.runtime.cpu_choice import choose_cpu_execution
from taptr.runtime.encode_choice import choose_frames_per_call
from taptr.runtime.engines import Engine, engine_for
from taptr.runtime.frames import EncodedFrames, FrameLoader, StreamFrames
from taptr.runtime.kernel_choice import choose_kernel
from taptr.runtime.precision import precision_context
from taptr.runtime.step_capture import StepCapture, check_capture
from taptr.types import OnStep


class Runner:
    """Runs one model on one device, the same way for whole videos and streams.

    Built in two steps: the constructor settles what needs no timing (and refuses what
    cannot run); `choose_speed` then times the speed-only choices, which the caller may
    put off until it has checked that a run fits in memory.

    Args:
        model: the network (moved to ``device`` and ``dtype``, put in eval mode).
        input_size: (H_m, W_m) the model's frames; speed choices and captured steps are
            timed and kept for it.
        device: where to run; default: CUDA if available, else the CPU.
        dtype: floating type of the weights and inputs.
        autocast: None, ``torch.float16`` or ``torch.bfloat16`` (`taptr.runtime.precision`);
            ``torch.bfloat16`` on a CPU without native bfloat16 runs float32, with a warning.
        history_frames: TAPTRv3: the most past frames held per point (0: all); None: the
            model's.
        capture: TAPTRv3: whether its per-frame step is captured and replayed, one of
            `taptr.types.CAPTURE_CHOICES`.

    Attributes:
        engine: the model family's `taptr.runtime.engines.Engine`.
        frames_per_call: frames per encoder call (1 until `choose_speed`).

    Raises:
        ValueError: an autocast type, capture or history limit the model cannot run.
    """

    def __init__(
        self,
        model: TAPTR,
        *,
        input_size: tuple[int, int],
        device: str | torch.device | None = None,
        dtype: torch.dtype = torch.float32,
        autocast: torch.dtype | None = None,
        history_frames: int | None = None,
        capture: str = "auto",
    ) -> None:
        if device is None:
            device = "cuda" if torch.cuda.is_available() else "cpu"
        self.device = torch.device(device)
        self.dtype = dtype
        self.model = model.to(self.device, dtype).eval()
        self.autocast = _runnable_autocast(autocast, self.device)
        if self.autocast == torch.bfloat16 and self.device.type == "cpu":
            self.model.bfloat16_trunk()
        self.input_size = input_size
        self.history_frames = history_frames
        self.capture = check_capture(capture)
        if capture == "on" and not isinstance(model, TAPTRv3):
            raise ValueError("capture applies to TAPTRv3 models only (others: --compile)")
        self.engine: Engine = engine_for(
            self.model, dtype, history_frames=history_frames, step_for=self.decoder_step
        )
        self.frames_per_call = 1

    def choose_speed(self, kernel: str, frames_per_call: int | str) -> None:
        """Sets the kernel, the CPU's execution and frames per call, timed where asked.

        Args:
            kernel: ``auto``, ``measure``, ``gather`` or ``grid_sample``
                (`taptr.runtime.kernel_choice`).
            frames_per_call: ``auto`` or a number (`taptr.runtime.encode_choice`).
        """
        choose_kernel(self.model, self.device, kernel, self.input_size)
        # float16 on a CPU runs most kernels without native support, minutes per timing:
        # nothing is timed there, one frame per call (float32 or bfloat16 are faster)
        cpu_float16 = self.device.type == "cpu" and self.autocast == torch.float16
        if cpu_float16 and frames_per_call == "auto":
            frames_per_call = 1
        with self.precision():
            if self.device.type == "cpu" and not cpu_float16:
                choose_cpu_execution(self.model, self.input_size)
            self.frames_per_call = choose_frames_per_call(
                self.model, self.device, self.input_size, frames_per_call
            )

    def precision(self) -> contextlib.AbstractContextManager[object]:
        """The context every model call runs in (`taptr.runtime.precision.precision_context`)."""
        return precision_context(self.device.type, self.autocast)

    def decoder_step(self, num_points: int | None, num_frames: int | None) -> StepCapture | None:
        """TAPTRv3's per-frame decoder step as ``capture`` says (None: the model's own).

        Args:
            num_points: points the model tracks (support included), or None for a stream
                (read from the first frame decoded).
            num_frames: frames this run decodes, or None for a stream.
        """
        if not isinstance(self.model, TAPTRv3) or self.capture == "off":
            return None
        if self.device.type == "cpu" and self.autocast == torch.bfloat16:
            # the CPU's bfloat16 products are switched by a context variable, which a
            # compiled step reads once, when traced: its outputs were measured neither
            # float32's nor eager bfloat16's (docs/BENCHMARKS.md)
            return None
        precision = f"{self.dtype} autocast {self.autocast}"
        key = capture_key(self.device, self.model.config, self.input_size, precision)
        model = self.model
        return StepCapture(model.decoder, self.device, self.capture, key, num_points, num_frames)

    def track(
        self, queries: QuerySet, num_frames: int, load: FrameLoader, on_step: OnStep = None
    ) -> TrackOutput:
        """Tracks points through a whole video, its frames encoded as they are needed.

        Args:
            queries: the points (B, N, ·) in model units.
            num_frames: video length T.
            load: frames first..last (B, F, 3, H_m, W_m) prepared for the model.
            on_step: called after each window or frame (progress).
        """
        frames = EncodedFrames(self.model, load, self.frames_per_call, num_frames)
        with self.precision():
            return self.engine.run(queries, num_frames, frames, on_step)

    def stream_frames(self) -> StreamFrames:
        """An empty cache for a stream's frames, encoded as `track` encodes a video's."""
        return StreamFrames(self.model, self.frames_per_call)

    def decode(self, state: Any, span: Span, frames: FrameSource) -> None:
        """Decodes one unit of a stream (a window, or a frame) in the run's precision."""
        with self.precision():
            self.engine.decode(state, span, frames)


def _runnable_autocast(autocast: torch.dtype | None, device: torch.device) -> torch.dtype | None:
    """``autocast`` as this device runs it (float32's None for bfloat16 on a CPU without it).

    Raises:
        ValueError: a type that is not an autocast type.
    """
    if autocast not in (None, torch.float16, torch.bfloat16):
        raise ValueError(f"autocast must be torch.float16, torch.bfloat16 or None, got {autocast}")
    if autocast == torch.bfloat16 and device.type == "cpu" and not native_bfloat16():
        warnings.warn(
            "this CPU has no native bfloat16 (AVX512-BF16 or AMX): running float32",
            stacklevel=4,
        )
        return None
    return autocast
