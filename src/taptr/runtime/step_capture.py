"""TAPTRv3's per-frame decoder step captured once and replayed, where that pays.

The static step (`taptr.model.v3.per_frame.FrameState.static_shapes`) has the same
shapes from frame to frame and asks the device nothing, so it can be compiled once and
replayed: on CUDA ``torch.compile(mode="reduce-overhead")`` records Inductor's kernels as
CUDA graphs, one launch per frame instead of hundreds; on a CPU Inductor's default mode
fuses the small element-wise operations (docs/BENCHMARKS.md: 1.1-1.24× on the decoder).
The outputs are the eager step's up to float rounding.

Capturing costs seconds to minutes once (compilation; Inductor keeps what it compiled
on disk, so a second process pays less), so whether it pays depends on the machine and on
how many frames follow. ``auto`` therefore decides from a `CaptureTiming` kept per
machine, model and shape (`taptr.runtime.measured`): the step is captured when the frames
still to decode save more than the capture costs. With nothing kept, a run long enough
that capturing would pay by a first guess (`GUESSED_CAPTURE_SECONDS`, `GUESSED_GAIN`)
measures it on the job: a few frames eager, then captured, timed, and the faster kept;
a stream of unknown length (the online tracker) never stalls to measure. A capture that
fails (no C++ compiler, an unsupported operation) is reported once and the step runs
eagerly.
"""

from __future__ import annotations

import logging
import math
import time
import weakref
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

import torch
from torch import nn

from taptr.model.trajectory import QuerySet
from taptr.model.v3.decoder import HeldFrames
from taptr.runtime.capture_timing import MIN_STEP_SECONDS, CaptureTiming
from taptr.runtime.measured import TOLERANCE, choice_key, keep, kept_choice, synchronize
from taptr.types import CAPTURE_CHOICES

logger = logging.getLogger(__name__)

MEASURED_FRAMES = 3
"""Frames timed each way when measuring on the job (the fastest of each is kept)."""

GUESSED_CAPTURE_SECONDS = {"cuda": 60.0, "cpu": 90.0}
"""First guess of what capturing costs, before anything was measured on the machine:
Inductor compiled TAPTRv3's decoder step in 73-81 s on a 2-core AMD EPYC (15 s in a later
process, from its cache; docs/BENCHMARKS.md)."""

GUESSED_GAIN = {"cuda": 0.5, "cpu": 0.15}
"""First guess of the share of the eager step's time a captured step saves: on that CPU
8-19 % (1.09-1.24×); on CUDA the eager step waits on hundreds of launches."""

BUCKET = 128
"""Captured runs pad their points up to a multiple of this, so that calls with nearby
point counts replay the same captured step instead of capturing another."""


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


NEVER = 2**31 - 1
"""The start frame of padding points: no video reaches it, so they are never decoded."""


def pad_points(queries: QuerySet, count: int) -> QuerySet:
    """``queries`` with points appended up to ``count`` that never start.

    Points not yet started take no part in the others' attention (the decoder's N × N
    mask), so the real points' tracks are unchanged; callers drop the padding's outputs
    with the rest of what follows the user's points.
    """
    batch, points = queries.start_frames.shape
    extra = count - points
    if extra <= 0:
        return queries
    never = queries.start_frames.new_full((batch, extra), NEVER)
    centre = queries.positions.new_full((batch, extra, 2), 0.5)
    hidden = queries.start_visible.new_zeros(batch, extra)
    return QuerySet(
        torch.cat((queries.start_frames, never), 1),  # (B, count)
        torch.cat((queries.positions, centre), 1),  # (B, count, 2)
        torch.cat((queries.start_visible, hidden), 1),  # (B, count)
    )


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


def points_bucket(count: int) -> int:
    """``count`` points padded up to the next multiple of `BUCKET`."""
    return max(BUCKET, -(-count // BUCKET) * BUCKET)


class StepCapture:
    """The decoder step a `taptr.model.v3.per_frame.FrameState` calls each frame.

    Called like the decoder; runs it eagerly or captured, as decided (see the module).

    Args:
        decoder: the model's decoder (on ``device``).
        device: where it runs.
        setting: one of `CAPTURE_CHOICES`.
        key_for: the `taptr.runtime.measured.choice_key` its timing is kept under, for a
            number of points (`capture_key`).
        points: points the run tracks, or None to read them from the first call (a
            stream, whose points come and go).
        frames: frames this run will decode, or None for a stream of unknown length.
        clock: the timer (injected by tests).
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
        if setting not in CAPTURE_CHOICES:
            choices = ", ".join(CAPTURE_CHOICES)
            raise ValueError(f"unknown capture {setting!r}; choose from {choices}")
        self.decoder, self.device, self.setting = decoder, device, setting
        self.key_for, self.key = key_for, ""
        self.clock = clock
        self.frames_left = math.inf if frames is None else frames
        self.timing: CaptureTiming | None = None
        self.captured = setting == "on"
        # on the job: eager times, then captured times, while measuring
        self.measuring = False
        self.eager_times: list[float] = []
        self.captured_times: list[float] = []
        self.calls = 0
        self.announced = False  # the compile's notice, said once
        if points is not None:
            self._look_up(points)

    def _look_up(self, points: int) -> None:
        """Reads the timing kept for ``points`` and decides how the run starts."""
        self.key = self.key_for(points)
        if self.setting != "auto":
            return
        self.timing = CaptureTiming.read(kept_choice(self.key))
        if self.timing is not None:
            self.captured = self.timing.pays(self.frames_left)
        else:
            self.measuring = math.isfinite(self.frames_left)

    def __call__(self, *args: Any) -> Any:
        """Runs the decoder on one frame (the arguments of ``V3Decoder.forward``)."""
        if not self.key:
            self._look_up(args[0].shape[2])  # content (B, 1, N, C)
        self.calls += 1
        self.frames_left -= 1
        timed = self.measuring or (self.captured and self.calls == 1 and self.timing is not None)
        start = self._now() if timed else 0.0
        output = self._captured_call(args) if self.captured else self.decoder(*args)
        if timed and (self.measuring or self.captured):  # not after a failed capture
            self._record(self._now() - start)
        return output

    def _captured_call(self, args: tuple[Any, ...]) -> Any:
        if self.decoder not in _captured and not self.announced:
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
        self.announced = True

    def _give_up(self, error: Exception) -> None:
        line = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        logger.warning("capturing TAPTRv3's per-frame step failed (%s): running it eagerly", line)
        self.captured = False
        if self.setting == "auto":  # kept, so that later runs do not try again
            measured = min(self.eager_times, default=MIN_STEP_SECONDS)
            eager_s = self.timing.eager_s if self.timing else max(measured, MIN_STEP_SECONDS)
            keep(self.key, asdict(CaptureTiming(eager_s, math.inf, 0.0)))
        self.measuring = False

    def _now(self) -> float:
        synchronize(self.device)
        return self.clock()

    def _record(self, seconds: float) -> None:
        """Takes one timed call's seconds; decides when enough are timed."""
        if not self.measuring:  # the first captured call of a kept timing: its capture cost
            assert self.timing is not None
            cost = max(seconds - self.timing.captured_s, 0.0)
            self.timing = CaptureTiming(self.timing.eager_s, self.timing.captured_s, cost)
            keep(self.key, asdict(self.timing))
            return
        if not self.captured:
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
        if guess.pays(self.frames_left):
            self.captured = True
        else:
            self.measuring = False  # too short a run to pay for measuring: eager

    def _decide(self) -> None:
        eager_s = min(self.eager_times[1:])
        captured_s = min(self.captured_times[1:])
        capture_s = max(self.captured_times[0] - captured_s, 0.0)
        self.timing = CaptureTiming(eager_s, captured_s, capture_s)
        keep(self.key, asdict(self.timing))
        self.measuring = False
        # what is spent is spent: from here on only the per-frame times count
        self.captured = captured_s < eager_s * (1 - TOLERANCE)
        logger.info(
            "TAPTRv3's per-frame step: eager %.4f s, captured %.4f s (capture took %.1f s): %s",
            eager_s,
            captured_s,
            capture_s,
            "captured" if self.captured else "eager",
        )


def capture_key(
    device: torch.device, config: object, input_size: tuple[int, int], precision: str
) -> Callable[[int], str]:
    """Where a `CaptureTiming` is kept, for a number of points.

    The key names the machine, the model, the points' bucket (`points_bucket`), the input
    size and the precision.
    """

    def key(points: int) -> str:
        shape = f"{input_size[0]}x{input_size[1]} {points_bucket(points)} points {precision}"
        return choice_key("TAPTRv3 step capture", device, repr(config), shape)

    return key
