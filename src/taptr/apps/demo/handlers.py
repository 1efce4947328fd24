"""The demo's two jobs, tracking and editing, as plain functions of the predictor API.

The page calls these with what the user chose; tests call them directly, without a server.
Each run writes into a fresh folder of the demo's private workspace (`new_run_folder`), so
outputs of different users and runs never collide, and `prune_runs` removes old ones from a
long-running server.

Conventions are the package's: videos (T, H, W, 3) uint8 RGB, queries (N, 3) as (t, x, y)
with (x, y) pixels (pixel centres at integers), tracks (T, N, 2) (x, y) pixels, visibility
(T, N) bool, masks (H, W) bool.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from taptr.api.predictor import Predictor
from taptr.api.regions import sample_region_queries
from taptr.apps.demo.settings import Limits
from taptr.apps.demo.uploads import DemoError, LoadedVideo, read_paste_image
from taptr.apps.editing import overlay_region
from taptr.io.tracks import save_tracks_csv, save_tracks_npz
from taptr.io.video import write_video
from taptr.viz.draw import draw_tracks

ProgressFn = Callable[[float, str], object]
"""Called with (fraction done in [0, 1], what is happening); Gradio's `gr.Progress` fits."""

RUN_PREFIX = "run-"


@dataclass(frozen=True)
class TrackOutputs:
    """What a tracking run wrote.

    Attributes:
        overlay: H.264 mp4 of the video with the tracks drawn on it.
        csv: ``tracks.csv``, one ``frame,point,x,y,visible`` row per frame and point.
        npz: ``tracks.npz`` with tracks (T, N, 2), visibility (T, N), queries (N, 3) and
            metadata (see `taptr.io.tracks`).
        message: one line for the page.
    """

    overlay: Path
    csv: Path
    npz: Path
    message: str


@dataclass(frozen=True)
class EditOutputs:
    """What an editing run wrote.

    Attributes:
        video: H.264 mp4 of the edited video.
        message: one line for the page.
    """

    video: Path
    message: str


def new_run_folder(root: str | os.PathLike[str]) -> Path:
    """A new, empty, uniquely named folder under the workspace ``root`` for one run."""
    return Path(tempfile.mkdtemp(prefix=RUN_PREFIX, dir=root))


def prune_runs(root: str | os.PathLike[str], max_age_s: float) -> int:
    """Removes run folders under ``root`` older than ``max_age_s`` seconds; returns how many."""
    deadline = time.time() - max_age_s
    removed = 0
    for folder in Path(root).glob(f"{RUN_PREFIX}*"):
        if folder.is_dir() and folder.stat().st_mtime < deadline:
            shutil.rmtree(folder, ignore_errors=True)
            removed += 1
    return removed


def check_disk_quota(root: str | os.PathLike[str], limit: int, upload: str | None = None) -> None:
    """Raises a `DemoError` when the workspace holds more than ``limit`` bytes.

    Args:
        root: the server's workspace.
        limit: the quota in bytes.
        upload: a file just written into the workspace by an upload; it is deleted when
            the quota is exceeded, so a refused upload takes no space.
    """
    used = sum(p.stat().st_size for p in Path(root).rglob("*") if p.is_file())
    if used <= limit:
        return
    if upload is not None and Path(upload).resolve().is_relative_to(Path(root).resolve()):
        Path(upload).unlink(missing_ok=True)
    raise DemoError(
        f"the demo's disk space is full ({used / 2**30:.1f} of {limit / 2**30:.1f} GiB); "
        "runs expire after an hour, try again later"
    )


def track_video(
    predictor: Predictor,
    video: LoadedVideo,
    queries: np.ndarray,
    *,
    folder: str | os.PathLike[str],
    backward: bool = False,
    model_name: str = "",
    progress: ProgressFn | None = None,
) -> TrackOutputs:
    """Tracks queries through a video and writes the overlay, CSV and NPZ files.

    Args:
        predictor: the tracker.
        video: the video, as loaded by `taptr.apps.demo.uploads.load_video`.
        queries: (N, 3) float (t, x, y), (x, y) in pixels of the video.
        folder: where the three files are written (created if missing).
        backward: also track the frames before each query frame.
        model_name: stored in the NPZ metadata.
        progress: optional progress callback; when given, the predictor also shows its
            per-window progress bar (tqdm), which Gradio can follow.

    Returns:
        The paths written and a one-line summary.
    """
    report = progress or _ignore
    frames = video.frames
    report(0.0, "tracking")
    result = predictor.track(frames, queries, backward=backward, progress=progress is not None)
    tracks = result.tracks[0].numpy()  # (T, N, 2)
    visibility = result.visibility[0].numpy()  # (T, N)
    out = Path(folder)
    report(0.85, "drawing the overlay")
    # Without the backward pass nothing is known before a query frame: draw nothing there.
    query_frames = None if backward else queries[:, 0].astype(np.int64)
    overlay = draw_tracks(frames, tracks, visibility, query_frames=query_frames)
    report(0.9, "writing the files")
    overlay_path = write_video(out / "overlay.mp4", overlay, video.fps)
    csv_path = save_tracks_csv(out / "tracks.csv", tracks, visibility)
    metadata = {
        "video": video.name,
        "num_frames": int(frames.shape[0]),
        "height": int(frames.shape[1]),
        "width": int(frames.shape[2]),
        "fps": video.fps,
        "model": model_name,
        "input_size": list(predictor.input_size),
        "backward": bool(backward),
        "coordinates": "(x, y) pixels, pixel centres at integers",
    }
    npz_path = save_tracks_npz(out / "tracks.npz", tracks, visibility, queries, metadata)
    report(1.0, "done")
    visible = float(visibility.mean()) if visibility.size else 0.0
    message = (
        f"tracked {len(queries)} points through {frames.shape[0]} frames "
        f"({visible:.0%} of the positions visible)"
    )
    return TrackOutputs(overlay_path, csv_path, npz_path, message)


def edit_video(
    predictor: Predictor,
    video: LoadedVideo,
    mask: np.ndarray,
    image: np.ndarray | str | os.PathLike[str] | None,
    query_frame: int,
    *,
    folder: str | os.PathLike[str],
    limits: Limits,
    stride: int = 6,
    opacity: float = 1.0,
    progress: ProgressFn | None = None,
) -> EditOutputs:
    """Pastes an image onto a painted region that follows the video (the paper's editing).

    Points sampled inside the region on ``query_frame`` are tracked both ways in time, and
    each frame warps the image by the region's fitted motion (`taptr.apps.editing`).

    Args:
        predictor: the tracker.
        video: the video, as loaded by `taptr.apps.demo.uploads.load_video`.
        mask: (H, W) bool region painted on ``query_frame``.
        image: (h, w, 3) RGB or (h, w, 4) RGBA uint8 image to paste, or (h, w) grey; or
            the uploaded file, read by `taptr.apps.demo.uploads.read_paste_image`.
        query_frame: the frame t the region was painted on.
        folder: where ``edited.mp4`` is written (created if missing).
        limits: the point limit for the region's samples.
        stride: pixel spacing of the tracked points inside the region.
        opacity: image opacity in [0, 1].
        progress: optional progress callback, as for `track_video`.

    Returns:
        The edited video's path and a one-line summary.

    Raises:
        DemoError: no image, an empty region, or a region on the wrong frame size.
    """
    report = progress or _ignore
    frames = video.frames
    if image is None:
        raise DemoError("no image to paste: upload an image for the region")
    if mask.shape != frames.shape[1:3] or not mask.any():
        raise DemoError("no region painted: paint over the query frame with the brush")
    if not 0.0 <= opacity <= 1.0:
        raise DemoError(f"opacity must lie in [0, 1], got {opacity}")
    if isinstance(image, (str, os.PathLike)):  # an upload: read header first (uploads.py)
        image = read_paste_image(image)
    image = np.asarray(image, dtype=np.uint8)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    queries = sample_region_queries(mask, query_frame, stride=stride, max_points=limits.max_points)
    report(0.0, "tracking the region")
    result = predictor.track(frames, queries, backward=True, progress=progress is not None)
    report(0.85, "pasting the image")
    edited = overlay_region(
        frames,
        image,
        mask,
        result.tracks[0].numpy(),
        result.visibility[0].numpy(),
        query_frame,
        opacity=opacity,
    )
    path = write_video(Path(folder) / "edited.mp4", edited, video.fps)
    report(1.0, "done")
    return EditOutputs(path, f"tracked {len(queries)} region points; pasted the image")


def _ignore(fraction: float, description: str) -> None:
    """The progress callback when nobody listens."""
