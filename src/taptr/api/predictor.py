"""`Predictor`: pixels and (t, x, y) queries in, tracks and visibility out.

The predictor holds what belongs to the task: it resizes the frames to the model's input
size, turns pixel queries into the model's points and surrounds them with context or
support points, hands both to its `taptr.runtime.runner.Runner` (which runs the model on
this machine: device, precision, the speed choices, TAPTRv3's captured step, windows or
frames), maps positions back to the input pixels per axis, returns each query exactly on
its own frame, and optionally tracks backwards in time (a second pass over the
time-reversed video).

Coordinates are pixel centres at integers in both the input video and the model input;
the model's normalised units are x / (W − 1), y / (H − 1), so (0, 0) and (W − 1, H − 1)
map onto each other across resolutions (the official convention).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from taptr.api.backward import needs_backward, track_both_ways
from taptr.api.context_points import with_context
from taptr.api.inputs import grid_queries, query_tensor, video_tensor
from taptr.api.prepared_frames import PreparedFrames
from taptr.api.queries import model_queries, on_own_frames
from taptr.api.resize import resize_frames
from taptr.api.support import numpy_type, with_support
from taptr.config import ModelConfig
from taptr.geometry import normalized_to_pixels
from taptr.memory_estimate import check_memory, estimate_tracking
from taptr.model.taptr import TAPTR, normalize_frames
from taptr.model.trajectory import QuerySet
from taptr.runtime.precision import autocast_type as autocast_type  # re-exported: public
from taptr.runtime.precision import precision_context as precision_context  # re-exported
from taptr.runtime.runner import Runner
from taptr.task.support_schemes import LOCAL_SUPPORT_BUDGET as LOCAL_SUPPORT_BUDGET
from taptr.task.support_schemes import (
    SupportPattern,
    SupportScheme,
    choose_scheme,
    model_points,
    support_scheme,
)
from taptr.types import TrackingResult

VideoInput = np.ndarray | Tensor | str | os.PathLike


class Predictor:
    """Tracks points through videos with a TAPTR model.

    Args:
        model: the network (moved to ``device`` and put in eval mode).
        input_size: (height, width) frames are resized to; default: the model config's.
        visibility_threshold: a point is visible where sigmoid(visibility logit) exceeds it;
            default: the model config's (0.5 for TAPTRv2, 0.45 for TAPTRv3, as their
            official evaluations decide).
        device: where to run; default: CUDA if available, else CPU.
        dtype: floating type of the model's weights and inputs (float32; float64 for
            exact comparisons).
        autocast: run the model under ``torch.autocast`` with this type (``torch.float16``
            or ``torch.bfloat16``), weights kept in ``dtype``: matrix products in half
            precision, reductions and the position updates in float32, as the official demo
            runs (float16). None (the default) runs in ``dtype`` throughout. On the CPU,
            ``torch.bfloat16`` instead runs the fast execution's products in bfloat16
            through oneDNN where the CPU has native bfloat16 (AVX512-BF16 or AMX;
            `taptr.model.ops.dense.bfloat16_products`), and float32 with a warning where it
            has not. Accuracy against float32 is in docs/BENCHMARKS.md.
        kernel: the deformable-attention kernel: ``auto`` measures ``gather`` against
            ``grid_sample`` on accelerators (`taptr.runtime.kernel_choice`) and keeps the
            model's execution on CPU (where ``gather`` is measured faster); ``measure``
            measures on any device; ``gather`` or ``grid_sample`` sets it.
        frames_per_call: frames encoded per encoder call: ``auto`` times the candidates
            that fit the device's budget at the input size, once per machine and shape,
            and remembers the fastest (`taptr.runtime.encode_choice`; one frame per call for
            512 × 512 on a CPU, without timing); a number sets it. Speed only. On a CPU
            the predictor also times, once per machine and shape, whether the fast
            execution's linear layers run faster through oneDNN or the BLAS and its
            frames channels-last or not (`taptr.runtime.cpu_choice`). Under float16 autocast
            on a CPU (slow there) nothing is timed and ``auto`` is one frame per call.
            The memory of the smallest run at the input size is checked before any timing.
        context_points: pad each video's queries with seeded context points up to this
            many points before the model runs (`taptr.api.context_points`); they are never
            returned. Default: the model config's (800 for the paper's weights, the points
            per training clip for models trained by taptr); 0 turns it off.
        support_points: how the user's points are surrounded before the model runs, never
            returned: ``"random"`` (``context_points`` seeded points, TAPTRv2's recipe),
            ``"local_and_grid"`` (63 points around each query and a 6 × 6 grid, TAPTRv3's
            evaluation), ``"grid"`` (the grid alone), ``"none"``, or any scheme
            registered in `taptr.task.support_schemes`. Default: the model config's,
            except that TAPTRv3 falls back to ``"grid"`` when the local points would take
            it past `LOCAL_SUPPORT_BUDGET` points (more than 32 queries).
        history_frames: TAPTRv3: the most past frames its long-temporal attention holds
            per point, the current one included (0: the whole video; memory grows by
            C · 4 bytes per point and frame, 1 KiB for the released models). Default: the
            model's (0).
        capture: TAPTRv3: whether its per-frame decoder step is compiled once and replayed
            (CUDA graphs on CUDA, Inductor on a CPU; `taptr.runtime.step_capture`):
            ``auto`` where a measurement kept for the machine and shape says it saves
            more time than it costs over the frames to decode (a long video with nothing
            kept measures it on the job), ``on`` always, ``off`` never. Speed only: the
            outputs are the eager step's up to float rounding. Not on a CPU in bfloat16.
        source: the checkpoint's name or path, for messages.
        notice: what to tell users about the model (the default model's fallback line).

    Attributes:
        runner: how the model runs on this machine (`taptr.runtime.runner.Runner`), made
            from ``device``, ``dtype``, ``autocast``, ``kernel``, ``frames_per_call``,
            ``history_frames`` and ``capture``; the online tracker runs through it too.
    """

    checkpoint_path: str | os.PathLike[str] | None = None
    """The file the weights were read from, named or not (set by `from_pretrained`)."""

    def __init__(
        self,
        model: TAPTR,
        *,
        input_size: tuple[int, int] | None = None,
        visibility_threshold: float | None = None,
        device: str | torch.device | None = None,
        dtype: torch.dtype = torch.float32,
        autocast: torch.dtype | None = None,
        kernel: str = "auto",
        frames_per_call: int | str = "auto",
        context_points: int | None = None,
        support_points: str | None = None,
        history_frames: int | None = None,
        capture: str = "auto",
        source: str | None = None,
        notice: str | None = None,
    ) -> None:
        config = model.config
        if input_size is None:  # an explicit size is used as given, never replaced
            input_size = config.input_size if config else (512, 512)
        height, width = input_size
        self.input_size: tuple[int, int] = (int(height), int(width))
        self.runner = Runner(
            model,
            input_size=self.input_size,
            device=device,
            dtype=dtype,
            autocast=autocast,
            history_frames=history_frames,
            capture=capture,
        )
        self.model = self.runner.model
        self.resize = config.resize if config else "bilinear"
        self.context_points = _context_points(context_points, config)
        if support_points is not None:
            support_scheme(support_points)  # refuses unknown names, listing the schemes
        self.support_points = support_points
        self.visibility_threshold = _visibility_threshold(visibility_threshold, config)
        self.source = source
        self.notice = notice
        # the smallest run's memory before any timing: timing an input size that cannot
        # run would take minutes and gigabytes only to be refused after it
        self._check_memory(1, 0, (1, 1), False, smallest=True)
        # last: these time the model, which only a valid predictor needs
        self.runner.choose_speed(kernel, frames_per_call)

    @property
    def device(self) -> torch.device:
        """Where the model runs (the runner's)."""
        return self.runner.device

    @property
    def dtype(self) -> torch.dtype:
        """Floating type of the model's weights and inputs."""
        return self.runner.dtype

    @property
    def autocast(self) -> torch.dtype | None:
        """The autocast type the model runs in (None: ``dtype`` throughout)."""
        return self.runner.autocast

    @property
    def frames_per_call(self) -> int:
        """Frames encoded per encoder call, as chosen."""
        return self.runner.frames_per_call

    @property
    def history_frames(self) -> int | None:
        """TAPTRv3's history limit as asked (None: the model's)."""
        return self.runner.history_frames

    @classmethod
    def from_pretrained(
        cls, name_or_path: str | os.PathLike[str] | None = None, **kwargs: Any
    ) -> Predictor:
        """A predictor for a checkpoint file or a model name.

        None gives the default model: the paper's weights (``taptrv2-official``, IDEA
        License 1.0, non-commercial; from the Hugging Face cache or downloaded once), else
        the bundled ``taptr-small-synthetic`` (Apache-2.0) with one warning (also kept in
        ``notice``). Without an explicit ``visibility_threshold``,
        a threshold stored in the file by ``taptr calibrate`` is used (0.5 when there is none).
        """
        from taptr.weights.registry import load_model

        choice = load_model(name_or_path)
        if "visibility_threshold" not in kwargs and choice.visibility_threshold is not None:
            kwargs["visibility_threshold"] = choice.visibility_threshold
        kwargs.setdefault("source", choice.name)
        kwargs.setdefault("notice", choice.notice)
        predictor = cls(choice.model, **kwargs)
        predictor.checkpoint_path = choice.path
        return predictor

    @torch.no_grad()
    def track(
        self,
        video: VideoInput,
        queries: np.ndarray | Tensor | None = None,
        *,
        grid_size: int | None = None,
        grid_query_frame: int = 0,
        backward: bool = False,
        progress: bool = False,
    ) -> TrackingResult:
        """Tracks query points through a video.

        Args:
            video: uint8 numpy (T, H, W, 3); torch (B, T, 3, H, W) uint8 or float in [0, 1];
                or a path to a video file or a folder of images.
            queries: (N, 3) or (B, N, 3) as (t, x, y): frame index and pixel position
                (pixel centres at integers).
            grid_size: instead of queries, track a grid_size × grid_size grid of points.
            grid_query_frame: the frame the grid is placed on.
            backward: also track frames before each query frame (time-reversed pass).
                Without it, frames before a point's query frame hold its query position
                and are reported not visible (logit −inf).
            progress: show a progress bar over the windows (on stderr).

        Returns:
            `TrackingResult` with tracks (B, T, N, 2) in input pixels, visibility
            (B, T, N), visibility logits (B, T, N) and the queries (B, N, 3).
        """
        frames = video_tensor(_read_if_path(video))
        batch, num_frames, _, height, width = frames.shape
        if num_frames == 0:
            raise ValueError("the video has no frames")
        if (queries is None) == (grid_size is None):
            raise ValueError("pass exactly one of queries or grid_size")
        if grid_size is not None:
            if not 0 <= grid_query_frame < num_frames:
                raise ValueError(f"grid_query_frame outside [0, {num_frames})")
            queries = grid_queries(grid_size, grid_query_frame, height, width)
        assert queries is not None
        query = query_tensor(queries, batch, num_frames, height, width)
        self._check_memory(num_frames, query.shape[1], (height, width), backward)
        engine = self.runner.engine
        # the reversed pass runs only for videos with a query after frame 0
        passes = sum(1 + (backward and needs_backward(query[b])) for b in range(batch))
        total = engine.steps(num_frames) * passes
        with tqdm(total=total, desc="tracking", unit=engine.unit, disable=not progress) as bar:
            results = [
                self._track_one(frames[b], query[b], backward, bar.update) for b in range(batch)
            ]
        tracks, logits = (torch.stack(parts) for parts in zip(*results, strict=True))
        visibility = logits.sigmoid() > self.visibility_threshold
        return TrackingResult(tracks, visibility, logits, query)

    def _check_memory(
        self,
        num_frames: int,
        num_points: int,
        frame_size: tuple[int, int],
        backward: bool,
        *,
        smallest: bool = False,
    ) -> None:
        """Refuses a run whose estimated peak memory exceeds the budget (before it starts).

        ``smallest``: the check of the smallest run at the input size (no query, one frame
        of one pixel), made before anything is timed; its message names the input size only.

        Raises:
            taptr.memory_estimate.MemoryEstimateError: a one-line ValueError naming the
                knobs (`taptr.memory_estimate`).
        """
        if self.model.config is None:
            return
        points = self.model_points(num_points)
        estimate = estimate_tracking(
            self.model.config,
            input_size=self.input_size,
            num_frames=num_frames,
            num_points=points,
            frame_size=frame_size,
            whole_video=False,  # the caller holds the video already
            backward=backward,
            history_frames=self.history_frames,
            frames_per_call=self.frames_per_call,
        )
        size = "x".join(map(str, self.input_size))
        what = f"tracking {points:,} points through {num_frames:,} frames at {size}"
        knobs = "use a smaller input size (input_size=, --input-size), fewer points or frames"
        if smallest:
            what = f"running the model at {size} at all ({points:,} points, one frame)"
            knobs = "use a smaller input size (input_size=, --input-size)"
        check_memory(estimate, what, knobs, self.device.type)

    def prepare(self, frames: Tensor) -> Tensor:
        """Model input from frames: (F, 3, H, W) uint8 or in [0, 1] → (1, F, 3, H_m, W_m).

        Resized as the model's config says (`taptr.api.resize`: the official demo's Lanczos
        for the paper's weights, antialiased bilinear for taptr's own models), then
        ImageNet-normalised.
        """
        if self.resize == "bilinear":  # runs on the model's device; Lanczos runs in Pillow
            frames = frames.to(self.device)
        chunk = resize_frames(frames, self.input_size, self.resize).to(self.device)
        return normalize_frames(chunk)[None].to(self.dtype)

    @property
    def support_pattern(self) -> SupportPattern:
        """The support schemes' numbers in the model's normalised units and type."""
        return SupportPattern.normalised(numpy_type(self.dtype), context_points=self.context_points)

    def chosen_support(self, num_queries: int) -> SupportScheme:
        """The registered scheme ``num_queries`` user points get (see the class)."""
        config = self.model.config
        configured = config.support_points if config else "random"
        return choose_scheme(configured, num_queries, self.support_pattern, self.support_points)

    def support_scheme(self, num_queries: int) -> str:
        """The name of the support ``num_queries`` user points get (see the class)."""
        return self.chosen_support(num_queries).name

    def model_points(self, num_queries: int) -> int:
        """How many points the model tracks for ``num_queries`` user points (support included)."""
        return model_points(self.chosen_support(num_queries), num_queries, self.support_pattern)

    def with_support(
        self, queries: QuerySet, num_frames: int | None, scheme: str | None = None
    ) -> QuerySet:
        """The model's point set: the user's points, then their context or support points.

        Args:
            queries: the user's points (B, N, ·) in model units.
            num_frames: the video's length, or None for a stream.
            scheme: the support to add; default the one chosen for the N points.
        """
        count = queries.start_frames.shape[1]
        chosen = self.chosen_support(count) if scheme is None else support_scheme(scheme)
        if chosen.drawn:  # TAPTRv2's seeded context points, drawn in the input's pixels
            return with_context(queries, self.context_points, self.input_size, num_frames)
        return with_support(queries, chosen.name)

    def _track_one(
        self, frames: Tensor, queries: Tensor, backward: bool, on_window: Callable[[], object]
    ) -> tuple[Tensor, Tensor]:
        """One video: frames (T, 3, H, W), queries (N, 3) → tracks (T, N, 2), logits (T, N)."""

        def one_pass(pass_queries: Tensor, reverse: bool) -> tuple[Tensor, Tensor]:
            return self._forward_pass(frames, pass_queries, on_window, reverse)

        if backward:
            tracks, logits = track_both_ways(one_pass, queries, frames.shape[0])
        else:
            tracks, logits = one_pass(queries, False)
        return on_own_frames(tracks, logits, queries, hide_earlier=not backward)

    def _forward_pass(
        self, frames: Tensor, queries: Tensor, on_window: Callable[[], object], reverse: bool
    ) -> tuple[Tensor, Tensor]:
        """Forward-in-time tracking: (T, 3, H, W), (N, 3) → tracks (T, N, 2), logits (T, N).

        With ``reverse``, the video is read backwards (frame t of the pass is frame T − 1 − t),
        window by window, without a reversed copy of the whole video.
        """
        num_frames, _, height, width = frames.shape
        query_set = model_queries(queries, height, width, self.device, self.dtype)
        query_set = self.with_support(query_set, num_frames)
        load = PreparedFrames(frames, self.prepare, reverse)
        output = self.runner.track(query_set, num_frames, load, on_window)
        real = queries.shape[0]  # context points come after the user's and are dropped
        positions = output.positions[0, :, :real].float()
        logits = output.visibility_logits[0, :, :real, 1].float()
        if not bool(torch.isfinite(positions).all()) or bool(logits.isnan().any()):
            raise ValueError(
                f"the model {self.source or '(unnamed)'} produced NaN or infinite tracks: its "
                "weights are corrupt or were trained into divergence"
            )
        return normalized_to_pixels(positions, height, width).cpu(), logits.cpu()


def _read_if_path(video: VideoInput) -> np.ndarray | Tensor:
    if isinstance(video, (str, os.PathLike)):
        from taptr.io.video import read_video

        return read_video(video)
    return video


def _context_points(context_points: int | None, config: ModelConfig | None) -> int:
    """The context points asked for, else the config's (0 without one).

    Raises:
        ValueError: not a whole number, or below 0.
    """
    if context_points is None:
        context_points = config.context_points if config else 0
    if isinstance(context_points, bool) or not isinstance(context_points, int):
        raise ValueError(f"context_points must be a whole number, got {context_points!r}")
    if context_points < 0:
        raise ValueError(f"context_points must be >= 0, got {context_points}")
    return context_points


def _visibility_threshold(threshold: float | None, config: ModelConfig | None) -> float:
    """The threshold asked for, else the config's (0.5 without one).

    Raises:
        ValueError: outside (0, 1).
    """
    if threshold is None:
        threshold = config.visibility_threshold if config else 0.5
    if not 0 < threshold < 1:
        raise ValueError(f"visibility_threshold must lie in (0, 1), got {threshold}")
    return threshold
