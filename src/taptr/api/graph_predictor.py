"""`GraphPredictor`: `Predictor`'s surface over TAPTRv3's exported graphs in an engine.

``ModelSpec(engine="onnxruntime")`` (``--engine``) loads this instead of a `Predictor`: the
checkpoint is exported once into the cache (`taptr.export.cache`), its graphs opened in
the engine named, and `taptr.onnx.OnnxTracker` tracks. What the commands and the corpus
actors read of a predictor is here with the same values a `Predictor` of the same spec
holds (the source, the checkpoint file, the threshold, input size, support and history
settings), so the settings record and its digest are the same, and `track` returns a
`taptr.types.TrackingResult` as `Predictor.track` does (batch 1). Streaming goes through
`online_tracker` (`taptr.onnx.OnnxOnlineTracker`).

Only TAPTRv3 exports to the graphs the engines run; v1 and v2 checkpoints are refused in
one line. The graphs run on the CPU.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from taptr.types import ENGINE_CHOICES, TrackingResult

if TYPE_CHECKING:
    import torch

    from taptr.api.spec import ModelSpec
    from taptr.export.cache import ExportRequest
    from taptr.onnx.stream_tracker import OnnxOnlineTracker
    from taptr.onnx.video_tracker import OnnxTracker
    from taptr.task.support_schemes import SupportScheme
    from taptr.weights.checkpoint_facts import CheckpointFacts


def check_exportable(spec: ModelSpec, found: CheckpointFacts) -> None:
    """Refuses a spec a graph engine cannot run, in one line.

    Raises:
        ValueError: an unknown engine, a TAPTR v1 or v2 checkpoint, an untrained preset
            (no file to export), or context points other than the model's.
    """
    engine, config = spec.engine, found.config
    if engine not in ENGINE_CHOICES:
        raise ValueError(f"engine must be one of {', '.join(ENGINE_CHOICES)}, got {engine!r}")
    if config.version != 3:
        raise ValueError(
            f"the {engine} engine runs TAPTRv3 checkpoints; {found.name} is TAPTR"
            f"{'v2' if config.version == 2 else ' v1'}: use --engine torch"
        )
    if found.path is None:
        raise ValueError(
            f"the {engine} engine exports a checkpoint file; {found.name} is an untrained "
            "preset: use --engine torch"
        )
    points = spec.context_points
    if points is not None and points != config.context_points:
        raise ValueError(
            f"the {engine} engine runs the model's own context points "
            f"({config.context_points}); use --engine torch for --context-points {points}"
        )


def engine_options(spec: ModelSpec) -> dict[str, Any]:
    """The engine's options of ``spec``: its threads and its precision (``spec.dtype``).

    Raises:
        ValueError: a precision no graph engine runs (`taptr.onnx.precisions`).
    """
    from taptr.onnx.precisions import check_precision
    from taptr.runtime.threads import choose_threads

    return {
        "threads": choose_threads(spec.threads).threads,
        "precision": check_precision(spec.dtype),
    }


def load_graph_predictor(spec: ModelSpec) -> GraphPredictor:
    """The predictor ``spec`` describes, its graphs exported first when not cached.

    Raises:
        ValueError: see `check_exportable` and `engine_options`.
        ModuleNotFoundError: the engine's package (or, to export, onnx) is missing.
    """
    from taptr.export.cache import ExportRequest, cached_export
    from taptr.onnx.graph_engines import engine_module, engine_named
    from taptr.weights.checkpoint_facts import checkpoint_facts

    engine = engine_named(spec.engine)
    engine_module(engine)  # a missing engine before a minute of export
    found = checkpoint_facts(spec.checkpoint)
    check_exportable(spec, found)
    assert found.path is not None  # checked: an untrained preset is refused
    size = tuple(spec.input_size or found.config.input_size)
    request = ExportRequest(found.path, found.name, (int(size[0]), int(size[1])))
    folder = cached_export(request, spec.engine)
    threshold = found.config.visibility_threshold if found.threshold is None else found.threshold
    tracker = _open_tracker(spec, folder, threshold, request)
    return GraphPredictor(tracker, spec, found, threshold)


def _open_tracker(
    spec: ModelSpec, folder: Path, threshold: float, request: ExportRequest
) -> OnnxTracker:
    """The export's tracker; an entry the engine cannot open is exported again, once."""
    from taptr.export.cache import discard, export_entry, export_key, say
    from taptr.onnx.precisions import PrecisionError
    from taptr.onnx.video_tracker import OnnxTracker

    options = engine_options(spec)

    def opened(path: Path) -> OnnxTracker:
        return OnnxTracker(
            path,
            engine=spec.engine,
            history_frames=spec.history_frames,
            visibility_threshold=threshold,
            support_points=spec.support,
            **options,
        )

    try:
        return opened(folder)
    except PrecisionError:  # the engine's or the CPU's refusal, not a damaged export
        raise
    except ValueError as error:  # a graph damaged past the cache's own checks
        reason = " ".join(str(error).split())[:200]
        say(f"taptr: the exported graphs in {folder} are damaged ({reason}); exporting again")
        discard(folder)
        key = export_key(request)
        return opened(export_entry(request, key, folder, spec.engine))


class GraphPredictor:
    """Tracks points with TAPTRv3's exported graphs, as a `Predictor` does.

    Args:
        tracker: the export's torch-free tracker.
        spec: what it was loaded from.
        found: the checkpoint's facts.
        threshold: the visibility threshold (the file's calibrated one, else the config's).
    """

    model = None
    """No PyTorch model: the graphs check their own memory (`taptr.onnx.graph_memory`)."""

    def __init__(
        self,
        tracker: OnnxTracker,
        spec: ModelSpec,
        found: CheckpointFacts,
        threshold: float,
    ) -> None:
        self.tracker = tracker
        self.engine: str = spec.engine
        self.source: str = found.name
        self.checkpoint_path = found.path
        self.notice: str | None = None
        self.config = found.config
        self.input_size: tuple[int, int] = tuple(tracker.manifest.input_size)  # type: ignore[assignment]
        self.context_points: int = found.config.context_points
        self.support_points: str | None = spec.support
        self.history_frames: int | None = spec.history_frames
        self.visibility_threshold: float = threshold
        self.resize: str = tracker.manifest.resize

    @property
    def device(self) -> torch.device:
        """The CPU, where the graphs run."""
        import torch

        return torch.device("cpu")

    def chosen_support(self, num_queries: int) -> SupportScheme:
        """The registered scheme ``num_queries`` user points get."""
        return self.tracker.chosen_support(num_queries)

    def model_points(self, num_queries: int) -> int:
        """Points the model tracks for ``num_queries`` user points (support included)."""
        pattern = self.tracker.support_pattern
        return num_queries + self.chosen_support(num_queries).count(num_queries, pattern)

    def online_tracker(self) -> OnnxOnlineTracker:
        """A streaming tracker over the same graphs (`taptr.api.streaming` uses it)."""
        from taptr.onnx.stream_tracker import OnnxOnlineTracker

        return OnnxOnlineTracker(self.tracker)

    def track(
        self,
        video: Any,
        queries: Any = None,
        *,
        grid_size: int | None = None,
        grid_query_frame: int = 0,
        backward: bool = False,
        progress: bool = False,
    ) -> TrackingResult:
        """`Predictor.track` for one video: uint8 (T, H, W, 3) or a path; (N, 3) queries.

        Returns:
            `TrackingResult` with tracks (1, T, N, 2), visibility (1, T, N), logits
            (1, T, N) and queries (1, N, 3), as torch tensors. ``progress`` is not shown.
        """
        import torch

        if hasattr(video, "numpy") and not isinstance(video, np.ndarray):
            video = video.numpy()  # a CPU tensor of uint8 (T, H, W, 3) frames
        if queries is not None and hasattr(queries, "numpy"):
            queries = queries.numpy()
        result = self.tracker.track(
            video,
            queries,
            grid_size=grid_size,
            grid_query_frame=grid_query_frame,
            backward=backward,
        )
        return TrackingResult(
            *(torch.from_numpy(np.ascontiguousarray(part))[None] for part in result)
        )
