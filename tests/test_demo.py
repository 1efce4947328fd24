"""The web demo's handlers, called directly: no server, no browser, no Gradio needed."""

from __future__ import annotations

import ast
import importlib.util
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import taptr
from taptr.apps.demo.handlers import edit_video, new_run_folder, prune_runs, track_video
from taptr.apps.demo.settings import Limits
from taptr.apps.demo.uploads import (
    DemoError,
    add_point,
    build_queries,
    click_to_point,
    load_video,
    mask_from_editor,
    preview_frame,
)
from taptr.cli.main import main
from taptr.io.tracks import CSV_HEADER, load_tracks_csv, load_tracks_npz
from taptr.io.video import video_info, write_video

DEMO_SOURCES = Path(__file__).resolve().parents[1] / "src" / "taptr" / "apps" / "demo"
ALLOWED_IMPORTS = (
    "taptr.api",
    "taptr.viz",
    "taptr.apps.editing",
    "taptr.data.sample_video",
    "taptr.apps.demo",
    "taptr.io",  # video and track files, temporary folders: the ground floor
)


@pytest.fixture(scope="module")
def clip_path(tmp_path_factory) -> Path:
    """An 8-frame 40×56 video with a bright square moving right by 2 px per frame."""
    frames = np.full((8, 40, 56, 3), 40, np.uint8)
    for t in range(8):
        frames[t, 12:22, 8 + 2 * t : 18 + 2 * t] = (230, 200, 40)
    return write_video(tmp_path_factory.mktemp("clip") / "square.mp4", frames, fps=8)


@pytest.fixture(scope="module")
def predictor():
    from taptr.api.predictor import Predictor

    return Predictor.from_pretrained("tiny", device="cpu")


def test_load_video_reads_within_the_limits(clip_path):
    video = load_video(clip_path, Limits(), name="mine.mp4")
    assert video.frames.shape == (8, 40, 56, 3) and video.fps == 8
    assert video.message == "mine.mp4: 8 frames of 56×40"


def test_load_video_cuts_long_videos_and_says_so(clip_path):
    video = load_video(clip_path, Limits(max_frames=5))
    assert len(video.frames) == 5
    assert "the first 5 of 8 frames" in video.message and "--max-frames" in video.message


def test_load_video_refuses_large_frames(clip_path):
    with pytest.raises(DemoError, match=r"56×40.*up to 48 pixels.*--max-side"):
        load_video(clip_path, Limits(max_side=48))


def test_load_video_names_unsupported_and_corrupt_files(tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("not a video")
    with pytest.raises(DemoError, match=r"unsupported video type '\.txt'"):
        load_video(text, Limits(), name="notes.txt")
    corrupt = tmp_path / "upload-1234" / "broken.mp4"
    corrupt.parent.mkdir()
    corrupt.write_bytes(np.random.default_rng(0).bytes(2000))
    with pytest.raises(DemoError, match=r"broken\.mp4") as error:
        load_video(corrupt, Limits(), name="broken.mp4")
    assert str(tmp_path) not in str(error.value)  # the temporary path means nothing to users


def test_click_lands_on_pixel_centres():
    # Gradio reports [column, row] rounded from the image's top-left corner, at (-0.5, -0.5).
    assert click_to_point([32, 48], 3) == (3, 31.5, 47.5)


def test_add_point_keeps_the_limit():
    points = add_point([], (0, 1.0, 2.0), Limits(max_points=1))
    assert points == [(0, 1.0, 2.0)]
    with pytest.raises(DemoError, match="at most 1 points"):
        add_point(points, (0, 3.0, 4.0), Limits(max_points=1))


def test_preview_draws_only_the_points_of_its_frame():
    frames = np.zeros((3, 32, 32, 3), np.uint8)
    shown = preview_frame(frames, 1, [(1, 10.0, 12.0), (2, 25.0, 25.0)])
    assert shown.shape == (32, 32, 3) and shown.dtype == np.uint8
    assert shown[12, 10].any() and not shown[25, 25].any()
    assert not frames.any()  # the video itself is untouched
    with pytest.raises(DemoError, match="outside"):
        preview_frame(frames, 3, [])


def test_mask_from_editor_reads_paint_layers():
    layer = np.zeros((20, 30, 4), np.uint8)
    layer[5:10, 2:8, 3] = 150
    mask = mask_from_editor({"background": None, "layers": [layer], "composite": None}, 20, 30)
    assert mask.shape == (20, 30) and mask.sum() == 30 and mask[5:10, 2:8].all()
    # a layer at twice the frame size (the editor's canvas) is scaled to the frame
    big = np.zeros((40, 60, 4), np.uint8)
    big[10:20, 4:16, 3] = 255
    assert mask_from_editor({"layers": [big]}, 20, 30)[5:10, 2:8].all()
    assert not mask_from_editor(None, 20, 30).any()


def test_build_queries_for_each_mode():
    shape, limits = (6, 40, 50, 3), Limits(max_points=20)
    points = build_queries(
        "points", video_shape=shape, query_frame=0, limits=limits, points=[(2, 5.0, 6.0)]
    )
    np.testing.assert_array_equal(points, [[2, 5, 6]])
    mask = np.zeros((40, 50), bool)
    mask[10:20, 10:30] = True
    region = build_queries(
        "region", video_shape=shape, query_frame=4, limits=limits, mask=mask, region_stride=4
    )
    assert (region[:, 0] == 4).all() and mask[
        region[:, 2].astype(int), region[:, 1].astype(int)
    ].all()
    grid = build_queries("grid", video_shape=shape, query_frame=1, limits=limits, grid_size=4)
    assert grid.shape == (16, 3) and (grid[:, 0] == 1).all()


@pytest.mark.parametrize(
    ("mode", "kwargs", "message"),
    [
        ("points", {}, "no points selected"),
        ("region", {"mask": np.zeros((40, 50), bool)}, "no region painted"),
        ("grid", {"grid_size": 5}, "5×5 grid exceeds the limit of 20"),
        ("lasso", {}, "unknown query mode"),
    ],
)
def test_build_queries_explains_what_is_missing(mode, kwargs, message):
    with pytest.raises(DemoError, match=message):
        build_queries(
            mode, video_shape=(6, 40, 50, 3), query_frame=0, limits=Limits(max_points=20), **kwargs
        )


def test_track_video_writes_overlay_csv_and_npz(clip_path, predictor, tmp_path):
    video = load_video(clip_path, Limits())
    queries = np.array([[0, 12.0, 16.0], [3, 20.5, 17.0]], np.float32)
    steps = []
    out = track_video(
        predictor,
        video,
        queries,
        folder=tmp_path,
        backward=True,
        model_name="tiny",
        progress=lambda fraction, text: steps.append(fraction),
    )
    assert steps[0] == 0.0 and steps[-1] == 1.0 and steps == sorted(steps)
    lines = out.csv.read_text().strip().splitlines()
    assert lines[0] == CSV_HEADER and len(lines) == 1 + 8 * 2
    tracks, visibility = load_tracks_csv(out.csv)
    saved = load_tracks_npz(out.npz)
    np.testing.assert_allclose(saved.tracks, tracks, atol=1e-4)
    np.testing.assert_array_equal(saved.visibility, visibility)
    np.testing.assert_array_equal(saved.queries, queries)
    assert saved.tracks[3, 1].tolist() == [20.5, 17.0]  # each query comes back on its frame
    assert saved.metadata["backward"] and saved.metadata["model"] == "tiny"
    info = video_info(out.overlay)
    assert (info.num_frames, info.height, info.width) == (8, 40, 56)
    assert out.message.startswith("tracked 2 points through 8 frames")


def test_edit_video_pastes_the_image(clip_path, predictor, tmp_path):
    video = load_video(clip_path, Limits())
    mask = np.zeros((40, 56), bool)
    mask[12:22, 8:18] = True
    image = np.zeros((8, 8, 3), np.uint8)
    image[..., 2] = 255
    out = edit_video(predictor, video, mask, image, 0, folder=tmp_path, limits=Limits(), stride=3)
    info = video_info(out.video)
    assert (info.num_frames, info.height, info.width) == (8, 40, 56)
    assert out.message.startswith("tracked 16 region points")
    with pytest.raises(DemoError, match="no image to paste"):
        edit_video(predictor, video, mask, None, 0, folder=tmp_path, limits=Limits())
    with pytest.raises(DemoError, match="no region painted"):
        edit_video(predictor, video, mask & False, image, 0, folder=tmp_path, limits=Limits())


def test_run_folders_are_fresh_and_pruned_by_age(tmp_path):
    old, new = new_run_folder(tmp_path), new_run_folder(tmp_path)
    assert old != new and old.parent == tmp_path and not any(old.iterdir())
    hour_ago = time.time() - 3600
    os.utime(old, (hour_ago, hour_ago))
    assert prune_runs(tmp_path, max_age_s=600) == 1
    assert not old.exists() and new.exists()


def test_limits_must_be_positive():
    with pytest.raises(ValueError, match=">= 1"):
        Limits(max_frames=0)


def test_demo_without_gradio_says_what_to_install(monkeypatch, capsys):
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "gradio" else real(name, *a)
    )
    assert main(["demo"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "pip install 'gradio" in err


def test_import_and_help_leave_gradio_alone():
    code = (
        "import sys, taptr, taptr.apps.demo, taptr.apps.demo.settings; "
        "from taptr.cli.main import build_parser; build_parser(); "
        "assert 'gradio' not in sys.modules, 'gradio imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_demo_imports_only_the_api_layer():
    sources = sorted(DEMO_SOURCES.glob("*.py"))
    assert len(sources) >= 5, f"demo sources not found in {DEMO_SOURCES}"
    for source in sources:
        for node in ast.walk(ast.parse(source.read_text())):
            names = (
                [alias.name for alias in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""]
                if isinstance(node, ast.ImportFrom)
                else []
            )
            for name in names:
                if name.startswith("taptr"):
                    assert name.startswith(ALLOWED_IMPORTS), f"{source.name} imports {name}"


def test_app_builds_with_every_element_the_page_needs(predictor, tmp_path):
    pytest.importorskip("gradio", reason="the demo extra is not installed")
    from taptr.apps.demo.app import build_app, gradio_samples

    app = build_app(predictor, workspace=tmp_path, model_name="tiny")
    for write in gradio_samples().values():  # served from the workspace, not site-packages
        assert write(tmp_path / "samples").parent == tmp_path / "samples"
    ids = {block.elem_id for block in app.blocks.values()}
    assert {"video-input", "query-frame", "points", "track", "overlay-video", "tracks-csv"} <= ids
    assert {"tracks-npz", "track-region", "edit-region", "paste-image", "edited-video"} <= ids
    assert sorted(p.name for p in tmp_path.iterdir()) == ["samples"]


def test_page_shows_the_fallback_notice_next_to_the_model(tmp_path):
    pytest.importorskip("gradio", reason="the demo extra is not installed")
    from taptr.apps.demo.app import build_app

    predictor = taptr.Predictor.from_pretrained(None, device="cpu")  # offline: falls back
    assert predictor.source == "taptr-small-synthetic" and predictor.notice
    app = build_app(predictor, workspace=tmp_path, model_name=predictor.source)
    texts = [getattr(block, "value", "") for block in app.blocks.values()]
    header = next(text for text in texts if isinstance(text, str) and "Model:" in text)
    assert "taptr-small-synthetic" in header and predictor.notice in header
    assert "trained on synthetic videos:" in header


def test_disk_quota_refuses_and_deletes_the_upload(tmp_path, capsys):
    from taptr.apps.demo.handlers import check_disk_quota

    (tmp_path / "uploads").mkdir()
    upload = tmp_path / "uploads" / "big.mp4"
    upload.write_bytes(b"x" * 2000)
    check_disk_quota(tmp_path, 4000, upload=str(upload))  # within the quota: kept
    assert upload.exists()
    with pytest.raises(DemoError, match="disk space is full"):
        check_disk_quota(tmp_path, 1000, upload=str(upload))
    assert not upload.exists()
    assert main(["demo", "--checkpoint", "tiny", "--max-disk-gb", "0"]) == 2
    assert "--max-disk-gb must be positive" in capsys.readouterr().err


def test_a_killed_servers_workspace_is_removed_by_the_next(tmp_path, monkeypatch):
    import tempfile

    from taptr.apps.demo.launch import WORKSPACE_PREFIX, private_workspace

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    dead = tmp_path / f"{WORKSPACE_PREFIX}999999999-abcd1234.tmp"  # no such process
    (dead / "uploads").mkdir(parents=True)
    alive = tmp_path / f"{WORKSPACE_PREFIX}{os.getpid()}-other123.tmp"
    alive.mkdir()
    with private_workspace() as workspace:
        assert workspace.name.startswith(f"{WORKSPACE_PREFIX}{os.getpid()}-")
        assert not dead.exists() and alive.exists()
    assert not workspace.exists()
