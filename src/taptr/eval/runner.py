"""Running an evaluation: videos in, per-video and mean metrics and a report out.

`run_evaluation` is what ``taptr eval`` calls: it builds the tracker and protocol a
`EvalConfig` names, scores the videos (sharded over torchrun processes when there are
several), writes the report from the main process and returns it. `evaluate` is the loop
alone, for any protocol and any iterable of videos (an evaluation inside training).
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

from taptr.data.tapvid import PendingVideo
from taptr.eval.datasets import DATASETS, open_dataset
from taptr.eval.metrics import QUERY_MODES
from taptr.eval.overlays import Candidate, WorstVideos, worst_indices, write_overlay
from taptr.eval.protocols import (
    EvalProtocol,
    OfficialProtocol,
    StandardProtocol,
    UnscorableVideoError,
    VideoResult,
    evaluate_video,
)
from taptr.eval.report import build_report, package_versions, write_report
from taptr.eval.sharding import SINGLE_PROCESS, Shard, gather, process_group, resolve_device
from taptr.types import AUTOCAST_TYPES

logger = logging.getLogger(__name__)

TRACKERS = ("taptr", "static", "lk")
PROTOCOLS = ("standard", "official")


@dataclass(frozen=True)
class EvalConfig:
    """What to evaluate, as ``taptr eval`` takes it.

    Attributes:
        dataset: one of `taptr.eval.datasets.DATASETS`.
        root: dataset file or folder.
        mode: query mode, ``"first"`` or ``"strided"``.
        tracker: ``"taptr"`` (the model), ``"static"`` or ``"lk"`` (baselines).
        protocol: ``"standard"`` (canonical TAP-Vid scaling, any tracker) or ``"official"``
            (TAPTR's own evaluation; taptr tracker with a checkpoint only).
        checkpoint: the model's checkpoint file or name; None = the default model (the
            paper's weights, else the bundled one; standard protocol only).
        max_videos: score only the first videos of the set.
        device: where the model runs; None = CUDA when available, else CPU.
        overlays: draw overlay videos of this many worst videos.
        context_points: the predictor's context points (standard protocol, taptr tracker);
            None = the model's own count, 0 = none.
        support_points: the predictor's support scheme (standard protocol, taptr
            tracker; `taptr.Predictor`); None = the model's own.
        points_per_call: track each video's queries in groups of this many, one call each
            (standard protocol, taptr tracker); None = all at once.
        dtype: ``float32``, or run the model under autocast in ``bfloat16`` / ``float16``
            (standard protocol, taptr tracker).
    """

    dataset: str
    root: str
    mode: str = "first"
    tracker: str = "taptr"
    protocol: str = "standard"
    checkpoint: str | None = None
    max_videos: int | None = None
    device: str | None = None
    overlays: int = 0
    context_points: int | None = None
    support_points: str | None = None
    points_per_call: int | None = None
    dtype: str = "float32"

    def __post_init__(self) -> None:
        for name, value, allowed in (
            ("dataset", self.dataset, DATASETS),
            ("mode", self.mode, QUERY_MODES),
            ("tracker", self.tracker, TRACKERS),
            ("protocol", self.protocol, PROTOCOLS),
            ("dtype", self.dtype, AUTOCAST_TYPES),
        ):
            if value not in allowed:
                raise ValueError(f"unknown {name} {value!r}; expected one of {', '.join(allowed)}")
        if self.protocol == "official" and (self.tracker != "taptr" or self.checkpoint is None):
            raise ValueError(
                "the official protocol evaluates the TAPTR model only: use --tracker taptr "
                "with --checkpoint (a released checkpoint, its name such as taptrv3-official, "
                "or a taptr checkpoint)"
            )
        if self.tracker != "taptr" and self.checkpoint is not None:
            raise ValueError(f"--checkpoint is for the taptr tracker, not {self.tracker!r}")
        if self.max_videos is not None and self.max_videos < 1:
            raise ValueError(f"max_videos must be at least 1, got {self.max_videos}")
        if self.overlays < 0:
            raise ValueError(f"overlays must be >= 0, got {self.overlays}")


def build_protocol(config: EvalConfig, device: str) -> EvalProtocol:
    """The protocol and tracker ``config`` names, with the model (if any) on ``device``."""
    if config.protocol == "official":
        from taptr.eval.official_protocol import OfficialTAPTR
        from taptr.weights.registry import resolve_model

        assert config.checkpoint is not None  # checked by EvalConfig
        return OfficialProtocol(OfficialTAPTR(resolve_model(config.checkpoint), device=device))
    if config.tracker == "static":
        from taptr.eval.baselines import StaticTracker

        return StandardProtocol(StaticTracker())
    if config.tracker == "lk":
        from taptr.eval.baselines import LucasKanadeTracker

        return StandardProtocol(LucasKanadeTracker())
    from taptr.eval.predictor_tracker import PredictorTracker
    from taptr.runtime.precision import autocast_type

    tracker = PredictorTracker.from_pretrained(
        config.checkpoint,
        backward=config.mode == "strided",
        device=device,
        context_points=config.context_points,
        support_points=config.support_points,
        points_per_call=config.points_per_call,
        autocast=autocast_type(config.dtype),
    )
    return StandardProtocol(tracker)


def evaluate(
    protocol: EvalProtocol,
    videos: Iterable[PendingVideo],
    query_mode: str,
    *,
    max_videos: int | None = None,
    shard: Shard = SINGLE_PROCESS,
    worst: WorstVideos | None = None,
    progress: bool = False,
) -> list[VideoResult]:
    """Scores this process's share of the videos, loading one video at a time.

    Args:
        protocol: how videos are prepared, tracked and scaled.
        videos: the dataset's videos, in order.
        query_mode: ``"first"`` or ``"strided"``.
        max_videos: stop after this many videos of the set.
        shard: which videos this process scores (video i goes to rank i mod world size).
        worst: collects the worst videos for overlays.
        progress: show a progress bar.

    Returns:
        This process's results, in dataset order.
    """
    results = []
    selected = itertools.islice(enumerate(videos), max_videos)
    for index, pending in tqdm(
        selected, desc="videos", unit="video", disable=not progress, total=max_videos
    ):
        if not shard.owns(index):
            continue
        result, prediction = evaluate_video(protocol, pending.load(), query_mode, index)
        logger.info("%s: AJ %.4f", result.name, result.metrics["average_jaccard"])
        results.append(result)
        if worst is not None:
            worst.offer(Candidate(result, pending, prediction))
    return results


@dataclass
class EvalRun:
    """What `run_evaluation` returns.

    Attributes:
        report: the ``results.json`` content.
        is_main: True in the process that wrote the files (always, without torchrun).
        files: the files written by this process.
    """

    report: dict[str, Any]
    is_main: bool
    files: list[Path]


def run_evaluation(
    config: EvalConfig, out_dir: str | os.PathLike[str], *, progress: bool = False
) -> EvalRun:
    """Evaluates, writes ``results.json``, ``videos.csv`` and overlays into ``out_dir``.

    Under torchrun, videos are shared among the processes and the results gathered; the
    main process writes the report, each process the overlays of its own videos.

    Args:
        config: what to evaluate.
        out_dir: output folder (created if missing).
        progress: show a progress bar (main process only).
    """
    device = resolve_device(config.device)
    with process_group(device) as shard:
        protocol = build_protocol(config, device)
        videos = open_dataset(config.dataset, config.root)
        worst = WorstVideos(config.overlays) if config.overlays else None
        try:
            local = evaluate(
                protocol,
                videos,
                config.mode,
                max_videos=config.max_videos,
                shard=shard,
                worst=worst,
                progress=progress and shard.is_main,
            )
        except UnscorableVideoError as error:
            raise ValueError(f"{config.dataset} {config.root}: {error}") from None
        results = sorted(gather(local, shard), key=lambda r: r.index)
    check_something_scored(results, config)
    resolved = dataclasses.asdict(config) | {
        "root": str(Path(config.root).resolve()),
        "device": device.split(":")[0],
        "world_size": shard.world_size,
    }
    report = build_report(resolved, results, package_versions())
    files = write_report(report, out_dir) if shard.is_main else []
    if worst is not None:
        chosen = set(worst_indices(results, config.overlays))
        for candidate in worst.candidates():
            if candidate.result.index in chosen:
                name = f"overlay_{candidate.result.index:04d}_{candidate.result.name}.mp4"
                path = Path(out_dir) / "overlays" / _safe(name)
                files.append(write_overlay(path, protocol, candidate, config.mode))
    return EvalRun(report, shard.is_main, files)


def check_something_scored(results: list[VideoResult], config: EvalConfig) -> None:
    """Refuses an evaluation that scored nothing; warns about each video without points.

    Raises:
        ValueError: no video was read, or no video has an evaluable point (every point
            occluded wherever a query could go); the message names the dataset and videos.
    """
    where = f"{config.dataset} {config.root}"
    if not results:
        raise ValueError(f"{where}: no videos to evaluate")
    empty = [r.name for r in results if r.num_points == 0]
    if len(empty) == len(results):
        names = ", ".join(repr(name) for name in empty[:5]) + (" ..." if len(empty) > 5 else "")
        raise ValueError(
            f"{where}: no evaluable point in any of its {len(results)} videos ({names}): every "
            f"point is occluded on every frame a {config.mode!r} query could use; nothing to score"
        )
    for name in empty:
        logger.warning("%s: video %r has no evaluable point; it stays out of the mean", where, name)


def _safe(name: str) -> str:
    """A file name made of letters, digits, ``._-`` only."""
    return "".join(c if c.isalnum() or c in "._-" else "_" for c in name)
