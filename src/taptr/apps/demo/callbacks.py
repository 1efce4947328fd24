"""The demo page's event handlers: each turns a page event into a call of `handlers`.

Every handler converts a `DemoError` (or any ValueError) of `taptr.apps.demo.uploads` and
`taptr.apps.demo.handlers` into a `gr.Error`, which the page shows as a message; the layout
and the wiring live in `taptr.apps.demo.app`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import gradio as gr
import numpy as np

from taptr.api.predictor import Predictor
from taptr.apps.demo import handlers
from taptr.apps.demo.settings import RUN_MAX_AGE_S, Limits
from taptr.apps.demo.uploads import (
    LoadedVideo,
    Point,
    add_point,
    build_queries,
    click_to_point,
    load_video,
    mask_from_editor,
    preview_frame,
)

_Out = TypeVar("_Out")


def points_text(points: list[Point]) -> str:
    """One ``t, x, y`` line per clicked point, in click order."""
    return "\n".join(f"{t}, {x:g}, {y:g}" for t, x, y in points)


def _user_error(error: ValueError) -> gr.Error:
    return gr.Error(str(error), print_exception=False)


def _report_to(progress: gr.Progress) -> handlers.ProgressFn:
    """The handlers' ``progress(fraction, text)`` callback, shown on Gradio's progress bar."""
    return lambda fraction, text: progress(fraction, desc=text)


@dataclass(frozen=True, eq=False)
class Callbacks:
    """The page's event handlers, bound to what every user shares.

    Each ``on_*`` method is one event's function; Gradio names the event's API endpoint
    after it, so the names are part of the page.

    Attributes:
        predictor: the tracker shared by all users.
        workspace: the demo's private temporary folder.
        limits: frame, resolution and point limits.
        model_name: stored in the NPZ metadata.
        samples: bundled videos, name → function writing the video into a folder.
        sample_dir: the folder the samples are written into.
    """

    predictor: Predictor
    workspace: Path
    limits: Limits
    model_name: str
    samples: Mapping[str, Callable[[Path], Path]]
    sample_dir: Path

    def on_upload(self, path: str | None) -> tuple[Any, ...]:
        """Shows an uploaded video, after checking the disk quota (which may delete it)."""
        if path is None:
            raise _user_error(ValueError("no video: upload a file or pick a sample"))
        try:
            handlers.check_disk_quota(self.workspace, self.limits.max_disk_bytes, upload=path)
            return self._show_video(load_video(path, self.limits))
        except ValueError as error:
            raise _user_error(error) from None

    def on_sample(self, name: str) -> tuple[Any, ...]:
        """Writes a bundled sample into the workspace and shows it in the video input too."""
        if name not in self.samples:
            raise _user_error(ValueError(f"unknown sample {name!r}"))
        path = self.samples[name](self.sample_dir)
        try:
            return (str(path), *self._show_video(load_video(path, self.limits)))
        except ValueError as error:
            raise _user_error(error) from None

    def on_frame(
        self, video: LoadedVideo | None, frame: int, points: list[Point]
    ) -> tuple[Any, ...]:
        """Moves the clicking image and both region editors to the chosen query frame."""
        if video is None:
            return None, None, None
        return _frame_views(video, frame, points)

    def on_click(
        self, video: LoadedVideo | None, points: list[Point], frame: int, evt: gr.SelectData
    ) -> tuple[Any, ...]:
        """Adds the clicked pixel as a query point on the current frame."""
        video = _require(video)
        try:
            points = add_point(points, click_to_point(evt.index, int(frame)), self.limits)
        except ValueError as error:
            raise _user_error(error) from None
        return points, preview_frame(video.frames, int(frame), points), points_text(points)

    def on_points_change(
        self, video: LoadedVideo | None, points: list[Point], frame: int
    ) -> tuple[Any, ...]:
        """Stores edited points (after undo or clear) and redraws them."""
        image = None if video is None else preview_frame(video.frames, int(frame), points)
        return points, image, points_text(points)

    @staticmethod
    def on_mode(mode: str) -> tuple[Any, ...]:
        """Shows only the inputs of the chosen query mode."""
        return (
            gr.Group(visible=mode == "points"),
            gr.Group(visible=mode == "region"),
            gr.Slider(visible=mode == "grid"),
        )

    def on_track(
        self,
        video: LoadedVideo | None,
        points: list[Point],
        mode: str,
        frame: int,
        region: dict[str, Any] | None,
        grid_size: int,
        backward: bool,
        progress: gr.Progress = gr.Progress(track_tqdm=True),  # noqa: B008 (Gradio's idiom)
    ) -> tuple[Any, ...]:
        """Tracks the queries of the chosen mode; returns the overlay, CSV, NPZ and message."""

        def job(video: LoadedVideo, height: int, width: int) -> handlers.TrackOutputs:
            queries = build_queries(
                mode,
                video_shape=video.frames.shape,
                query_frame=int(frame),
                limits=self.limits,
                points=points,
                mask=mask_from_editor(region, height, width),
                grid_size=int(grid_size),
            )
            self._make_room()
            return handlers.track_video(
                self.predictor,
                video,
                queries,
                folder=handlers.new_run_folder(self.workspace),
                backward=bool(backward),
                model_name=self.model_name,
                progress=_report_to(progress),
            )

        out = self._run_job(video, job)
        return str(out.overlay), str(out.csv), str(out.npz), out.message

    def on_edit(
        self,
        video: LoadedVideo | None,
        region: dict[str, Any] | None,
        image: np.ndarray | str | None,
        frame: int,
        opacity: float,
        progress: gr.Progress = gr.Progress(track_tqdm=True),  # noqa: B008 (Gradio's idiom)
    ) -> tuple[Any, ...]:
        """Pastes the image onto the painted region in every frame; returns video, message."""

        def job(video: LoadedVideo, height: int, width: int) -> handlers.EditOutputs:
            self._make_room()
            return handlers.edit_video(
                self.predictor,
                video,
                mask_from_editor(region, height, width),
                image,
                int(frame),
                folder=handlers.new_run_folder(self.workspace),
                limits=self.limits,
                opacity=float(opacity),
                progress=_report_to(progress),
            )

        out = self._run_job(video, job)
        return str(out.video), out.message

    def _show_video(self, video: LoadedVideo) -> tuple[Any, ...]:
        # A new video invalidates the points, the paint and the previous run's outputs.
        slider = gr.Slider(value=0, maximum=max(len(video.frames) - 1, 1), interactive=True)
        return (video, [], slider, *_frame_views(video, 0, []), "", video.message, None, None, None)

    def _make_room(self) -> None:
        # Old runs go first, so that the quota counts only what users can still download.
        handlers.prune_runs(self.workspace, RUN_MAX_AGE_S)
        handlers.check_disk_quota(self.workspace, self.limits.max_disk_bytes)

    def _run_job(
        self, video: LoadedVideo | None, job: Callable[[LoadedVideo, int, int], _Out]
    ) -> _Out:
        """Runs ``job(video, height, width)``, showing its ValueErrors on the page."""
        video = _require(video)
        try:
            height, width = video.frames.shape[1:3]
            return job(video, height, width)
        except ValueError as error:
            raise _user_error(error) from None


def _require(video: LoadedVideo | None) -> LoadedVideo:
    if video is None:
        raise _user_error(ValueError("no video yet: upload one or pick a sample first"))
    return video


def _frame_views(video: LoadedVideo, frame: int, points: list[Point]) -> tuple[Any, ...]:
    """The clicking image (with the frame's points) and the two editors' backgrounds."""
    frame = min(max(int(frame), 0), len(video.frames) - 1)
    image = video.frames[frame]
    return preview_frame(video.frames, frame, points), image, image
