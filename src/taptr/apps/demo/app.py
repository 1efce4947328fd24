"""The Gradio page of ``taptr demo``: components wired to the plain handlers.

The page has a video source (an upload or a bundled sample) and a query-frame slider shared
by two tabs:

- **Track points**: click points on the query frame (undo, clear), paint a region, or use a
  grid; optionally track backwards; run with a progress bar; watch the overlay video and
  download ``tracks.csv`` and ``tracks.npz``;
- **Edit video**: paint a region on the query frame, upload an image, get the video with
  the image stuck to the region.

Everything that is not layout lives in `taptr.apps.demo.uploads` and
`taptr.apps.demo.handlers`; each callback here converts their `DemoError` (or any
ValueError) into a `gr.Error`, which the page shows as a message. Per-user state (the
decoded video, the clicked points) is held in `gr.State`, so users never see each other's
data.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import gradio as gr
import numpy as np

from taptr.api.predictor import Predictor
from taptr.apps.demo import handlers
from taptr.apps.demo.settings import RUN_MAX_AGE_S, Limits
from taptr.apps.demo.uploads import (
    QUERY_MODES,
    SAMPLES,
    LoadedVideo,
    Point,
    add_point,
    build_queries,
    click_to_point,
    load_video,
    mask_from_editor,
    preview_frame,
)

_BRUSH = gr.Brush(colors=["rgba(255, 40, 90, 0.6)"], color_mode="fixed", default_size=12)
_MODE_LABELS = {"points": "Clicked points", "region": "Painted region", "grid": "Grid"}


def gradio_samples() -> dict[str, Callable[[Path], Path]]:
    """Real footage that ships inside Gradio (a rotating globe), when the install has it."""
    video = Path(gr.__file__).parent / "media_assets" / "videos" / "b.mp4"

    def copy(folder: Path) -> Path:
        # Gradio serves files from the workspace only (allowed_paths), not from site-packages.
        target = folder / "gradio-globe.mp4"
        if not target.is_file():
            shutil.copyfile(video, target)
        return target

    return {"Gradio's sample video (rotating globe, 480×270)": copy} if video.is_file() else {}


def build_app(
    predictor: Predictor,
    *,
    workspace: Path,
    limits: Limits | None = None,
    model_name: str = "",
    samples: Mapping[str, Callable[[Path], Path]] | None = None,
) -> gr.Blocks:
    """Builds the page (without launching it).

    Args:
        predictor: the tracker shared by all users.
        workspace: the demo's private temporary folder; samples and run outputs go there.
        limits: frame, resolution and point limits.
        model_name: shown on the page and stored in the NPZ metadata.
        samples: bundled videos, name → function writing the video into a folder; default:
            taptr's generated clips and, when present, Gradio's sample video.
    """
    limits = limits or Limits()
    samples = dict(samples) if samples is not None else {**SAMPLES, **gradio_samples()}
    sample_dir = workspace / "samples"
    sample_dir.mkdir(parents=True, exist_ok=True)

    def user_error(error: ValueError) -> gr.Error:
        return gr.Error(str(error), print_exception=False)

    def frame_views(video: LoadedVideo, frame: int, points: list[Point]) -> tuple[Any, ...]:
        frame = min(max(int(frame), 0), len(video.frames) - 1)
        image = video.frames[frame]
        return preview_frame(video.frames, frame, points), image, image

    def show_video(video: LoadedVideo) -> tuple[Any, ...]:
        slider = gr.Slider(value=0, maximum=max(len(video.frames) - 1, 1), interactive=True)
        return (video, [], slider, *frame_views(video, 0, []), "", video.message, None, None, None)

    def on_upload(path: str | None) -> tuple[Any, ...]:
        if path is None:
            raise user_error(ValueError("no video: upload a file or pick a sample"))
        try:
            handlers.check_disk_quota(workspace, limits.max_disk_bytes, upload=path)
            return show_video(load_video(path, limits))
        except ValueError as error:
            raise user_error(error) from None

    def on_sample(name: str) -> tuple[Any, ...]:
        if name not in samples:
            raise user_error(ValueError(f"unknown sample {name!r}"))
        path = samples[name](sample_dir)
        try:
            return (str(path), *show_video(load_video(path, limits)))
        except ValueError as error:
            raise user_error(error) from None

    def require(video: LoadedVideo | None) -> LoadedVideo:
        if video is None:
            raise user_error(ValueError("no video yet: upload one or pick a sample first"))
        return video

    def on_frame(video: LoadedVideo | None, frame: int, points: list[Point]) -> tuple[Any, ...]:
        if video is None:
            return None, None, None
        return frame_views(video, frame, points)

    def on_click(
        video: LoadedVideo | None, points: list[Point], frame: int, evt: gr.SelectData
    ) -> tuple[Any, ...]:
        video = require(video)
        try:
            points = add_point(points, click_to_point(evt.index, int(frame)), limits)
        except ValueError as error:
            raise user_error(error) from None
        return points, preview_frame(video.frames, int(frame), points), points_text(points)

    def on_points_change(
        video: LoadedVideo | None, points: list[Point], frame: int
    ) -> tuple[Any, ...]:
        image = None if video is None else preview_frame(video.frames, int(frame), points)
        return points, image, points_text(points)

    def on_mode(mode: str) -> tuple[Any, ...]:
        return (
            gr.Group(visible=mode == "points"),
            gr.Group(visible=mode == "region"),
            gr.Slider(visible=mode == "grid"),
        )

    def on_track(
        video: LoadedVideo | None,
        points: list[Point],
        mode: str,
        frame: int,
        region: dict[str, Any] | None,
        grid_size: int,
        backward: bool,
        progress: gr.Progress = gr.Progress(track_tqdm=True),  # noqa: B008 (Gradio's idiom)
    ) -> tuple[Any, ...]:
        video = require(video)
        try:
            height, width = video.frames.shape[1:3]
            queries = build_queries(
                mode,
                video_shape=video.frames.shape,
                query_frame=int(frame),
                limits=limits,
                points=points,
                mask=mask_from_editor(region, height, width),
                grid_size=int(grid_size),
            )
            handlers.prune_runs(workspace, RUN_MAX_AGE_S)
            handlers.check_disk_quota(workspace, limits.max_disk_bytes)
            out = handlers.track_video(
                predictor,
                video,
                queries,
                folder=handlers.new_run_folder(workspace),
                backward=bool(backward),
                model_name=model_name,
                progress=lambda fraction, text: progress(fraction, desc=text),
            )
        except ValueError as error:
            raise user_error(error) from None
        return str(out.overlay), str(out.csv), str(out.npz), out.message

    def on_edit(
        video: LoadedVideo | None,
        region: dict[str, Any] | None,
        image: np.ndarray | None,
        frame: int,
        opacity: float,
        progress: gr.Progress = gr.Progress(track_tqdm=True),  # noqa: B008 (Gradio's idiom)
    ) -> tuple[Any, ...]:
        video = require(video)
        try:
            height, width = video.frames.shape[1:3]
            handlers.prune_runs(workspace, RUN_MAX_AGE_S)
            handlers.check_disk_quota(workspace, limits.max_disk_bytes)
            out = handlers.edit_video(
                predictor,
                video,
                mask_from_editor(region, height, width),
                image,
                int(frame),
                folder=handlers.new_run_folder(workspace),
                limits=limits,
                opacity=float(opacity),
                progress=lambda fraction, text: progress(fraction, desc=text),
            )
        except ValueError as error:
            raise user_error(error) from None
        return str(out.video), out.message

    # Gradio keeps its own copies of uploads and outputs; drop them with the run folders.
    expiry = int(RUN_MAX_AGE_S)
    with gr.Blocks(
        title="taptr demo", analytics_enabled=False, delete_cache=(expiry // 6, expiry)
    ) as demo:
        gr.Markdown(
            "# taptr: track any point\n"
            f"Model: **{model_name or 'custom'}**. "
            + (f"*Note: {predictor.notice}* " if predictor.notice else "")
            + f"Limits: {limits.max_frames} frames, "
            f"{limits.max_side} px on the longer side, {limits.max_points} points. "
            "Coordinates are (x, y) pixels with pixel centres at integers."
        )
        video_state = gr.State(None)
        points_state = gr.State([])
        with gr.Row():
            video_input = gr.Video(
                label="Video", sources=["upload"], elem_id="video-input", height=280
            )
            with gr.Column():
                sample = gr.Dropdown(list(samples), value=next(iter(samples)), label="Sample")
                sample_button = gr.Button("Load sample", elem_id="load-sample")
                video_message = gr.Markdown(elem_id="video-message")
                frame_slider = gr.Slider(
                    0, 1, value=0, step=1, label="Query frame", interactive=False
                )
        with gr.Tab("Track points"), gr.Row():
            with gr.Column():
                mode = gr.Radio(
                    [(_MODE_LABELS[m], m) for m in QUERY_MODES], value="points", label="Queries"
                )
                with gr.Group() as click_group:
                    click_image = gr.Image(
                        label="Click to add points on the query frame",
                        interactive=False,
                        format="png",
                        buttons=[],
                        elem_id="query-frame",
                    )
                    with gr.Row():
                        undo_button = gr.Button("Undo", size="sm")
                        clear_button = gr.Button("Clear", size="sm")
                    points_box = gr.Textbox(
                        label="Points (t, x, y)", lines=3, interactive=False, elem_id="points"
                    )
                with gr.Group(visible=False) as region_group:
                    track_editor = _region_editor("Paint the region to track", "track-region")
                grid_size = gr.Slider(2, 20, value=8, step=1, label="Grid size", visible=False)
                backward = gr.Checkbox(label="Also track backwards in time", value=False)
                track_button = gr.Button("Track", variant="primary", elem_id="track")
            with gr.Column():
                overlay_video = gr.Video(
                    label="Tracks", interactive=False, elem_id="overlay-video", height=360
                )
                track_message = gr.Markdown(elem_id="track-message")
                csv_file = gr.File(
                    label="tracks.csv", interactive=False, elem_id="tracks-csv", height=90
                )
                npz_file = gr.File(
                    label="tracks.npz", interactive=False, elem_id="tracks-npz", height=90
                )
        with gr.Tab("Edit video"), gr.Row():
            with gr.Column():
                edit_editor = _region_editor(
                    "Paint the region to edit on the query frame", "edit-region"
                )
                overlay_image = gr.Image(
                    label="Image to paste",
                    type="numpy",
                    image_mode="RGBA",
                    sources=["upload"],
                    elem_id="paste-image",
                )
                opacity = gr.Slider(0.0, 1.0, value=1.0, step=0.05, label="Opacity")
                edit_button = gr.Button("Edit", variant="primary", elem_id="edit")
            with gr.Column():
                edited_video = gr.Video(
                    label="Edited video", interactive=False, elem_id="edited-video", height=360
                )
                edit_message = gr.Markdown(elem_id="edit-message")

        views = [click_image, track_editor, edit_editor]
        loaded = [video_state, points_state, frame_slider, *views, points_box, video_message]
        cleared = [overlay_video, csv_file, npz_file]
        video_input.upload(on_upload, video_input, [*loaded, *cleared])
        sample_button.click(on_sample, sample, [video_input, *loaded, *cleared])
        frame_slider.change(on_frame, [video_state, frame_slider, points_state], views)
        click_image.select(
            on_click,
            [video_state, points_state, frame_slider],
            [points_state, click_image, points_box],
        )
        undo_button.click(
            lambda v, p, f: on_points_change(v, p[:-1], f),
            [video_state, points_state, frame_slider],
            [points_state, click_image, points_box],
        )
        clear_button.click(
            lambda v, p, f: on_points_change(v, [], f),
            [video_state, points_state, frame_slider],
            [points_state, click_image, points_box],
        )
        mode.change(on_mode, mode, [click_group, region_group, grid_size])
        track_button.click(
            on_track,
            [video_state, points_state, mode, frame_slider, track_editor, grid_size, backward],
            [overlay_video, csv_file, npz_file, track_message],
        )
        edit_button.click(
            on_edit,
            [video_state, edit_editor, overlay_image, frame_slider, opacity],
            [edited_video, edit_message],
        )
    return demo


def points_text(points: list[Point]) -> str:
    """One ``t, x, y`` line per clicked point, in click order."""
    return "\n".join(f"{t}, {x:g}, {y:g}" for t, x, y in points)


def _region_editor(label: str, elem_id: str) -> gr.ImageEditor:
    # PNG keeps the paint's alpha exact (the default WebP is lossy); no upload, crop or
    # resize, because the background must stay the query frame the mask refers to.
    return gr.ImageEditor(
        label=label,
        type="numpy",
        image_mode="RGBA",
        format="png",
        sources=[],
        transforms=[],
        layers=False,
        brush=_BRUSH,
        eraser=gr.Eraser(default_size=12),
        elem_id=elem_id,
    )
