"""Checking exported graphs against the PyTorch model on a clip: parity and speed.

`compare` tracks the same points through the same frames twice: with the PyTorch model's
own driver (`taptr.runtime.engines.run_tracker`, its current attention kernel) and with the
exported graphs (TAPTR v1 and v2: the same sliding-window driver over the graphs,
`taptr.export.graph_runner`; TAPTRv3: the torch-free frame loop, `taptr.onnx.frame_loop`),
and reports the largest differences and the time each took.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch

from taptr.data.sample_video import make_sample_clip
from taptr.export.graph_runner import track_points
from taptr.export.graph_steps import load_steps
from taptr.export.manifest import ExportManifest
from taptr.model.taptr import TAPTR, normalize_frames
from taptr.model.trajectory import QuerySet
from taptr.model.v3.taptr import TAPTRv3
from taptr.onnx.frame_loop import track_points as track_frames
from taptr.onnx.graph_engines import open_graphs
from taptr.onnx.v3_manifest import V3Manifest
from taptr.runtime.engines import run_tracker
from taptr.runtime.frames import EncodedFrames
from taptr.task.results import TrackArrays


class Parity(NamedTuple):
    """Exported graphs versus PyTorch on one clip.

    Attributes:
        position_error: max |Δ| of the positions, normalised units (x / (W − 1), y / (H − 1)).
        position_error_pixels: the same in pixels of the model input.
        visibility_error: max |Δ| of the visibility logits (all three channels).
        torch_seconds: the PyTorch run, encoding included.
        exported_seconds: the exported run, encoding included.
    """

    position_error: float
    position_error_pixels: float
    visibility_error: float
    torch_seconds: float
    exported_seconds: float


def sample_queries(num_frames: int, num_points: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Points spread over the clip: start frames (N,) from 0 to T − 1 and (N, 2) positions."""
    rng = np.random.default_rng(seed)
    starts = np.linspace(0, num_frames - 1, num_points).round().astype(np.int64)
    positions = rng.uniform(0.05, 0.95, (num_points, 2)).astype(np.float32)
    return starts, positions


def sample_frames(num_frames: int, size: tuple[int, int], seed: int) -> np.ndarray:
    """The package's procedural clip at ``size`` (H, W), (T, 3, H, W) float32 in [0, 1]."""
    clip = make_sample_clip(num_frames=num_frames, height=size[0], width=size[1], seed=seed)
    return clip.video.transpose(0, 3, 1, 2).astype(np.float32) / 255


def torch_tracks(
    model: TAPTR,
    frames: np.ndarray,
    starts: np.ndarray,
    positions: np.ndarray,
    history_frames: int | None = None,
) -> TrackArrays:
    """The model's own driver on float32 frames (T, 3, H, W); outputs as `track_points`.

    ``history_frames``: TAPTRv3's history limit (default: the model's).
    """
    parameter = next(model.parameters())
    video = normalize_frames(torch.from_numpy(frames)).to(parameter)[None]  # (1, T, 3, H, W)
    queries = QuerySet(
        torch.from_numpy(starts)[None].to(parameter.device),
        torch.from_numpy(positions)[None].to(parameter),
        torch.ones(1, len(starts), dtype=torch.bool, device=parameter.device),
    )
    with torch.no_grad():
        output = run_tracker(
            model,
            queries,
            len(frames),
            EncodedFrames(model, video),
            parameter.dtype,
            history_frames=history_frames,
        )
    return TrackArrays(
        output.positions[0].float().cpu().numpy(), output.visibility_logits[0].float().cpu().numpy()
    )


def _best_time(repeats: int, run: Callable[[], TrackArrays]) -> tuple[float, TrackArrays]:
    """The shortest of ``repeats`` runs, and the last result."""
    best = float("inf")
    for _ in range(max(1, repeats)):
        began = time.perf_counter()
        result = run()
        best = min(best, time.perf_counter() - began)
    return best, result


ExportedRun = Callable[[np.ndarray, np.ndarray, np.ndarray], TrackArrays]
"""Frames (T, 3, H, W), start frames (N,) and positions (N, 2) → tracks, through graphs."""


def exported_tracker(
    model: TAPTR, directory: str | os.PathLike[str], threads: int | None
) -> tuple[ExportManifest | V3Manifest, int | None, ExportedRun]:
    """An export's manifest, its history limit (TAPTRv3) and how it tracks a clip.

    TAPTR v1 and v2 run through their window driver over the graphs; TAPTRv3 through the
    torch-free frame loop.
    """
    if isinstance(model, TAPTRv3):
        graphs = open_graphs(directory, "onnxruntime", threads=threads)

        def frame_loop(frames: np.ndarray, starts: np.ndarray, xy: np.ndarray) -> TrackArrays:
            return TrackArrays(*track_frames(graphs, frames, len(frames), starts, xy))

        return graphs.manifest, graphs.manifest.history_frames, frame_loop
    steps = load_steps(directory, threads=threads)

    def window_loop(frames: np.ndarray, starts: np.ndarray, xy: np.ndarray) -> TrackArrays:
        return track_points(steps, steps.manifest, frames, len(frames), starts, xy)

    return steps.manifest, None, window_loop


def compare(
    model: TAPTR,
    directory: str | os.PathLike[str],
    *,
    num_frames: int = 11,
    num_points: int = 8,
    seed: int = 0,
    repeats: int = 1,
    threads: int | None = None,
) -> Parity:
    """Tracks a sample clip with ``model`` and with the export in ``directory``.

    Args:
        model: the PyTorch model that was exported.
        directory: the export folder.
        num_frames: clip length T (11 gives two overlapping windows of 8).
        num_points: points N, starting on frames spread from 0 to T − 1.
        seed: seed of the clip's textures and of the point positions.
        repeats: runs of each side; the best time is reported.
        threads: CPU threads for onnxruntime (PyTorch uses its current setting).
    """
    manifest, history, run_exported = exported_tracker(model, directory, threads)
    frames = sample_frames(num_frames, manifest.input_size, seed)
    starts, positions = sample_queries(num_frames, num_points, seed)
    torch_seconds, expected = _best_time(
        repeats, lambda: torch_tracks(model.eval(), frames, starts, positions, history)
    )
    exported_seconds, exported = _best_time(
        repeats, lambda: run_exported(frames, starts, positions)
    )
    error = np.abs(exported.positions - expected.positions)  # (T, N, 2)
    pixels = error * (np.array(manifest.input_size[::-1], np.float32) - 1)
    return Parity(
        float(error.max()),
        float(pixels.max()),
        float(np.abs(exported.visibility_logits - expected.visibility_logits).max()),
        torch_seconds,
        exported_seconds,
    )
