"""TAPTRv3's per-frame decoder step captured once and replayed, where that pays.

The static step (`taptr.model.v3.per_frame.DecoderStep.static_shapes`) has the same
shapes from frame to frame and asks the device nothing, so it can be compiled once and
replayed: on CUDA ``torch.compile(mode="reduce-overhead")`` records Inductor's kernels as
CUDA graphs, one launch per frame instead of hundreds; on a CPU Inductor's default mode
fuses the small element-wise operations (what that saves: docs/BENCHMARKS.md). The outputs
are the eager step's up to float rounding.

Capturing costs seconds to minutes once (compilation; Inductor keeps what it compiled
on disk, so a second process pays less), so whether it pays depends on the machine and on
how many frames follow. ``auto`` therefore decides from a `CaptureTiming` kept per
machine, model and shape (`taptr.runtime.measured`): the step is captured when the frames
still to decode save more than the capture costs. With nothing kept, a run long enough
that capturing would pay by a first guess (`GUESSED_CAPTURE_SECONDS`, `GUESSED_GAIN`)
measures it on the job: a few frames eager, then captured, timed, and the faster kept;
a stream of unknown length (the online tracker) never stalls to measure. A capture that
fails (no C++ compiler, an unsupported operation) is reported once and the step runs
eagerly. Where a step stands in all this is its `Phase`.
"""

from __future__ import annotations

import enum
import logging
import math
import time
import weakref
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

import torch
from torch import nn

from taptr.model.v3.decoder import HeldFrames
from taptr.model.v3.per_frame import compiled
from taptr.runtime.capture_timing import MIN_STEP_SECONDS, CaptureTiming
from taptr.runtime.measured import TOLERANCE, keep, kept_choice, synchronize
from taptr.types import CAPTURE_CHOICES

logger = logging.getLogger(__name__)

MEASURED_FRAMES = 3
"""Frames timed each way when measuring on the job (the fastest of each is kept)."""

GUESSED_CAPTURE_SECONDS = {"cuda": 60.0, "cpu": 90.0}
"""First guess of what capturing costs, before anything was measured on the machine: a
little above what compiling TAPTRv3's decoder step took in a fresh process on the CPU
measured in docs/BENCHMARKS.md (a later process, reading Inductor's cache, pays less)."""

GUESSED_GAIN = {"cuda": 0.5, "cpu": 0.15}
"""First guess of the share of the eager step's time a captured step saves: about what
that CPU measured (docs/BENCHMARKS.md); on CUDA the eager step waits on hundreds of
launches."""

BACKEND = "inductor"
"""``torch.compile``'s backend for captured steps (tests set ``eager``, which only traces)."""

_captured: weakref.WeakKeyDictionary[nn.Module, dict[str, Any]] = weakref.WeakKeyDictionary()


def captured_step(decoder: nn.Module, device: torch.device) -> Any:
    """The decoder compiled for replay on ``device`` (made once per decoder and kept).

    Kept apart from the module (not ``decoder.compile()``), so that the eager step stays
    callable beside it and the module's state dict is unchanged.
    """
    made = _captured.setdefault(decoder, {})
    if BACKEND not in made:
        mode = "reduce-overhead" if device.type == "cuda" and BACKEND == "inductor" else None
        made[BACKEND] = torch.compile(decoder, mode=mode, fullgraph=True, backend=BACKEND)
    return made[BACKEND]


def _kind(device: torch.device) -> str:
    """The key of the first guesses: ``cuda`` or ``cpu`` (other devices guessed as CPUs)."""
    return "cuda" if device.type == "cuda" else "cpu"


def _history_size_may_change(args: tuple[Any, ...]) -> None:
    """Compiles for any history buffer size at once, instead of once more after it doubles."""
    for held in args:
        if isinstance(held, HeldFrames):
            dims = ((held.content, 2), (held.distances, 0), (held.weights, 2), (held.outside, 0))
            for tensor, dim in dims:
                if tensor is not None:
                    torch._dynamo.maybe_mark_dynamic(tensor, dim)


class Phase(enum.Enum):
    """What the next call of a `StepCapture` does.

    A step starts in one of them (`StepCapture`: from the setting and any kept timing) and
    moves on as its calls are timed; a failed capture sends any phase to `EAGER`.
    """

    EAGER = "eager"
    """Runs the module as it is, untimed: ``off``, a decision for it, or a failed capture."""

    CAPTURE = "capture"
    """Captures (says so first, unless this process compiled the step already), then `REPLAY`."""

    REPLAY = "replay"
    """Replays the captured step, untimed: ``on``, or a decision for it."""

    CAPTURE_COST = "capture cost"
    """A kept timing said capturing pays: captures, timing the call for what capturing costs
    in this process (Inductor's cache makes a second process cheaper), then `REPLAY`."""

    TIME_EAGER = "time eager"
    """Measuring on the job: times the eager step for `MEASURED_FRAMES` calls after the
    first, then captures if a first guess says it may pay (`TIME_CAPTURED`), else `EAGER`."""

    TIME_CAPTURED = "time captured"
    """Measuring on the job: captures, then times the replays, and keeps the faster
    (`REPLAY` or `EAGER`)."""


CAPTURED_PHASES = frozenset({Phase.CAPTURE, Phase.REPLAY, Phase.CAPTURE_COST, Phase.TIME_CAPTURED})
"""The phases whose call runs the captured step."""

TIMED_PHASES = frozenset({Phase.CAPTURE_COST, Phase.TIME_EAGER, Phase.TIME_CAPTURED})
"""The phases whose call is timed."""


def check_capture(setting: str) -> str:
    """``setting`` when it is one of `CAPTURE_CHOICES`.

    Raises:
        ValueError: another value; the message lists the choices.
    """
    if setting not in CAPTURE_CHOICES:
        choices = ", ".join(CAPTURE_CHOICES)
        raise ValueError(f"capture must be one of {choices}, got {setting!r}")
    return setting


class StepCapture:
    """The decoder step a `taptr.model.v3.per_frame.FrameState` calls each frame.

    Called like the decoder; runs it eagerly or captured as its `Phase` says (see the
    module for how ``auto`` decides).

    Args:
        decoder: the model's decoder (on ``device``).
        device: where it runs.
        setting: one of `CAPTURE_CHOICES`.
        key_for: the `taptr.runtime.measured.choice_key` its timing is kept under, for a
            number of points (`taptr.runtime.capture_buckets.capture_key`).
        points: points the run tracks, or None to read them from the first call (a
            stream, whose points come and go).
        frames: frames this run will decode, or None for a stream of unknown length.
        clock: the timer (injected by tests).

    Attributes:
        phase: what the next call does.
        key: where its timing is kept ("" until the points are known).
        frames_left: frames still to decode (infinite for a stream).
        timing: the kept or measured timing, None while there is none.
    """

    def __init__(
        self,
        decoder: nn.Module,
        device: torch.device,
        setting: str,
        key_for: Callable[[int], str],
        points: int | None,
        frames: int | None,
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        self.decoder, self.device, self.setting = decoder, device, check_capture(setting)
        self.key_for, self.key = key_for, ""
        self.clock = clock
        self.frames_left = math.inf if frames is None else frames
        self.timing: CaptureTiming | None = None
        self.phase = Phase.CAPTURE if setting == "on" else Phase.EAGER
        self.eager_times: list[float] = []  # measuring on the job
        self.captured_times: list[float] = []
        if points is not None:
            self._look_up(points)

    @property
    def captured(self) -> bool:
        """Whether the next call runs the captured step (with the decoder's static shapes)."""
        return self.phase in CAPTURED_PHASES

    @property
    def static_shapes(self) -> bool:
        """Whether the next call needs fixed shapes: it replays, or the decoder is compiled."""
        return self.captured or compiled(self.decoder)

    def _look_up(self, points: int) -> None:
        """Reads the timing kept for ``points`` and decides how an ``auto`` run starts."""
        self.key = self.key_for(points)
        if self.setting != "auto":
            return
        self.timing = CaptureTiming.read(kept_choice(self.key))
        if self.timing is not None:
            paying = self.timing.pays(self.frames_left)
            self.phase = Phase.CAPTURE_COST if paying else Phase.EAGER
        elif math.isfinite(self.frames_left):
            self.phase = Phase.TIME_EAGER

    def __call__(self, *args: Any) -> Any:
        """Runs the decoder on one frame (the arguments of ``V3Decoder.forward``)."""
        if not self.key:
            self._look_up(args[0].shape[2])  # content (B, 1, N, C)
        self.frames_left -= 1
        phase = self.phase
        start = self._now() if phase in TIMED_PHASES else 0.0
        output = self._captured_call(args) if phase in CAPTURED_PHASES else self.decoder(*args)
        if self.phase is not phase:  # the capture failed: nothing to record
            return output
        if phase in TIMED_PHASES:
            self._record(self._now() - start)
        elif phase is Phase.CAPTURE:
            self.phase = Phase.REPLAY
        return output

    def _captured_call(self, args: tuple[Any, ...]) -> Any:
        first = self.phase is not Phase.REPLAY and not self.captured_times
        if first and self.decoder not in _captured:
            self._announce()
        try:
            step = captured_step(self.decoder, self.device)
            if self.device.type == "cuda":
                # each frame is a new replay: outputs of the previous one may be overwritten
                torch.compiler.cudagraph_mark_step_begin()
            _history_size_may_change(args)
            return step(*args)
        except Exception as error:  # any failure to capture falls back to the eager step
            self._give_up(error)
            return self.decoder(*args)

    def _announce(self) -> None:
        """Says, before the stall, that the step compiles and about how long it takes."""
        timing = self.timing or CaptureTiming.read(kept_choice(self.key))
        cost = timing.capture_s if timing else GUESSED_CAPTURE_SECONDS[_kind(self.device)]
        # a progress bar that stops for a minute needs a reason, whichever setting asked
        logger.warning(
            "compiling TAPTRv3's per-frame step to replay it (about %.0f s, once per "
            "process; capture='off' or --capture off skips it)",
            cost,
        )

    def _give_up(self, error: Exception) -> None:
        line = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        logger.warning("capturing TAPTRv3's per-frame step failed (%s): running it eagerly", line)
        self.phase = Phase.EAGER
        if self.setting == "auto":  # kept, so that later runs do not try again
            measured = min(self.eager_times, default=MIN_STEP_SECONDS)
            eager_s = self.timing.eager_s if self.timing else max(measured, MIN_STEP_SECONDS)
            keep(self.key, asdict(CaptureTiming(eager_s, math.inf, 0.0)))

    def _now(self) -> float:
        synchronize(self.device)
        return self.clock()

    def _record(self, seconds: float) -> None:
        """Takes one timed call's seconds; moves on when enough are timed."""
        if self.phase is Phase.CAPTURE_COST:
            assert self.timing is not None
            cost = max(seconds - self.timing.captured_s, 0.0)
            self.timing = CaptureTiming(self.timing.eager_s, self.timing.captured_s, cost)
            keep(self.key, asdict(self.timing))
            self.phase = Phase.REPLAY
            return
        if self.phase is Phase.TIME_EAGER:
            self.eager_times.append(seconds)
            # the first call pays one-time costs (allocation, kernel choice): not counted
            if len(self.eager_times) == MEASURED_FRAMES + 1:
                self._start_capture_if_it_may_pay()
            return
        self.captured_times.append(seconds)
        if len(self.captured_times) == MEASURED_FRAMES + 1:
            self._decide()

    def _start_capture_if_it_may_pay(self) -> None:
        eager_s = min(self.eager_times[1:])
        kind = _kind(self.device)
        guess = CaptureTiming(
            eager_s, eager_s * (1 - GUESSED_GAIN[kind]), GUESSED_CAPTURE_SECONDS[kind]
        )
        # too short a run to pay for measuring: eager
        self.phase = Phase.TIME_CAPTURED if guess.pays(self.frames_left) else Phase.EAGER

    def _decide(self) -> None:
        eager_s = min(self.eager_times[1:])
        captured_s = min(self.captured_times[1:])
        capture_s = max(self.captured_times[0] - captured_s, 0.0)
        self.timing = CaptureTiming(eager_s, captured_s, capture_s)
        keep(self.key, asdict(self.timing))
        # what is spent is spent: from here on only the per-frame times count
        faster = captured_s < eager_s * (1 - TOLERANCE)
        self.phase = Phase.REPLAY if faster else Phase.EAGER
        logger.info(
            "TAPTRv3's per-frame step: eager %.4f s, captured %.4f s (capture took %.1f s): %s",
            eager_s,
            captured_s,
            capture_s,
            "captured" if faster else "eager",
        )
