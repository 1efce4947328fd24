"""``taptr track-corpus`` as Ray jobs: killed actors, truncated files, reruns, signals, S3.

The main job runs once (Ray starts in seconds, actors in more): 20 videos of mixed
lengths, one killed mid-video in its first attempt and one in every attempt (their
actors die as the OOM killer would end them), a corrupt file, an oversized one and a
truncated one. Then a job stopped by SIGINT and by SIGTERM in a subprocess while it waits
on Ray, each resumed; and a job run from Python (`taptr.corpus.track_corpus`) writing to
an S3-compatible server on loopback, rerun by the command. Every Ray process of these
jobs listens and connects on loopback only (checked while they run). The layout's own
rules are tested without Ray in tests/test_corpus_layout.py and
tests/test_corpus_tampered.py; losing a node in tests/test_corpus_cluster.py.
"""

from __future__ import annotations

import builtins
import contextlib
import io
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import taptr
from taptr.cli.main import main
from taptr.io.video import read_video, write_video
from tests.corpus_helpers import ray_sockets_beyond_loopback, s3_on_loopback
from tests.helpers import panning_clip, write_truncated_clip

pytest.importorskip("ray")
pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")

LENGTHS = [3, 4, 5, 6, 7, 8, 9, 10, 11, 12] * 2
OWN_POINTS = [[0, 10.0, 12.0], [2, 30.5, 20.0], [1, 5.0, 5.0]]


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    """A video list of 23 videos: 20 good, a corrupt, an oversized and a truncated one."""
    folder = tmp_path_factory.mktemp("corpus")
    rows = ["path,id,points"]
    for index, count in enumerate(LENGTHS):
        write_video(
            folder / f"clip{index:02d}.mp4", panning_clip(count, 1 + index % 3, index), fps=10
        )
        points = json.dumps(OWN_POINTS) if index % 4 == 1 else ""
        rows.append(f'clip{index:02d}.mp4,v{index:02d},"{points}"')
    write_video(folder / "long.mp4", panning_clip(26, 1, 99), fps=10)  # over --max-video-frames 25
    (folder / "corrupt.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42 but not a video")
    write_truncated_clip(folder / "cut.mp4")
    rows += ["corrupt.mp4,corrupt,", "long.mp4,long,", "cut.mp4,cut,"]
    (folder / "corpus.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    return folder


def _track_corpus(corpus: Path, checkpoint: Path, out: Path, *extra: str) -> tuple[int, str]:
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        status = main(
            [
                "track-corpus",
                str(corpus / "corpus.csv"),
                "--grid",
                "2",
                "--checkpoint",
                str(checkpoint),
                "--device",
                "cpu",
                "--out",
                str(out),
                "--actors",
                "2",
                "--attempts",
                "2",
                "--max-video-frames",
                "30",
                "--part-videos",
                "4",
                "--progress-every",
                "0",
                *extra,
            ]
        )
    return status, printed.getvalue()


@pytest.fixture
def quiet_ray(monkeypatch):
    # Ray's memory monitor kills workers when the whole machine is short of memory, which
    # on a shared test machine is other processes' doing; the deaths tested here are ours
    monkeypatch.setenv("RAY_memory_monitor_refresh_ms", "0")


def test_a_corpus_survives_killed_actors_records_every_failure_and_resumes(
    corpus, tiny_checkpoint, tmp_path, monkeypatch, quiet_ray
):
    out = tmp_path / "out"
    monkeypatch.setenv("TAPTR_CORPUS_KILL", "v07:1")
    own_print = builtins.print
    status, printed = _track_corpus(corpus, tiny_checkpoint, out, "--max-video-frames", "25")
    assert status == 2, printed
    assert builtins.print is own_print  # Ray swaps it when it reports a worker's death
    # v07's actor died in its first attempt: done in its second
    assert re.search(r"23 videos: 20 done \(\d+ after their worker died\), 0 skipped", printed)
    assert "3 failed in" in printed
    assert re.search(r"corpus: 23/23 videos \(3 failed\), [\d.]+ frames/s, done", printed)
    # the lines count written videos: never past the video list's 23, never back
    counts = [int(found) for found in re.findall(r"^corpus: (\d+)/23 videos", printed, re.M)]
    assert (
        counts == sorted(counts) and max(counts) == 23 and "left" not in printed.split("done")[-1]
    )
    # Ray's lines (a killed actor, a dead raylet's last log lines) stay in its logs
    assert all(re.match(r"corpus: |\d+ videos: |  ", line) for line in printed.splitlines())

    # every good video complete exactly once, v07 too; many videos to a part
    table = pq.read_table(out / "tracks")
    index = pq.read_table(out / "_index")
    assert sorted(index["video_id"].to_pylist()) == sorted(
        [f"v{i:02d}" for i in range(20)] + ["corrupt", "long", "cut"]
    )
    assert len(list((out / "tracks").iterdir())) < 20
    predictor = taptr.Predictor.from_pretrained(tiny_checkpoint, device="cpu")
    for index_, count in enumerate(LENGTHS):
        rows = table.filter(pa.compute.equal(table["video_id"], f"v{index_:02d}")).to_pylist()
        assert [row["point_id"] for row in rows] == list(range(len(rows)))
        queries = np.array([row["query"] for row in rows], np.float32)
        if index_ % 4 == 1:
            np.testing.assert_array_equal(queries, np.float32(OWN_POINTS))
        else:
            assert len(rows) == 4  # --grid 2
        expected = predictor.track(read_video(corpus / f"clip{index_:02d}.mp4"), queries)
        tracks = np.array([row["positions"] for row in rows], np.float32).transpose(1, 0, 2)
        visibility = np.array([row["visibility"] for row in rows]).T
        assert tracks.shape == (count, len(rows), 2)
        assert (rows[0]["num_frames"], rows[0]["declared_frames"], rows[0]["decoded_frames"]) == (
            count,
            count,
            count,
        )
        # float32 noise only: the stream encodes chunks of frames where track encodes windows
        np.testing.assert_allclose(tracks, expected.tracks[0].numpy(), atol=5e-3, rtol=0)
        np.testing.assert_array_equal(visibility, expected.visibility[0].numpy())
        assert rows[0]["model"] == str(tiny_checkpoint) and len(rows[0]["settings_digest"]) == 16

    # bad videos recorded with their one-line errors and frame counts
    failures = {row["video_id"]: row for row in pq.read_table(out / "failures").to_pylist()}
    assert set(failures) == {"corrupt", "long", "cut"}
    assert "cannot read video" in failures["corrupt"]["error"]
    assert failures["corrupt"]["attempts"] == 0  # it never reached the model
    assert "declares 26 frames, more than the limit of 25" in failures["long"]["error"]
    assert (failures["long"]["declared_frames"], failures["long"]["attempts"]) == (26, 0)
    cut = failures["cut"]
    assert (cut["declared_frames"], cut["attempts"]) == (24, 1) and cut["decoded_frames"] < 24
    assert f"decoded {cut['decoded_frames']} of the 24 frames" in cut["error"]
    assert all("\n" not in row["error"] for row in failures.values())
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["state"], summary["done"], summary["failed"]) == ("finished", 20, 3)
    assert summary["retried"] >= 1 and summary["left"] == 0
    assert not list((out / "_staging").iterdir())

    # a rerun skips them all without starting Ray; --accept-truncated keeps the cut one
    monkeypatch.delenv("TAPTR_CORPUS_KILL")
    started = time.perf_counter()
    status, printed = _track_corpus(corpus, tiny_checkpoint, out, "--max-video-frames", "25")
    assert time.perf_counter() - started < 20
    assert status == 2
    assert "23 videos: 0 done, 20 skipped (already done), 0 failed, 3 failed before" in printed
    assert "--retry-failed tracks them again" in printed
    status, printed = _track_corpus(
        corpus, tiny_checkpoint, out, "--retry-failed", "--accept-truncated"
    )
    assert "23 videos: 2 done" in printed  # cut and long (limit now 30); corrupt fails again
    tracks = pq.read_table(out / "tracks")
    cut_rows = tracks.filter(pa.compute.equal(tracks["video_id"], "cut")).to_pylist()
    assert cut_rows[0]["declared_frames"] == 24 and cut_rows[0]["decoded_frames"] < 24
    ids = tracks["video_id"].to_pylist()
    assert all(ids.count(f"v{i:02d}") in (3, 4) for i in range(20))  # each video once
    assert [row["video_id"] for row in pq.read_table(out / "failures").to_pylist()] == ["corrupt"]


def _descendants(pid: int) -> set[int]:
    """Process ids below ``pid``, read from /proc."""
    parents = {}
    for entry in Path("/proc").iterdir():
        with contextlib.suppress(OSError, ValueError, IndexError):
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            parents[int(entry.name)] = int(fields[1])
    found, frontier = set(), {pid}
    while frontier:
        frontier = {child for child, parent in parents.items() if parent in frontier} - found
        found |= frontier
    return found


def _running(pid: int) -> bool:
    with contextlib.suppress(OSError, IndexError):
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        return state != "Z"
    return False


def _start_job(corpus: Path, out: Path) -> subprocess.Popen:
    command = [
        sys.executable, "-m", "taptr.cli.main", "track-corpus", str(corpus), "--grid", "2",
        "--checkpoint", "tiny", "--device", "cpu", "--out", str(out), "--actors", "1",
        "--part-videos", "1", "--progress-every", "0",
    ]  # fmt: skip
    environment = {**os.environ, "RAY_memory_monitor_refresh_ms": "0"}
    return subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=environment,
        preexec_fn=_interruptible,
    )


def _interruptible() -> None:
    """Ctrl-C's default for the job: a test run started in the background of a shell
    without job control ignores SIGINT, and the job would inherit that (POSIX)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _parts(out: Path) -> int:
    return len(list((out / "_index").iterdir())) if (out / "_index").is_dir() else 0


def _stop_after_a_part(job: subprocess.Popen, out: Path, number: int) -> tuple[str, str]:
    """Sends signal ``number`` once the job has written a part; checks no process is left."""
    before = _parts(out)
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and job.poll() is None and _parts(out) == before:
        time.sleep(0.2)
    if job.poll() is not None:
        _, stderr = job.communicate()
        pytest.fail(f"the job ended ({job.returncode}) before a part was written: {stderr[-3000:]}")
    family = _descendants(job.pid)
    assert family  # Ray's processes run below the job's
    exposed = ray_sockets_beyond_loopback(job.pid)
    assert exposed == []  # the local instance listens and connects on loopback only
    job.send_signal(number)  # the driver is waiting on Ray: its actor is tracking
    stdout, stderr = job.communicate(timeout=120)
    time.sleep(2)
    alive = [pid for pid in family if _running(pid)]
    assert not alive, [Path(f"/proc/{pid}/cmdline").read_bytes()[:80] for pid in alive]
    return stdout, stderr


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads processes from /proc")
def test_sigint_and_sigterm_stop_the_job_cleanly_and_a_rerun_finishes_it(tiny_checkpoint, tmp_path):
    folder = tmp_path / "clips"
    folder.mkdir()
    for index in range(12):
        write_video(folder / f"c{index:02d}.mp4", panning_clip(40, 1, index), fps=10)
    # each signal stops a job of its own: on a loaded machine a stopped job may finish
    # most videos before it stops, leaving a second one on the same folder too little
    for number, status in ((signal.SIGINT, 130), (signal.SIGTERM, 143)):
        out = tmp_path / f"out-{number}"
        job = _start_job(folder, out)
        stdout, stderr = _stop_after_a_part(job, out, number)
        assert job.returncode == status, stderr
        assert stderr.splitlines()[-1] == ("interrupted" if status == 130 else "terminated")
        assert "Traceback" not in stderr and "Fatal" not in stderr and "SIGABRT" not in stderr
        assert stderr.count("UNTRAINED weights") == 1  # the driver's, not one per actor
        summary = json.loads((out / "summary.json").read_text())
        assert summary["state"] == "interrupted", stdout
        assert "left for the next run" in stdout or summary["left"] == 0
    job = _start_job(folder, out)
    stdout, stderr = job.communicate(timeout=300)
    assert job.returncode == 0, stderr
    assert "12 videos: " in stdout and " 0 failed" in stdout
    # Ray's own notices (token authentication, worker logs) stay out of the user's way
    assert all(line.startswith("taptr") for line in stderr.splitlines()), stderr
    ids = pq.read_table(out / "tracks")["video_id"].to_pylist()
    assert sorted(set(ids)) == [str(folder / f"c{i:02d}.mp4") for i in range(12)]
    assert all(ids.count(video) == 4 for video in set(ids))  # each video's rows once
    assert json.loads((out / "summary.json").read_text())["state"] == "finished"


@pytest.fixture
def s3_server(monkeypatch):
    """An S3-compatible server (moto) on loopback with a bucket, and its credentials."""
    pytest.importorskip("moto")
    import pyarrow.fs as pafs

    with s3_on_loopback() as endpoint:
        if endpoint is None:
            pytest.skip("the S3 server did not start")
        for name, value in (
            ("AWS_ACCESS_KEY_ID", "test"),
            ("AWS_SECRET_ACCESS_KEY", "test"),
            ("AWS_DEFAULT_REGION", "us-east-1"),
        ):
            monkeypatch.setenv(name, value)
        pafs.FileSystem.from_uri(f"s3://corpus?{endpoint}&allow_bucket_creation=true")[
            0
        ].create_dir("corpus")
        yield endpoint


def test_results_go_to_an_object_store(corpus, tiny_checkpoint, s3_server, quiet_ray):
    """The Python API writes to S3 (no argparse, sockets on loopback); the CLI reruns it."""
    import pandas as pd
    import pyarrow.fs as pafs

    from taptr.api.spec import ModelSpec
    from taptr.corpus import CorpusOptions, CorpusVideo, QuerySpec, read_failures, track_corpus
    from taptr.corpus.layout import ResultLayout
    from taptr.corpus.storage import StoreError

    uri = f"s3://corpus/results?{s3_server}"
    nothing = read_failures(uri)  # no folder on the store yet: the columns all the same
    assert nothing.num_rows == 0 and "video_id" in nothing.schema.names
    with pytest.raises(StoreError, match=r"(?i)cannot use s3://missing/results\?.*bucket"):
        ResultLayout.at(f"s3://missing/results?{s3_server}").prepare()
    names = ["clip00.mp4", "clip01.mp4", "corrupt.mp4"]
    videos = [CorpusVideo(str(corpus / n), str(corpus / n), QuerySpec(grid=2)) for n in names]
    exposed: list[str] = []

    def print_line(text, **_):  # called while the local instance runs
        exposed.extend(ray_sockets_beyond_loopback())

    model = ModelSpec(str(tiny_checkpoint), device="cpu")
    options = CorpusOptions(out=uri, actors=1, progress_every=0)
    summary = track_corpus(videos, model, options, print_line=print_line)
    assert "3 videos: 2 done, 0 skipped (already done), 1 failed" in summary.line()
    assert exposed == []
    store, root = pafs.FileSystem.from_uri(uri)
    tracks = pd.read_parquet(f"{root}/tracks", filesystem=store)
    assert sorted(set(tracks["video_id"])) == [
        str(corpus / "clip00.mp4"),
        str(corpus / "clip01.mp4"),
    ]
    assert len(tracks) == 8 and list(tracks["decoded_frames"].unique()) == [3, 4]
    assert len(pd.read_parquet(f"{root}/failures", filesystem=store)) == 1
    printed = io.StringIO()
    argv = ["track-corpus", *(str(corpus / n) for n in names), "--grid", "2",
            "--checkpoint", str(tiny_checkpoint), "--device", "cpu", "--out", uri]  # fmt: skip
    with contextlib.redirect_stdout(printed):
        assert main(argv) == 2  # the CLI's digests are the API's: nothing to do
    assert "3 videos: 0 done, 2 skipped (already done), 0 failed, 1 failed before" in (
        printed.getvalue()
    )
    assert "results in s3://corpus/results/tracks?" in printed.getvalue()


def test_impossible_requests_fail_in_seconds_with_the_numbers(corpus, tmp_path, capsys, quiet_ray):
    argv = ["track-corpus", str(corpus / "clip00.mp4"), "--grid", "2", "--checkpoint", "tiny",
            "--out", str(tmp_path / "out")]  # fmt: skip
    started = time.perf_counter()
    assert main([*argv, "--address", "127.0.0.1:1"]) == 2
    assert "cannot reach the Ray cluster at 127.0.0.1:1" in capsys.readouterr().err
    assert time.perf_counter() - started < 30
    assert main([*argv, "--gpus-per-actor", "1"]) == 2
    error = capsys.readouterr().err
    assert "no node of the cluster can hold one tracker actor (1 CPU, 1 GPU" in error
    assert "no GPU" in error
    assert not (tmp_path / "out" / "tracks").exists()  # refused before any work
