"""``taptr track-corpus`` on a local Ray instance: complete rows, killed actors, reruns, failures.

The Ray job runs once, in one test (Ray starts in seconds, actors in more, and pytest-xdist
may send tests of one module to different workers): 20 videos of mixed lengths, one of them
killed mid-video once (its actor dies as the OOM killer would end it), a corrupt file and an
oversized one. The tests around it need no Ray: the bound on the attempts at a video whose
worker keeps dying, manifests, the schema, progress lines.
"""

from __future__ import annotations

import builtins
import contextlib
import io
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

import taptr
from taptr.cli.main import main
from taptr.corpus.inputs import QuerySpec, video_key
from taptr.corpus.manifest import read_manifest
from taptr.corpus.progress import Progress, Summary
from taptr.io.video import read_video, write_video

pytest.importorskip("ray")
pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")

DOCS = Path(__file__).resolve().parents[1] / "docs" / "CORPUS.md"
LENGTHS = [3, 4, 5, 6, 7, 8, 9, 10, 11, 12] * 2
OWN_POINTS = [[0, 10.0, 12.0], [2, 30.5, 20.0], [1, 5.0, 5.0]]


def _pan(count: int, speed: int, seed: int) -> np.ndarray:
    """(count, 32, 48, 3) frames of a random texture panning left by ``speed`` pixels a frame."""
    texture = np.random.default_rng(seed).integers(0, 256, (32, 48 + count * speed, 3), np.uint8)
    return np.stack([texture[:, speed * t : speed * t + 48] for t in range(count)])


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    """A manifest of 22 videos: 20 good, a corrupt one and an oversized one."""
    folder = tmp_path_factory.mktemp("corpus")
    rows = ["path,id,points"]
    for index, count in enumerate(LENGTHS):
        write_video(folder / f"clip{index:02d}.mp4", _pan(count, 1 + index % 3, index), fps=10)
        points = json.dumps(OWN_POINTS) if index % 4 == 1 else ""
        rows.append(f'clip{index:02d}.mp4,v{index:02d},"{points}"')
    write_video(folder / "long.mp4", _pan(14, 1, 99), fps=10)  # over --max-video-frames 12
    (folder / "corrupt.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42 but not a video")
    rows += ["corrupt.mp4,corrupt,", "long.mp4,long,"]
    (folder / "corpus.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    return folder


@pytest.fixture(scope="module")
def checkpoint(tiny_checkpoint):
    return tiny_checkpoint


@pytest.fixture
def local_ray(monkeypatch):
    import ray

    # Ray's memory monitor kills workers when the whole machine is short of memory, which
    # on a shared test machine is other processes' doing; the deaths tested here are ours
    monkeypatch.setenv("RAY_memory_monitor_refresh_ms", "0")
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def _track_corpus(corpus: Path, checkpoint: Path, out: Path) -> tuple[int, str]:
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
                "12",
                "--progress-every",
                "0",
            ]
        )
    return status, printed.getvalue()


def test_a_corpus_on_local_ray_survives_killed_actors_and_resumes(
    corpus, checkpoint, tmp_path, monkeypatch, local_ray
):
    out = tmp_path / "out"
    monkeypatch.setenv("TAPTR_CORPUS_KILL", "v07:1")
    own_print = builtins.print
    status, printed = _track_corpus(corpus, checkpoint, out)
    assert status == 2, printed
    assert builtins.print is own_print  # Ray Data's progress bars swap it; it is put back
    # v07's actor died in its first attempt: it was done in the second
    assert (
        "22 videos: 20 done (1 after their worker died), 0 skipped (already done), 2 failed"
        in printed
    )
    assert re.search(r"corpus: 22/22 videos \(2 failed\), [\d.]+ frames/s", printed)

    # every good video complete exactly once, v07 too (its first actor died mid-video)
    assert len(list((out / "tracks").iterdir())) == 20
    table = pq.read_table(out / "tracks")
    predictor = taptr.Predictor.from_pretrained(checkpoint, device="cpu")
    for index, count in enumerate(LENGTHS):
        rows = table.filter(pa.compute.equal(table["video_id"], f"v{index:02d}")).to_pylist()
        assert [row["point_id"] for row in rows] == list(range(len(rows)))
        queries = np.array([row["query"] for row in rows], np.float32)
        if index % 4 == 1:
            np.testing.assert_array_equal(queries, np.float32(OWN_POINTS))
        else:
            assert len(rows) == 4  # --grid 2
        expected = predictor.track(read_video(corpus / f"clip{index:02d}.mp4"), queries)
        tracks = np.array([row["positions"] for row in rows], np.float32).transpose(1, 0, 2)
        visibility = np.array([row["visibility"] for row in rows]).T
        assert tracks.shape == (count, len(rows), 2) and rows[0]["num_frames"] == count
        # float32 noise only: the stream encodes chunks of frames where track encodes windows
        np.testing.assert_allclose(tracks, expected.tracks[0].numpy(), atol=5e-3, rtol=0)
        np.testing.assert_array_equal(visibility, expected.visibility[0].numpy())
        assert rows[0]["model"] == str(checkpoint) and len(rows[0]["settings_digest"]) == 16

    # bad videos recorded with their one-line errors, the others went on
    failures = {row["video_id"]: row for row in pq.read_table(out / "failures").to_pylist()}
    assert set(failures) == {"corrupt", "long"}
    assert "cannot read video" in failures["corrupt"]["error"]
    assert "declares 14 frames, more than the limit of 12" in failures["long"]["error"]
    assert all("\n" not in row["error"] for row in failures.values())
    assert not (out / "_staging").exists() and not (out / "_attempts").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["done"], summary["skipped"], len(summary["failed"])) == (20, 0, 2)
    assert summary["retried"] == 1

    # a rerun skips them all: finished, or failed with the same settings
    monkeypatch.delenv("TAPTR_CORPUS_KILL")
    status, printed = _track_corpus(corpus, checkpoint, out)
    assert status == 2
    assert "22 videos: 0 done, 20 skipped (already done), 0 failed, 2 failed before" in printed
    assert "--retry-failed tracks them again" in printed
    assert len(list((out / "tracks").iterdir())) == 20


def test_a_video_whose_worker_keeps_dying_becomes_a_failure_row(corpus, tmp_path):
    from taptr.corpus.pipeline import CorpusOptions, _todo
    from taptr.corpus.probe import probe_video
    from taptr.corpus.results import ResultLayout, read_failures
    from taptr.corpus.worker import TrackOptions, VideoTracker

    layout = ResultLayout(str(tmp_path))
    layout.prepare()
    row = {"video_id": "v", "path": str(corpus / "clip00.mp4"), "key": "k", "digest": "d"}
    row = probe_video({**row, "queries": QuerySpec(grid=2).to_json()}, None)
    assert row["error"] == "" and row["num_frames"] == 3
    for _ in range(2):  # two attempts whose actor died (as os._exit leaves them)
        layout.start_attempt("k", "d")
    tracker = VideoTracker(lambda: None, TrackOptions(str(tmp_path), max_attempts=2))
    outcome = tracker.track_one(row)
    assert outcome["status"] == "failed"
    assert outcome["error"] == "its worker died in each of 2 attempts (killed or out of memory)"
    (failure,) = read_failures(tmp_path).to_pylist()
    assert (failure["video_id"], failure["attempts"]) == ("v", 2)
    # the next run leaves it, unless asked to try again
    summary = Summary(total=1)
    assert _todo([row], layout, CorpusOptions(out=str(tmp_path)), summary) == []
    assert summary.failed_before == 1
    retry = CorpusOptions(out=str(tmp_path), retry_failed=True)
    assert _todo([row], layout, retry, Summary(total=1)) == [row]


def test_the_documented_schema_is_the_written_one(tmp_path):
    from taptr.corpus.results import ResultLayout, VideoTracks, tracks_schema

    layout = ResultLayout(str(tmp_path))
    layout.prepare()
    rng = np.random.default_rng(0)
    video = VideoTracks(
        "clips/a.mp4",
        "/data/clips/a.mp4",
        np.float32([[0, 1, 2], [3, 4, 5]]),
        rng.random((7, 2, 2), np.float32),
        rng.random((7, 2)) > 0.5,
        (32, 48),
        None,
        "tiny",
        "0123456789abcdef",
    )
    written = layout.write_tracks(video_key(video.video_id), video)
    assert written.parent == tmp_path / "tracks" and written.name.endswith(
        ".0123456789abcdef.parquet"
    )
    frame = __import__("pandas").read_parquet(tmp_path / "tracks")
    assert list(frame.columns) == tracks_schema().names
    np.testing.assert_array_equal(np.stack(frame["positions"][1]), video.tracks[:, 1])
    np.testing.assert_array_equal(frame["visibility"][0], video.visibility[:, 0])
    assert frame["fps"].isna().all() and list(frame["point_id"]) == [0, 1]
    documented = DOCS.read_text(encoding="utf-8")
    for name in tracks_schema().names:
        assert f"| `{name}` |" in documented, name


def test_duckdb_reads_the_dataset_as_the_docs_query_it(tmp_path):
    duckdb = pytest.importorskip("duckdb")
    from taptr.corpus.results import ResultLayout, VideoTracks

    layout = ResultLayout(str(tmp_path))
    layout.prepare()
    for name, frames in (("a", 4), ("b", 6)):
        tracks = np.zeros((frames, 3, 2), np.float32)
        visible = np.ones((frames, 3), bool)
        visible[0, 1] = False
        video = VideoTracks(
            name, name, np.zeros((3, 3), np.float32), tracks, visible, (8, 8), 10.0, "m", "d"
        )
        layout.write_tracks(video_key(name), video)
    query = (
        "SELECT video_id, count(*) AS points, "
        "avg(list_sum(CAST(visibility AS INTEGER[])) / num_frames) AS visible "
        f"FROM '{tmp_path}/tracks/*.parquet' GROUP BY video_id ORDER BY video_id"
    )
    rows = duckdb.sql(query).fetchall()
    assert [row[:2] for row in rows] == [("a", 3), ("b", 3)]
    np.testing.assert_allclose([row[2] for row in rows], [11 / 12, 17 / 18])


def test_manifests_in_csv_and_parquet(tmp_path):
    default = QuerySpec(grid=3)
    table = pa.table(
        {
            "path": ["a.mp4", "/abs/b.mp4"],
            "id": ["first", None],
            "points": [[[0.0, 1.0, 2.0]], None],
        }
    )
    pq.write_table(table, tmp_path / "m.parquet")
    first, second = read_manifest(tmp_path / "m.parquet", default)
    assert (first.video_id, first.path) == ("first", str(tmp_path / "a.mp4"))
    assert first.queries.points == ((0.0, 1.0, 2.0),)
    assert (second.video_id, second.path, second.queries) == ("/abs/b.mp4", "/abs/b.mp4", default)
    (tmp_path / "m.csv").write_text("path,grid,query_frame\nc.mp4,4,2\nd.mp4,,\n")
    with pytest.raises(ValueError, match="row 2: no points, grid or mask"):
        read_manifest(tmp_path / "m.csv", None)
    assert read_manifest(tmp_path / "m.csv", default)[0].queries == QuerySpec(grid=4, query_frame=2)
    (tmp_path / "bad.csv").write_text("path,colour\nc.mp4,red\n")
    with pytest.raises(ValueError, match=r"unknown columns \['colour'\]"):
        read_manifest(tmp_path / "bad.csv", default)
    (tmp_path / "nan.csv").write_text('path,points\nc.mp4,"[[0, 1]]"\n')
    with pytest.raises(ValueError, match="row 1: points must be rows of three numbers"):
        read_manifest(tmp_path / "nan.csv", default)


def test_two_ids_for_one_name_and_keys_that_stay_apart():
    from taptr.corpus.inputs import CorpusVideo
    from taptr.corpus.pipeline import CorpusOptions, track_corpus

    assert video_key("a/b c.mp4") != video_key("a_b c.mp4")
    assert "." not in video_key("a/b.c.mp4").rsplit("-", 1)[1]
    twins = [
        CorpusVideo("x", "a.mp4", QuerySpec(grid=2)),
        CorpusVideo("x", "b.mp4", QuerySpec(grid=2)),
    ]
    with pytest.raises(ValueError, match="the id 'x' names two videos"):
        track_corpus(twins, lambda: None, CorpusOptions(out="unused"))


def test_progress_lines_and_the_summary():
    summary = Summary(total=5, skipped=1)
    lines = []
    progress = Progress(summary, 4, every=3600, print_line=lambda text, **_: lines.append(text))
    progress.update({"video_id": "a", "status": "done", "frames": 30, "error": "", "seconds": 2})
    failed = {"video_id": "b", "status": "failed", "frames": 0, "error": "no frames", "seconds": 1}
    progress.update(failed)
    assert lines == []  # not yet time for a line
    progress.update({"video_id": "c", "status": "done", "frames": 10, "error": "", "seconds": 1})
    progress.update({"video_id": "d", "status": "done", "frames": 20, "error": "", "seconds": 1})
    assert len(lines) == 1 and lines[0].startswith("corpus: 4/4 videos (1 failed), ")
    assert lines[0].endswith("about 0.0s left")
    summary.seconds = 10.0
    assert summary.line() == (
        "5 videos: 3 done, 1 skipped (already done), 1 failed in 10.0s; 0.3 videos/s, 6 frames/s"
    )
    assert summary.as_dict()["failed"] == {"b": "no frames"}
    assert summary.actor_seconds == 4  # the failed video's second is not a tracked frame's


def test_without_ray_the_command_says_how_to_install_it(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)
    status = main(["track-corpus", str(tmp_path), "--grid", "2", "--out", str(tmp_path / "o")])
    assert status == 2
    assert 'pip install "taptr[ray]"' in capsys.readouterr().err
