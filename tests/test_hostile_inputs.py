"""Regression tests for hostile and careless inputs, second round (issue 29).

One test (or a parametrised set) per defect of the issue, each failing on the code before
the fix: decoders that skipped the guards, checkpoints whose sizes lied, special files,
"this is a bug" exits on user input, evaluation succeeding on nothing, and noise on
stderr. Files are built by `tests.bombs` in a few kilobytes; nothing here allocates what a
file declares, and every read of a special file runs under a timeout.
"""

from __future__ import annotations

import argparse
import os
import pickle
import socket
import subprocess
import sys
import threading
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from taptr.cli.main import main
from taptr.io import limits
from taptr.io.video import iter_frames, read_video, video_info, write_video
from taptr.weights.checkpoint import CheckpointError, load_checkpoint
from tests import bombs


def _error_line(capsys, command: str) -> str:
    """The one ``taptr COMMAND: error:`` line of stderr (other lines may precede it)."""
    err = capsys.readouterr().err
    assert "Traceback" not in err and "this is a bug" not in err, err
    lines = [line for line in err.splitlines() if line.startswith(f"taptr {command}: error:")]
    assert len(lines) == 1, err
    return lines[0]


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (12, 48, 64, 3), dtype=np.uint8)
    return write_video(tmp_path_factory.mktemp("clip") / "clip.mp4", frames, fps=10)


def _no_hang(run, *args, fifos=(), timeout: float = 20.0):
    """``run(*args)`` in a thread; fails the test if it blocks (and unblocks the FIFOs)."""
    outcome: dict[str, object] = {}

    def target() -> None:
        try:
            outcome["value"] = run(*args)
        except BaseException as error:
            outcome["error"] = error

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(timeout)
    if thread.is_alive():
        for fifo in fifos:  # a writer lets a blocked open() return, then EOF
            os.close(os.open(fifo, os.O_RDWR | os.O_NONBLOCK))
        thread.join(10)
        pytest.fail(f"{run.__name__} blocked on a special file")
    if "error" in outcome:
        raise outcome["error"]  # type: ignore[misc]
    return outcome.get("value")


# -- decoders that skipped the guards ------------------------------------------------------


def test_gif_canvas_bomb_is_refused_on_the_streaming_path(tmp_path, monkeypatch):
    path = tmp_path / "bomb.gif"
    path.write_bytes(bombs.gif_canvas(4000, 4000))
    assert path.stat().st_size < 100
    monkeypatch.setenv("TAPTR_MAX_IMAGE_PIXELS", "1000000")
    import taptr.io.video as video_io

    monkeypatch.setattr(video_io, "rgb", lambda frame: pytest.fail("decoded"))
    for reader in (video_info, lambda p: next(iter_frames(p)), read_video):
        with pytest.raises(limits.LimitError, match=r"4000x4000 frames.*TAPTR_MAX_IMAGE_PIXELS"):
            reader(path)


def test_gif_canvas_bomb_through_taptr_track_exits_2_before_the_model(tmp_path, capsys):
    path = tmp_path / "bomb.gif"
    path.write_bytes(bombs.gif_canvas())
    assert main(["track", str(path), "--grid", "2", "--out", str(tmp_path / "o")]) == 2
    assert "16000x16000 frames exceeds" in _error_line(capsys, "track")


def test_mask_declaring_25000x25000_16_bit_rgba_is_refused_before_decoding(tmp_path, monkeypatch):
    import cv2

    from taptr.api.regions import read_mask

    path = tmp_path / "mask.png"
    path.write_bytes(bombs.png_bomb(25_000, 25_000, depth=16, colour=6))
    monkeypatch.setattr(cv2, "imread", lambda *a: pytest.fail("OpenCV decoded it"))
    with pytest.raises(limits.LimitError) as error:
        read_mask(path, name="--mask")
    assert "25000x25000" in str(error.value) and "TAPTR_MAX_IMAGE_PIXELS" in str(error.value)


def test_overlay_bomb_is_refused_before_decoding(tmp_path, monkeypatch):
    import cv2

    from taptr.cli.edit import _read_overlay

    path = tmp_path / "overlay.png"
    path.write_bytes(bombs.png_bomb(25_000, 25_000, depth=16, colour=6))
    monkeypatch.setattr(cv2, "imread", lambda *a: pytest.fail("OpenCV decoded it"))
    with pytest.raises(limits.LimitError, match="--overlay"):
        _read_overlay(str(path))


def test_image_that_is_not_png_under_a_png_name_is_refused_not_decoded_by_content(tmp_path):
    from taptr.data.check import check_kubric_folder
    from taptr.data.kubric import read_sequence, write_sequence
    from taptr.types import TrackingSample

    folder = tmp_path / "frames"
    folder.mkdir()
    (folder / "0.png").write_bytes(bombs.hdr_image(16, 16))
    with pytest.raises(ValueError, match=r"0\.png: not a readable image"):
        read_video(folder)
    sample = TrackingSample(
        np.zeros((2, 16, 16, 3), np.uint8), np.ones((2, 1, 2), np.float32), np.ones((2, 1), bool)
    )
    write_sequence(tmp_path / "kubric" / "0000", sample)
    (tmp_path / "kubric" / "0000" / "frames" / "001.png").write_bytes(bombs.hdr_image(16, 16))
    with pytest.raises(ValueError, match=r"001\.png: not a readable image"):
        read_sequence(tmp_path / "kubric" / "0000")
    report = check_kubric_folder(tmp_path / "kubric")
    assert len(report.errors) == 1 and "not a readable image" in report.errors[0].message


def test_demo_upload_to_paste_is_read_header_first(tmp_path):
    import inspect

    import taptr.apps.demo.app as app
    from taptr.apps.demo.uploads import DemoError, read_paste_image

    bomb = tmp_path / "upload.png"
    bomb.write_bytes(bombs.png_bomb(25_000, 25_000, depth=16, colour=6))
    with pytest.raises(DemoError, match=r"the image to paste.*TAPTR_MAX_IMAGE_PIXELS"):
        read_paste_image(bomb)
    (tmp_path / "hdr.png").write_bytes(bombs.hdr_image(8, 8))
    with pytest.raises(DemoError, match="not a readable image"):
        read_paste_image(tmp_path / "hdr.png")
    grey = tmp_path / "grey.png"
    grey.write_bytes(bombs.png_bytes(6, 5, 200))
    assert read_paste_image(grey).shape == (6, 5, 3)
    # the page hands over the file's path, so Gradio only opens the header
    assert 'type="filepath"' in inspect.getsource(app._edit_tab)


@pytest.mark.parametrize(
    ("variable", "value", "message"),
    [
        ("TAPTR_MAX_IMAGE_PIXELS", "100", "TAPTR_MAX_IMAGE_PIXELS"),
        ("TAPTR_MAX_VIDEO_BYTES", "1K", "TAPTR_MAX_VIDEO_BYTES"),
        ("TAPTR_MAX_VIDEO_BYTES", "1.5G", "TAPTR_MAX_VIDEO_BYTES='1.5G' is not a valid limit"),
    ],
)
def test_limits_apply_to_taptr_track(clip, tmp_path, capsys, monkeypatch, variable, value, message):
    import taptr.api.streaming as streaming

    monkeypatch.setattr(streaming, "track_frames", lambda *a, **k: pytest.fail("tracked"))
    monkeypatch.setenv(variable, value)
    assert main(["track", str(clip), "--grid", "2", "--out", str(tmp_path / "o")]) == 2
    assert message in _error_line(capsys, "track")


def test_unparsable_limit_names_the_variable_and_its_syntax(monkeypatch):
    monkeypatch.setenv("TAPTR_MAX_VIDEO_BYTES", "1.5G")
    with pytest.raises(ValueError) as error:
        limits.limit("video_bytes")
    assert "TAPTR_MAX_VIDEO_BYTES='1.5G'" in str(error.value) and "K, M, G or T" in str(error.value)
    for bad in ("-1", "0", "lots", "12X", "1" * 40, "１２"):
        monkeypatch.setenv("TAPTR_MAX_POINTS", bad)
        with pytest.raises(ValueError, match="TAPTR_MAX_POINTS"):
            limits.check_environment()
    monkeypatch.setenv("TAPTR_MAX_POINTS", "20")
    monkeypatch.setenv("TAPTR_MAX_VIDEO_BYTES", "16G")
    assert limits.limit("video_bytes") == 16 * 1024**3 and limits.limit("points") == 20


# -- checkpoints whose sizes lied ----------------------------------------------------------


def test_deflated_record_is_bounded_by_what_it_inflates_to(tmp_path):
    path = bombs.deflated_checkpoint(tmp_path / "deflated.pth", 64 * 1024**2)
    assert path.stat().st_size < 200_000
    with pytest.raises(CheckpointError) as error:
        load_checkpoint(path)
    message = str(error.value)
    assert "\n" not in message and "inflate to more than" in message and str(path) in message


def test_zero_stride_view_is_refused_by_its_logical_size(tmp_path, monkeypatch):
    path = bombs.view_checkpoint(tmp_path / "view.pth", 50_000_000)  # 200 MB shown, 4 B held
    monkeypatch.setenv("TAPTR_MAX_CHECKPOINT_BYTES", "64M")
    assert path.stat().st_size < 2_000_000
    with pytest.raises(CheckpointError) as error:
        load_checkpoint(path)
    assert "tensor views of 200,9" in str(error.value) and "\n" not in str(error.value)


def test_finiteness_check_never_materialises_more_than_a_storage(tmp_path, monkeypatch):
    from taptr import build_model
    from taptr.weights.checkpoint import checkpoint_dict

    data = checkpoint_dict(build_model("tiny"))
    key = next(k for k, v in data["model"].items() if v.dim() == 4)
    data["model"][key] = torch.ones(1).expand(data["model"][key].shape)  # stride 0
    data["model"]["encoder.level_embed"] = torch.ones(1).expand(100_000)  # wrong shape
    torch.save(data, tmp_path / "views.pth")
    seen: list[tuple[int, int]] = []
    real = torch.isfinite
    monkeypatch.setattr(
        torch,
        "isfinite",
        lambda t: (
            seen.append((t.numel(), t.untyped_storage().nbytes() // t.element_size())) or real(t)
        ),
    )
    with pytest.raises(CheckpointError, match="wrong shape"):
        load_checkpoint(tmp_path / "views.pth")
    assert seen and all(numel <= storage for numel, storage in seen), seen


def test_config_nested_100000_deep_is_a_one_line_checkpoint_error(tmp_path):
    path = bombs.deep_config_checkpoint(tmp_path / "deep.pth")
    with pytest.raises(CheckpointError) as error:
        load_checkpoint(path)
    assert "nested more than" in str(error.value) and "\n" not in str(error.value)


def test_config_value_nested_a_few_levels_or_too_long_is_named(tmp_path):
    from taptr import build_model
    from taptr.weights.checkpoint import checkpoint_dict

    data = checkpoint_dict(build_model("tiny"))
    for value, message in (([[[[1]]]], "nested more than 3"), (list(range(10_000)), "values")):
        torch.save(dict(data, config=dict(data["config"], d_model=value)), tmp_path / "c.pth")
        with pytest.raises(CheckpointError, match=message):
            load_checkpoint(tmp_path / "c.pth")


def test_input_size_4096_is_refused_by_the_estimate_before_tracking(monkeypatch):
    from taptr import build_model
    from taptr.api.predictor import Predictor
    from taptr.memory_estimate import MemoryEstimateError
    from taptr.runtime.runner import Runner

    monkeypatch.setattr(Runner, "track", lambda *a, **k: pytest.fail("tracked"))
    monkeypatch.setenv("TAPTR_MAX_MEMORY", "2G")
    with pytest.raises(MemoryEstimateError) as error:  # when built: before any timing
        Predictor(build_model("small").eval(), input_size=(4096, 4096), device="cpu")
    assert "input_size" in str(error.value) and "TAPTR_MAX_MEMORY" in str(error.value)


def test_input_size_4096_on_the_command_line_names_the_knobs(clip, tmp_path, capsys, monkeypatch):
    import taptr.api.streaming as streaming

    monkeypatch.setattr(streaming, "track_frames", lambda *a, **k: pytest.fail("tracked"))
    monkeypatch.setenv("TAPTR_MAX_MEMORY", "2G")
    argv = ["track", str(clip), "--grid", "2", "--input-size", "4096", "4096"]
    assert main([*argv, "--out", str(tmp_path / "o")]) == 2
    line = _error_line(capsys, "track")
    assert "at 4096x4096 at all" in line and "--input-size" in line


def test_allocator_failure_is_one_line_naming_the_knobs(monkeypatch, capsys):
    def hungry(_args: argparse.Namespace) -> int:
        raise RuntimeError(
            "[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate "
            "memory: you tried to allocate 6000000000 bytes. Error code 12"
        )

    import taptr.cli.sample_video as command

    monkeypatch.setattr(command, "run", hungry)
    assert main(["sample-video", "x.mp4"]) == 1
    line = capsys.readouterr().err.strip()
    assert "\n" not in line and "bug" not in line
    assert "out of memory" in line and "--input-size" in line and "6000000000 bytes" in line


# -- special files -------------------------------------------------------------------------


def test_fifo_named_like_a_video_is_refused_without_hanging(tmp_path, capsys):
    fifo = tmp_path / "clip.mp4"
    os.mkfifo(fifo)
    argv = ["track", str(fifo), "--grid", "2", "--out", str(tmp_path / "o")]
    assert _no_hang(main, argv, fifos=[fifo]) == 2
    assert "is a FIFO (named pipe), not a regular file" in _error_line(capsys, "track")


def _special(tmp_path: Path, kind: str, name: str) -> Path:
    path = tmp_path / name
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "folder":
        path.mkdir()
    elif kind == "socket":
        server = socket.socket(socket.AF_UNIX)
        server.bind(str(path))
        _SOCKETS.append(server)
    elif kind == "device":
        path.symlink_to("/dev/zero")
    return path


_SOCKETS: list[socket.socket] = []
_WORDS = {"fifo": "FIFO", "folder": "folder", "socket": "socket", "device": "character device"}


def _read_checkpoint(path: Path) -> object:
    return load_checkpoint(path)


def _read_points(path: Path) -> object:
    from taptr.cli.common.points import read_points_file

    return read_points_file(str(path))


def _read_mask(path: Path) -> object:
    from taptr.api.regions import read_mask

    return read_mask(path, name="--mask")


def _read_overlay(path: Path) -> object:
    from taptr.cli.edit import _read_overlay as read_overlay

    return read_overlay(str(path))


def _read_dataset(path: Path) -> object:
    from taptr.data.tapvid import iter_tapvid

    return list(iter_tapvid("davis", path))


_READERS = {
    "checkpoint": (_read_checkpoint, "model.pth"),
    "points_file": (_read_points, "points.txt"),
    "mask": (_read_mask, "mask.png"),
    "overlay": (_read_overlay, "overlay.png"),
    "dataset": (_read_dataset, "tapvid_davis.pkl"),
}
_CASES = [
    (role, kind)
    for role in _READERS
    for kind in ("fifo", "folder", "socket", "device")
    if (role, kind) != ("dataset", "folder")  # a folder is a dataset root: looked inside
]


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs POSIX special files")
@pytest.mark.parametrize(("role", "kind"), _CASES)
def test_special_files_are_refused_saying_what_they_are(tmp_path, role, kind):
    reader, name = _READERS[role]
    path = _special(tmp_path, kind, name)
    try:
        with pytest.raises(ValueError) as error:
            _no_hang(reader, path, fifos=[path] if kind == "fifo" else [])
    finally:
        while _SOCKETS:
            _SOCKETS.pop().close()
    assert _WORDS[kind] in str(error.value) and name in str(error.value), error.value


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs POSIX special files")
@pytest.mark.parametrize("where", ["frames/001.png", "0000.npy"])
def test_fifo_in_a_kubric_folder_does_not_hang_check_data_or_eval(tmp_path, capsys, where):
    from taptr.data.kubric import write_sequence
    from taptr.types import TrackingSample

    sample = TrackingSample(
        np.zeros((8, 16, 16, 3), np.uint8), np.ones((8, 2, 2), np.float32), np.ones((8, 2), bool)
    )
    write_sequence(tmp_path / "kubric" / "0000", sample)
    fifo = tmp_path / "kubric" / "0000" / where
    fifo.unlink()
    os.mkfifo(fifo)
    assert _no_hang(main, ["check-data", str(tmp_path / "kubric")], fifos=[fifo]) == 1
    assert "FIFO" in capsys.readouterr().err
    argv = ["eval", "--dataset", "kubric", "--root", str(tmp_path / "kubric")]
    argv += ["--tracker", "static", "--out", str(tmp_path / "out")]
    assert _no_hang(main, argv, fifos=[fifo]) == 2
    assert "is a FIFO (named pipe)" in _error_line(capsys, "eval")


# -- other "this is a bug" exits on user input ---------------------------------------------


@pytest.mark.parametrize("where", ["out", "video"])
def test_over_long_names_are_user_errors(clip, tmp_path, capsys, where):
    long = "x" * 300
    video = str(tmp_path / f"{long}.mp4") if where == "video" else str(clip)
    out = str(tmp_path / long / "o") if where == "out" else str(tmp_path / "o")
    assert main(["track", video, "--grid", "2", "--out", out]) == 2
    assert "too long" in _error_line(capsys, "track")


def test_video_whose_frame_size_changes_mid_stream_names_the_file_and_frame(tmp_path):
    path = bombs.spliced_video(tmp_path / "spliced.mkv")
    with pytest.raises(ValueError) as error:
        read_video(path)
    assert str(path) in str(error.value) and "frame 3 is 64x48" in str(error.value)
    with pytest.raises(ValueError, match=r"spliced\.mkv: frame 3"):
        list(iter_frames(path))


# -- evaluation that succeeded on nothing --------------------------------------------------


def _eval(capsys, items: dict, tmp_path: Path) -> str:
    path = tmp_path / "tapvid_davis.pkl"
    path.write_bytes(pickle.dumps(items))
    argv = ["eval", "--dataset", "davis", "--root", str(path), "--tracker", "static"]
    assert main([*argv, "--out", str(tmp_path / "out")]) == 2
    assert not (tmp_path / "out" / "results.json").exists()
    return _error_line(capsys, "eval")


def test_eval_on_a_dataset_without_videos_exits_2(tmp_path, capsys):
    line = _eval(capsys, {}, tmp_path)
    assert "davis" in line and "no videos to evaluate" in line


def test_eval_where_every_point_is_occluded_exits_2_naming_the_videos(tmp_path, capsys):
    item = bombs.davis_item(frames=6, size=16)
    item["occluded"][:] = True
    line = _eval(capsys, {"bear": item, "cows": item}, tmp_path)
    assert "davis" in line and "'bear'" in line and "no evaluable point" in line


def test_eval_with_ground_truth_far_outside_the_frame_exits_2(tmp_path, capsys):
    item = bombs.davis_item(frames=6, size=16)
    item["occluded"][:] = False
    item["points"][1, 2] = (40.0, 0.5)  # raster units: 40 frame widths to the right
    line = _eval(capsys, {"bear": item}, tmp_path)
    assert "davis" in line and "'bear'" in line and "outside its 16x16 frame" in line


# -- noise ---------------------------------------------------------------------------------


WARNS = """
import sys, warnings
import taptr.cli.sample_video as command

def run(_args):
    warnings.warn("clip.mp4: decoded 1 frames where the container declares 12", stacklevel=1)
    return 0

command.run = run
from taptr.cli.main import main
sys.exit(main(["sample-video", "x.mp4"]))
"""


def test_warnings_are_one_taptr_line():
    # a process of its own: pytest records warnings instead of printing them
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    done = subprocess.run([sys.executable, "-c", WARNS], capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr
    assert done.stderr == (
        "taptr: warning: clip.mp4: decoded 1 frames where the container declares 12\n"
    )


def test_opencv_log_lines_do_not_reach_stderr(tmp_path, capfd, monkeypatch):
    import cv2

    def reads(_args: argparse.Namespace) -> int:
        cv2.imread(str(tmp_path / "missing.png"))  # OpenCV logs "can't open/read file"
        return 0

    import taptr.cli.sample_video as command

    monkeypatch.setattr(command, "run", reads)
    previous = cv2.utils.logging.getLogLevel()
    try:
        assert main(["sample-video", "x.mp4"]) == 0
    finally:
        cv2.utils.logging.setLogLevel(previous)
    assert "WARN" not in capfd.readouterr().err


def test_a_folder_named_like_a_frame_is_named_not_logged_by_opencv(tmp_path, capfd):
    from taptr.data.kubric import write_sequence
    from taptr.types import TrackingSample

    sample = TrackingSample(
        np.zeros((8, 16, 16, 3), np.uint8), np.ones((8, 2, 2), np.float32), np.ones((8, 2), bool)
    )
    write_sequence(tmp_path / "0000", sample)
    (tmp_path / "0000" / "frames" / "003.png").unlink()
    (tmp_path / "0000" / "frames" / "003.png").mkdir()
    assert main(["check-data", str(tmp_path)]) == 1
    err = capfd.readouterr().err
    assert "[ WARN" not in err and "003.png is a folder" in err


def test_points_beyond_float32_get_our_message(clip, tmp_path, capsys):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's RuntimeWarning would fail here
        argv = ["track", str(clip), "--points", "0,1e39,10", "--out", str(tmp_path / "o")]
        assert main(argv) == 2
    assert "beyond float32's range" in _error_line(capsys, "track")


@pytest.mark.parametrize(
    ("flag", "value"),
    [("--max-frames", str(10**20)), ("--grid", str(10**20)), ("--context-points", str(10**20))],
)
def test_numeric_options_are_checked_with_our_message(clip, tmp_path, capsys, flag, value):
    argv = ["track", str(clip), "--out", str(tmp_path / "o")]
    argv += ["--points", "0,1,1"] if flag != "--grid" else []
    values = [value, value] if flag == "--input-size" else [value]
    assert main([*argv, flag, *values]) == 2
    line = _error_line(capsys, "track")
    assert flag in line and "islice" not in line


def test_float_video_array_in_a_tapvid_pickle_is_named_as_such(tmp_path):
    from taptr.data.tapvid import iter_tapvid

    item = bombs.davis_item()
    item["video"] = item["video"].astype(np.float32)
    path = tmp_path / "tapvid_davis.pkl"
    path.write_bytes(pickle.dumps({"bear": item}))
    with pytest.raises(ValueError) as error:
        next(iter_tapvid("davis", path)).load()
    assert "'video' is a float32 array of shape (4, 8, 8, 3)" in str(error.value)


def test_huge_grid_prints_the_estimate_before_tracking(clip, tmp_path, capsys, monkeypatch):
    import taptr.api.streaming as streaming

    def stop(*_args: object, **_kwargs: object) -> None:
        raise ValueError("stopped before tracking")

    monkeypatch.setattr(streaming, "track_frames", stop)
    monkeypatch.setenv("TAPTR_MAX_MEMORY", "1T")
    argv = ["track", str(clip), "--grid", "316", "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    estimate = next(line for line in err.splitlines() if "needs about" in line)
    assert "99,856 points" in estimate and "GiB" in estimate
    assert err.index("needs about") < err.index("stopped before tracking")
    monkeypatch.setenv("TAPTR_MAX_MEMORY", "1G")
    assert main(argv) == 2
    assert "track fewer points (now 99,856)" in _error_line(capsys, "track")
