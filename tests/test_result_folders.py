"""Result folders are replaced as a set, and no temporary file outlives its run.

Regression tests for issue 15, item 4: an interrupted ``taptr track`` into a folder with an
earlier run leaves the earlier results (never new tracks beside an old overlay); SIGINT and
SIGTERM remove temporaries; temporaries of a SIGKILLed process are removed by the next write.
"""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import taptr.io.video as video_io
from taptr.cli.main import main
from taptr.io.atomic import (
    LEGACY_STALE_SECONDS,
    atomic_path,
    deferred_signals,
    remove_stale_temporaries,
    result_folder,
)
from taptr.io.video import write_video


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """A 6-frame 48×64 video with a moving square."""
    frames = np.full((6, 48, 64, 3), 40, np.uint8)
    for t in range(6):
        frames[t, 16:28, 10 + 2 * t : 22 + 2 * t] = (230, 200, 40)
    return write_video(tmp_path_factory.mktemp("clip") / "clip.mp4", frames, fps=10)


def _track(clip, out, *extra: str) -> int:
    return main(["track", str(clip), *extra, "--checkpoint", "tiny", "--out", str(out)])


def _digest(folder) -> dict[str, str]:
    return {
        entry.name: hashlib.sha256(entry.read_bytes()).hexdigest()
        for entry in sorted(folder.iterdir())
    }


def _hidden(folder) -> list[str]:
    return [entry.name for entry in folder.iterdir() if entry.name.startswith(".")]


@pytest.fixture
def ctrl_c_raises(monkeypatch):
    """SIGINT raises KeyboardInterrupt, as in a terminal, even when the suite was started in
    the background, where the shell makes SIGINT ignored."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def _dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


@pytest.mark.parametrize(
    ("how", "status"),
    [("exception", 130), ("sigint", 130), ("sigterm", 143)],
    ids=["keyboard-interrupt", "sigint", "sigterm"],
)
def test_interrupted_track_keeps_the_earlier_results(
    clip, tmp_path, monkeypatch, how, status, ctrl_c_raises
):
    out = tmp_path / "out"
    assert _track(clip, out, "--grid", "2", "--trajectories") == 0
    before = _digest(out)
    real = video_io.write_video

    def interrupted(*args, **kwargs):
        real(*args, **kwargs)  # tracks.npz, tracks.csv and overlay.mp4 are all written ...
        if how == "exception":
            raise KeyboardInterrupt
        os.kill(os.getpid(), signal.SIGINT if how == "sigint" else signal.SIGTERM)
        time.sleep(1)  # ... and the signal arrives before the set is swapped in

    monkeypatch.setattr(video_io, "write_video", interrupted)
    assert _track(clip, out, "--grid", "3") == status
    assert _digest(out) == before
    assert not _hidden(tmp_path) and not _hidden(out)


def test_a_new_run_replaces_the_whole_set_and_keeps_other_files(clip, tmp_path):
    out = tmp_path / "out"
    assert _track(clip, out, "--grid", "2", "--trajectories") == 0
    (out / "notes.txt").write_text("mine")
    assert _track(clip, out, "--grid", "3") == 0
    names = sorted(entry.name for entry in out.iterdir())
    assert names == ["notes.txt", "overlay.mp4", "settings.json", "tracks.csv", "tracks.npz"]
    assert not _hidden(tmp_path)


def test_result_files_have_ordinary_permissions(clip, tmp_path):
    out = tmp_path / "out"
    assert _track(clip, out, "--grid", "2") == 0
    umask = os.umask(0)
    os.umask(umask)
    for entry in out.iterdir():
        assert entry.stat().st_mode & 0o777 == 0o666 & ~umask, entry
    assert out.stat().st_mode & 0o777 == 0o777 & ~umask


def test_result_folder_removes_the_staging_folder_on_failure(tmp_path):
    target = tmp_path / "out"
    with pytest.raises(RuntimeError), result_folder(target, ["a.txt"]) as staging:
        (staging / "a.txt").write_text("half")
        raise RuntimeError("crash")
    assert list(tmp_path.iterdir()) == []  # the folder it created is gone again
    target.mkdir()
    (target / "a.txt").write_text("old")
    with pytest.raises(RuntimeError), result_folder(target, ["a.txt"]) as staging:
        (staging / "a.txt").write_text("half")
        raise RuntimeError("crash")
    assert [entry.name for entry in target.iterdir()] == ["a.txt"]
    assert (target / "a.txt").read_text() == "old"


def test_result_folder_refuses_a_file(tmp_path):
    (tmp_path / "out").write_text("")
    with pytest.raises(NotADirectoryError), result_folder(tmp_path / "out", []):
        pass


def test_signals_are_held_back_while_the_set_is_swapped(ctrl_c_raises):
    reached_end = False
    with pytest.raises(KeyboardInterrupt), deferred_signals():
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.2)
        reached_end = True
    assert reached_end


def test_temporary_names_carry_the_process_id(tmp_path):
    with atomic_path(tmp_path / "checkpoint.pt") as tmp:
        assert tmp.name.startswith(f".checkpoint.{os.getpid()}-") and tmp.name.endswith(".tmp.pt")
        tmp.write_text("x")


def test_stale_temporaries_of_dead_processes_are_removed(tmp_path):
    dead, alive = _dead_pid(), os.getppid()
    stale = tmp_path / f".checkpoint.{dead}-abcd1234.tmp.pt"
    live = tmp_path / f".checkpoint.{alive}-abcd1234.tmp.pt"
    old_legacy = tmp_path / ".checkpoint.abcd1234.tmp.pt"
    new_legacy = tmp_path / ".checkpoint.wxyz5678.tmp.pt"
    other_target = tmp_path / f".checkpoint.best.{dead}-abcd1234.tmp.pt"
    for path in (stale, live, old_legacy, new_legacy, other_target):
        path.write_text("partial")
    hour_ago = time.time() - LEGACY_STALE_SECONDS - 60
    os.utime(old_legacy, (hour_ago, hour_ago))
    with atomic_path(tmp_path / "checkpoint.pt") as tmp:
        tmp.write_text("new")
    assert not stale.exists() and not old_legacy.exists()
    assert live.exists() and new_legacy.exists() and other_target.exists()


def test_a_sigkilled_write_is_cleaned_by_the_next_one(tmp_path):
    target = tmp_path / "checkpoint.pt"
    script = (
        "import os, signal, sys\n"
        "from taptr.io.atomic import atomic_path\n"
        "with atomic_path(sys.argv[1]) as tmp:\n"
        "    tmp.write_bytes(b'x' * 1000)\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    killed = subprocess.run([sys.executable, "-c", script, str(target)], check=False)
    assert killed.returncode == -signal.SIGKILL
    assert len(_hidden(tmp_path)) == 1  # the temporary the killed process left
    with atomic_path(target) as tmp:
        tmp.write_text("done")
    assert [entry.name for entry in tmp_path.iterdir()] == ["checkpoint.pt"]


def test_stale_staging_folders_are_removed_by_the_next_track(clip, tmp_path):
    out = tmp_path / "out"
    staging = out / f".taptr.{_dead_pid()}-abcd1234.tmp"
    staging.mkdir(parents=True)
    (staging / "tracks.npz").write_bytes(b"partial")
    assert _track(clip, out, "--grid", "2") == 0
    assert not _hidden(out)


def test_out_dot_needs_only_the_folder_itself(clip, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert _track(clip, ".", "--grid", "2") == 0
    assert sorted(entry.name for entry in tmp_path.iterdir()) == [
        "overlay.mp4",
        "settings.json",
        "tracks.csv",
        "tracks.npz",
    ]


def test_convert_cleans_a_stale_temporary(tmp_path, capsys):
    from taptr import build_model
    from taptr.weights.checkpoint import save_checkpoint

    save_checkpoint(build_model("tiny"), tmp_path / "src.pth")
    leftover = tmp_path / f".dst.{_dead_pid()}-abcd1234.tmp.pth"
    leftover.write_bytes(b"\0" * 1000)
    assert main(["convert", str(tmp_path / "src.pth"), str(tmp_path / "dst.pth")]) == 0
    assert not leftover.exists() and (tmp_path / "dst.pth").is_file()


def test_remove_stale_temporaries_ignores_a_missing_folder(tmp_path):
    assert remove_stale_temporaries(tmp_path / "missing", ".x.", ".tmp") == []
