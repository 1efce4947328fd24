"""The Gradio page of ``taptr demo``: components wired to the plain handlers.

The page has a video source (an upload or a bundled sample) and a query-frame slider shared
by two tabs:

- **Track points**: click points on the query frame (undo, clear), paint a region, or use a
  grid; optionally track backwards; run with a progress bar; watch the overlay video and
  download ``tracks.csv`` and ``tracks.npz``;
- **Edit video**: paint a region on the query frame, upload an image, get the video with
  the image stuck to the region.

Everything that is not layout lives in `taptr.apps.demo.callbacks` (the events' functions),
`taptr.apps.demo.uploads` and `taptr.apps.demo.handlers`. Per-user state (the decoded video,
the clicked points) is held in `gr.State`, so users never see each other's data.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import gradio as gr

from taptr.api.predictor import Predictor
from taptr.apps.demo.callbacks import Callbacks
from taptr.apps.demo.settings import RUN_MAX_AGE_S, Limits
from taptr.apps.demo.uploads import QUERY_MODES, SAMPLES

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
    callbacks = Callbacks(predictor, workspace, limits, model_name, samples, sample_dir)
    # Gradio keeps its own copies of uploads and outputs; drop them with the run folders.
    expiry = int(RUN_MAX_AGE_S)
    with gr.Blocks(
        title="taptr demo", analytics_enabled=False, delete_cache=(expiry // 6, expiry)
    ) as demo:
        _header(predictor, limits, model_name)
        states = _States(video=gr.State(None), points=gr.State([]))
        source = _video_section(samples)
        with gr.Tab("Track points"), gr.Row():
            track = _track_tab()
        with gr.Tab("Edit video"), gr.Row():
            edit = _edit_tab()
        _wire_events(callbacks, states, source, track, edit)
    return demo


@dataclass(frozen=True)
class _States:
    """Per-user state: the decoded video and the clicked points."""

    video: gr.State
    points: gr.State


@dataclass(frozen=True)
class _VideoSection:
    """The video source above the tabs, shared by both."""

    video_input: gr.Video
    sample: gr.Dropdown
    sample_button: gr.Button
    video_message: gr.Markdown
    frame_slider: gr.Slider


@dataclass(frozen=True)
class _ClickGroup:
    """The query frame to click points on, with undo, clear and the list of points."""

    group: gr.Group
    image: gr.Image
    undo_button: gr.Button
    clear_button: gr.Button
    points_box: gr.Textbox


@dataclass(frozen=True)
class _TrackTab:
    """The "Track points" tab: the queries on the left, the results on the right."""

    mode: gr.Radio
    click: _ClickGroup
    region_group: gr.Group
    editor: gr.ImageEditor
    grid_size: gr.Slider
    backward: gr.Checkbox
    button: gr.Button
    overlay_video: gr.Video
    message: gr.Markdown
    csv_file: gr.File
    npz_file: gr.File


@dataclass(frozen=True)
class _EditTab:
    """The "Edit video" tab: region, image and opacity on the left, the result on the right."""

    editor: gr.ImageEditor
    image: gr.Image
    opacity: gr.Slider
    button: gr.Button
    edited_video: gr.Video
    message: gr.Markdown


def _header(predictor: Predictor, limits: Limits, model_name: str) -> None:
    """The title line: the model, its notice if any, the limits and the coordinate convention."""
    gr.Markdown(
        "# taptr: track any point\n"
        f"Model: **{model_name or 'custom'}**. "
        + (f"*Note: {predictor.notice}* " if predictor.notice else "")
        + f"Limits: {limits.max_frames} frames, "
        f"{limits.max_side} px on the longer side, {limits.max_points} points. "
        "Coordinates are (x, y) pixels with pixel centres at integers."
    )


def _video_section(samples: Mapping[str, Callable[[Path], Path]]) -> _VideoSection:
    """The row above the tabs: video upload, sample picker, load message, query-frame slider."""
    with gr.Row():
        video_input = gr.Video(label="Video", sources=["upload"], elem_id="video-input", height=280)
        with gr.Column():
            sample = gr.Dropdown(list(samples), value=next(iter(samples)), label="Sample")
            sample_button = gr.Button("Load sample", elem_id="load-sample")
            video_message = gr.Markdown(elem_id="video-message")
            frame_slider = gr.Slider(0, 1, value=0, step=1, label="Query frame", interactive=False)
    return _VideoSection(video_input, sample, sample_button, video_message, frame_slider)


def _click_group() -> _ClickGroup:
    """The "Clicked points" queries: the query frame to click on, undo, clear, the points."""
    with gr.Group() as group:
        image = gr.Image(
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
    return _ClickGroup(group, image, undo_button, clear_button, points_box)


def _track_tab() -> _TrackTab:
    """The "Track points" tab's content: query modes and options, then tracks and downloads."""
    with gr.Column():
        mode = gr.Radio(
            [(_MODE_LABELS[m], m) for m in QUERY_MODES], value="points", label="Queries"
        )
        click = _click_group()
        with gr.Group(visible=False) as region_group:
            editor = _region_editor("Paint the region to track", "track-region")
        grid_size = gr.Slider(2, 20, value=8, step=1, label="Grid size", visible=False)
        backward = gr.Checkbox(label="Also track backwards in time", value=False)
        button = gr.Button("Track", variant="primary", elem_id="track")
    with gr.Column():
        overlay_video = gr.Video(
            label="Tracks", interactive=False, elem_id="overlay-video", height=360
        )
        message = gr.Markdown(elem_id="track-message")
        csv_file = gr.File(label="tracks.csv", interactive=False, elem_id="tracks-csv", height=90)
        npz_file = gr.File(label="tracks.npz", interactive=False, elem_id="tracks-npz", height=90)
    return _TrackTab(
        mode,
        click,
        region_group,
        editor,
        grid_size,
        backward,
        button,
        overlay_video,
        message,
        csv_file,
        npz_file,
    )


def _edit_tab() -> _EditTab:
    """The "Edit video" tab's content: region, image to paste and opacity, then the result."""
    with gr.Column():
        editor = _region_editor("Paint the region to edit on the query frame", "edit-region")
        image = gr.Image(
            label="Image to paste",
            # a path, not pixels: Gradio only opens the header, and taptr decodes the file
            # after checking it (taptr.apps.demo.uploads.read_paste_image)
            type="filepath",
            image_mode=None,
            sources=["upload"],
            elem_id="paste-image",
        )
        opacity = gr.Slider(0.0, 1.0, value=1.0, step=0.05, label="Opacity")
        button = gr.Button("Edit", variant="primary", elem_id="edit")
    with gr.Column():
        edited_video = gr.Video(
            label="Edited video", interactive=False, elem_id="edited-video", height=360
        )
        message = gr.Markdown(elem_id="edit-message")
    return _EditTab(editor, image, opacity, button, edited_video, message)


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


def _wire_events(
    callbacks: Callbacks,
    states: _States,
    source: _VideoSection,
    track: _TrackTab,
    edit: _EditTab,
) -> None:
    """Connects the page's events to the callbacks, in the order Gradio registers them."""
    views = [track.click.image, track.editor, edit.editor]
    loaded = [states.video, states.points, source.frame_slider, *views]
    loaded += [track.click.points_box, source.video_message]
    cleared = [track.overlay_video, track.csv_file, track.npz_file]
    source.video_input.upload(callbacks.on_upload, source.video_input, [*loaded, *cleared])
    source.sample_button.click(
        callbacks.on_sample, source.sample, [source.video_input, *loaded, *cleared]
    )
    source.frame_slider.change(
        callbacks.on_frame, [states.video, source.frame_slider, states.points], views
    )
    # Clicking, undo and clear all read and rewrite the same three things.
    points_in = [states.video, states.points, source.frame_slider]
    points_out = [states.points, track.click.image, track.click.points_box]
    track.click.image.select(callbacks.on_click, points_in, points_out)
    track.click.undo_button.click(
        lambda v, p, f: callbacks.on_points_change(v, p[:-1], f), points_in, points_out
    )
    track.click.clear_button.click(
        lambda v, p, f: callbacks.on_points_change(v, [], f), points_in, points_out
    )
    track.mode.change(
        callbacks.on_mode, track.mode, [track.click.group, track.region_group, track.grid_size]
    )
    track.button.click(
        callbacks.on_track,
        [states.video, states.points, track.mode, source.frame_slider, track.editor]
        + [track.grid_size, track.backward],
        [track.overlay_video, track.csv_file, track.npz_file, track.message],
    )
    edit.button.click(
        callbacks.on_edit,
        [states.video, edit.editor, edit.image, source.frame_slider, edit.opacity],
        [edit.edited_video, edit.message],
    )
