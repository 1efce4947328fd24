"""The corpus's results layout, video lists, cluster checks and progress, without a Ray job.

Parts holding many videos, published whole and read back; the index as the commit and
the skip set; superseded rows compacted; foreign files and links refused; the first
layout migrated; video lists bounded before parsing; impossible requests of the cluster
refused in seconds.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from taptr.cli.main import main
from taptr.corpus.inputs import CorpusVideo, QuerySpec
from taptr.corpus.progress import Progress, Summary
from taptr.corpus.records import DONE, FAILED, Failure, Finished, VideoTracks
from taptr.corpus.video_list import MAX_HEADER_BYTES, read_video_list
from taptr.messages import install_line
from tests.corpus_helpers import video as tracked

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")

DOCS = Path(__file__).resolve().parents[1] / "docs" / "CORPUS.md"
RUN = "20261207T000000000000Z"


def _failure(name: str, digest: str = "d" * 16) -> Failure:
    return Failure(name, f"/clips/{name}.mp4", "cannot read video", 1, 48, 6, digest)


def _layout(tmp_path: Path):
    from taptr.corpus.layout import ResultLayout

    layout = ResultLayout.at(str(tmp_path / "out"))
    layout.prepare()
    return layout


def _writer(layout, run: str = RUN, videos: int = 1000):
    from taptr.corpus.parts import PartLimits, PartWriter

    return PartWriter(layout, run, PartLimits(videos=videos))


def test_a_part_holds_many_videos_and_the_dataset_reads_as_one_table(tmp_path):
    import pandas as pd

    from taptr.corpus.schema import tracks_schema

    layout = _layout(tmp_path)
    writer = _writer(layout, videos=3)
    for index, name in enumerate(["a", "b", "c", "d"]):
        writer.add_tracks(index, tracked(name, frames=4 + index))
        if writer.due():
            committed = writer.flush()
            assert committed.indices == (0, 1, 2)
    writer.add_failure(4, _failure("e"))
    assert writer.flush().indices == (3, 4)
    out = tmp_path / "out"
    assert len(list((out / "tracks").iterdir())) == 2  # 4 videos, 2 parts
    frame = pd.read_parquet(out / "tracks")
    assert list(frame.columns) == tracks_schema().names
    assert sorted(set(frame["video_id"])) == ["a", "b", "c", "d"] and len(frame) == 12
    d = frame[frame["video_id"] == "d"]
    np.testing.assert_array_equal(np.stack(d["positions"].iloc[1]), tracked("d", 7).tracks[:, 1])
    assert list(d["declared_frames"]) == [7] * 3 and list(d["decoded_frames"]) == [7] * 3
    (failure,) = pd.read_parquet(out / "failures").to_dict("records")
    assert (failure["declared_frames"], failure["decoded_frames"], failure["attempts"]) == (
        48,
        6,
        1,
    )
    index = layout.read_index()
    assert sorted(index["video_id"].to_pylist()) == ["a", "b", "c", "d", "e"]
    assert index.filter(pa.compute.equal(index["status"], FAILED))["video_id"].to_pylist() == ["e"]
    for name in tracks_schema().names:  # every column is documented
        assert f"| `{name}` |" in DOCS.read_text(encoding="utf-8"), name


def test_duckdb_and_pyarrow_read_the_parts_as_the_docs_query_them(tmp_path):
    duckdb = pytest.importorskip("duckdb")
    import pyarrow.dataset as ds

    layout = _layout(tmp_path)
    writer = _writer(layout)
    for index, (name, frames) in enumerate((("a", 4), ("b", 6))):
        video = tracked(name, frames)
        visible = np.ones((frames, 3), bool)
        visible[0, 1] = False
        writer.add_tracks(index, VideoTracks(**{**vars(video), "visibility": visible}))
    writer.flush()
    query = (
        "SELECT video_id, count(*) AS points, "
        "avg(list_sum(CAST(visibility AS INTEGER[])) / num_frames) AS visible "
        f"FROM '{tmp_path}/out/tracks/*.parquet' GROUP BY video_id ORDER BY video_id"
    )
    rows = duckdb.sql(query).fetchall()
    assert [row[:2] for row in rows] == [("a", 3), ("b", 3)]
    np.testing.assert_allclose([row[2] for row in rows], [11 / 12, 17 / 18])
    table = ds.dataset(tmp_path / "out" / "tracks").to_table(filter=ds.field("video_id") == "b")
    assert table.num_rows == 3


def test_a_part_that_reads_back_short_is_not_committed(tmp_path, monkeypatch):
    from taptr.corpus.storage import Storage

    layout = _layout(tmp_path)
    writer = _writer(layout)
    writer.add_tracks(0, tracked("a"))
    real_write = Storage.write

    def lossy(self, relative, data):  # a store that drops the end of what it was given
        real_write(self, relative, data if "_index" in relative else data[: len(data) // 2])

    monkeypatch.setattr(Storage, "write", lossy)
    with pytest.raises(OSError, match="does not read back"):
        writer.flush()
    assert layout.read_index().num_rows == 0  # no index: the video is not done
    assert list((tmp_path / "out" / "tracks").iterdir()) == []  # nor a file readers would meet
    monkeypatch.setattr(Storage, "write", real_write)
    assert writer.flush().indices == (0,)  # the rows wait for the next try
    assert layout.remove_orphans() == []


def test_orphan_parts_are_removed_and_superseded_rows_compacted(tmp_path):
    from taptr.corpus.compaction import compact
    from taptr.corpus.layout import FAILURES, TRACKS
    from taptr.corpus.standing import standing

    layout = _layout(tmp_path)
    first = _writer(layout, "20261207T000000000000Z")
    for index, name in enumerate("abc"):
        first.add_tracks(index, tracked(name))
    first.add_failure(3, _failure("f"))
    first.flush()
    second = _writer(layout, "20261208T000000000000Z")
    second.add_tracks(0, tracked("a", frames=9, digest="e" * 16))  # a, other settings
    second.add_failure(1, _failure("b"))  # b failed after its result: both stand
    second.add_tracks(2, tracked("f"))  # f done now: its old failure goes
    second.flush()
    # a part without an index: its actor died while writing it
    orphan = tmp_path / "out" / TRACKS / "part-20261208T000000000000Z-0badc0de-000000.parquet"
    orphan.write_bytes(
        (tmp_path / "out" / TRACKS)
        .joinpath(sorted(os.listdir(tmp_path / "out" / TRACKS))[0])
        .read_bytes()
    )
    assert layout.remove_orphans() == [orphan.name.removesuffix(".parquet")]
    assert compact(layout, "20261209T000000000000Z") == 1  # the first part, rewritten
    rows = standing(layout.read_index()).to_pylist()
    found = {row["video_id"]: (row["done_digest"], row["failed_digest"]) for row in rows}
    assert found["a"] == ("e" * 16, None)  # the newer result stands
    assert None not in found["b"]  # a failure newer than its result stands beside it
    assert found["f"] == ("d" * 16, None)  # a result newer than its failure replaces it
    tracks = layout.read_tracks()
    counts = {name: tracks["video_id"].to_pylist().count(name) for name in "abcf"}
    assert counts == {"a": 3, "b": 3, "c": 3, "f": 3}  # each video's rows once
    frames = tracks.filter(pa.compute.equal(tracks["video_id"], "a"))["num_frames"].to_pylist()
    assert frames == [9, 9, 9]
    assert layout.read_failures()["video_id"].to_pylist() == ["b"]
    assert compact(layout, "20261209T000000000000Z") == 0  # nothing left to do
    assert len(layout.parts(FAILURES)) == 1


def test_a_rerun_skips_what_the_index_says_is_done(tmp_path):
    from taptr.corpus.damage import sound_index
    from taptr.corpus.pipeline import CorpusOptions, plan

    layout = _layout(tmp_path)
    writer = _writer(layout)
    writer.add_tracks(0, tracked("done"))
    writer.add_failure(1, _failure("failed"))
    writer.flush()
    spec = QuerySpec(grid=2)
    videos = [
        CorpusVideo("done", "x", spec, "d" * 16),
        CorpusVideo("failed", "x", spec, "d" * 16),
        CorpusVideo("other-settings", "x", spec, "d" * 16),
        CorpusVideo("new", "x", spec, "e" * 16),
    ]
    summary = Summary(total=4)
    tasks = plan(videos, sound_index(layout), CorpusOptions(out=str(tmp_path / "out")), summary)
    assert [task.video_id for task in tasks] == ["other-settings", "new"]
    assert [task.index for task in tasks] == [0, 1]
    assert (summary.skipped, summary.failed_before) == (1, 1)
    retry = CorpusOptions(out=str(tmp_path / "out"), retry_failed=True)
    assert len(plan(videos, sound_index(layout), retry, Summary(total=4))) == 3
    overwrite = CorpusOptions(out=str(tmp_path / "out"), overwrite=True)
    assert len(plan(videos, sound_index(layout), overwrite, Summary(total=4))) == 4


def test_foreign_files_links_and_the_old_layout_are_refused_before_any_work(tmp_path):
    from taptr.corpus.layout import ResultLayout

    out = tmp_path / "out"
    _layout(tmp_path)
    layout = ResultLayout.at(str(out))
    (out / "tracks" / "someone-elses.parquet").write_bytes(b"PAR1")
    with pytest.raises(ValueError, match=r"not this job's own: tracks/someone-elses.parquet"):
        layout.check()
    (out / "tracks" / "someone-elses.parquet").unlink()
    (out / "_staging").rmdir()
    (out / "_staging").symlink_to(tmp_path)
    with pytest.raises(ValueError, match=r"_staging \(a link\)"):
        layout.check()
    (out / "_staging").unlink()
    (out / "failures" / "x-0123456789abcdef.0123456789abcdef.parquet").write_bytes(b"PAR1")
    with pytest.raises(ValueError, match=r"old layout .* --migrate"):
        layout.check()
    (out / "failures" / "x-0123456789abcdef.0123456789abcdef.parquet").unlink()
    (out / "_corpus.json").write_text('{"layout": 99}')
    with pytest.raises(ValueError, match="newer taptr"):
        layout.check()


def test_the_first_layout_migrates_with_its_digests(tmp_path):
    from taptr.corpus.layout import ResultLayout
    from taptr.corpus.migrate import migrate
    from taptr.corpus.schema import tracks_schema

    out = tmp_path / "out"
    (out / "tracks").mkdir(parents=True)
    (out / "failures").mkdir()
    (out / "_attempts" / "k.d").mkdir(parents=True)
    old_tracks = tracks_schema()
    old_tracks = pa.schema(
        [f for f in old_tracks if "_frames" not in f.name or f.name == "num_frames"],
        metadata={b"taptr.schema": b"1"},
    )
    for name in ("a", "b"):
        rows = {f.name: [None] * 2 for f in old_tracks}
        rows.update(
            video_id=[name] * 2,
            point_id=[0, 1],
            num_frames=[5, 5],
            settings_digest=["0123456789abcdef"] * 2,
            positions=[[[1.0, 2.0]] * 5] * 2,
            visibility=[[True] * 5] * 2,
            query=[[0.0, 1.0, 2.0]] * 2,
        )
        pq.write_table(
            pa.table(rows, schema=old_tracks),
            out / "tracks" / f"{name}-{'0' * 16}.0123456789abcdef.parquet",
        )
    failure = {
        "video_id": ["c"],
        "path": ["c.mp4"],
        "error": ["no frames"],
        "attempts": [1],
        "settings_digest": ["0123456789abcdef"],
    }
    pq.write_table(pa.table(failure), out / "failures" / f"c-{'1' * 16}.0123456789abcdef.parquet")
    layout = ResultLayout.at(str(out))
    with pytest.raises(ValueError, match="--migrate"):
        layout.check()
    assert migrate(layout) == 3
    layout.prepare()
    tracks = layout.read_tracks()
    assert sorted(set(tracks["video_id"].to_pylist())) == ["a", "b"]
    assert tracks["decoded_frames"].to_pylist() == [5] * 4
    assert tracks["declared_frames"].null_count == 4
    assert layout.read_failures()["error"].to_pylist() == ["no frames"]
    index = layout.read_index()
    assert set(index["settings_digest"].to_pylist()) == {"0123456789abcdef"}
    assert not (out / "_attempts").exists()


def test_video_lists_in_csv_and_parquet(tmp_path):
    default = QuerySpec(grid=3)
    table = pa.table(
        {
            "path": ["a.mp4", "/abs/b.mp4", "c.mp4"],
            "id": ["first", None, "third"],
            "points": [[[0.0, 1.0, 2.0]], None, None],
            "grid": [None, None, 2.0],  # pandas writes a column with a gap as float64
            "query_frame": [None, None, float("nan")],
        }
    )
    pq.write_table(table, tmp_path / "m.parquet")
    first, second, third = read_video_list(tmp_path / "m.parquet", default)
    assert (first.video_id, first.path) == ("first", str(tmp_path / "a.mp4"))
    assert first.queries.points == ((0.0, 1.0, 2.0),)
    assert (second.video_id, second.path, second.queries) == ("/abs/b.mp4", "/abs/b.mp4", default)
    assert third.queries == QuerySpec(grid=2)
    (tmp_path / "m.csv").write_text("path,grid,query_frame\nc.mp4,4.0,2\nd.mp4,,\n")
    with pytest.raises(ValueError, match="row 3: no points, grid or mask"):
        read_video_list(tmp_path / "m.csv", None)
    assert read_video_list(tmp_path / "m.csv", default)[0].queries == QuerySpec(
        grid=4, query_frame=2
    )


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("path,colour\nc.mp4,red\n", r"unknown columns \['colour'\]"),
        ("path,id,id\nc.mp4,a,b\n", r"the columns \['id'\] appear more than once"),
        ("path,id\n", "lists no videos"),
        ("path,id\na.mp4,x\nb.mp4,y\na.mp4,x\n", "rows 2 and 4 both have the id 'x'"),
        ("path,grid\na.mp4,2.5\n", "row 2: grid '2.5' is not a whole number"),
        ('path,points\nc.mp4,"[[0, 1]]"\n', "row 2: points must be rows of three numbers"),
        (
            'path,points\nc.mp4,"' + "[" * 60000 + "]" * 60000 + '"\n',
            "row 2: points nest 60000 levels deep",
        ),
        ("path\n" + "x" * 5000 + ".mp4\n", "row 2: path is longer than 4096 characters"),
        ("p" * (MAX_HEADER_BYTES + 10) + "\n", "header line is longer than"),
    ],
)
def test_video_lists_are_bounded_and_refused_in_one_line(tmp_path, text, message):
    (tmp_path / "m.csv").write_text(text)
    with pytest.raises(ValueError, match=message) as error:
        read_video_list(tmp_path / "m.csv", QuerySpec(grid=2))
    assert "\n" not in str(error.value) and len(str(error.value)) < 400


def test_a_12000_point_csv_row_is_read(tmp_path):
    points = [[0, 100.123456, 200.654321]] * 12_000
    (tmp_path / "m.csv").write_text(f'path,points\nc.mp4,"{json.dumps(points)}"\n')
    (video,) = read_video_list(tmp_path / "m.csv", None)
    assert len(video.queries.points) == 12_000


def test_ids_given_twice_across_inputs_are_refused(tmp_path):
    from taptr.corpus.pipeline import CorpusOptions, run_corpus

    twins = [
        CorpusVideo("x", "a.mp4", QuerySpec(grid=2)),
        CorpusVideo("x", "b.mp4", QuerySpec(grid=2)),
    ]
    with pytest.raises(ValueError, match="the id 'x' is given to videos 1 and 2"):
        run_corpus(twins, None, CorpusOptions(out=str(tmp_path)))


class _FakeRay:
    """``ray.nodes()`` of a cluster on paper."""

    def __init__(self, *nodes):
        self._nodes = [{"Alive": True, "Resources": resources} for resources in nodes]

    def nodes(self):
        return self._nodes


@pytest.mark.parametrize(
    ("actors", "shape", "message"),
    [
        (None, (1000, 0, 2**30), r"no node of the cluster can hold one tracker actor \(1000 CPU"),
        (None, (1, 1, 2**30), "no node .* the largest has 2 CPU, no GPU"),
        (1_000_000, (1, 0, 2**30), "--actors 1000000 .* more than the cluster holds: 2"),
        (None, (0.01, 0, 20 * 2**30), r"no node .*\(0.01 CPU, 20.0 GiB\)"),
    ],
)
def test_impossible_requests_of_the_cluster_are_refused(actors, shape, message):
    from taptr.corpus.cluster import ActorShape, plan_actors

    ray = _FakeRay({"CPU": 2.0, "memory": 16 * 2**30})
    with pytest.raises(ValueError, match=message):
        plan_actors(ray, actors, ActorShape(*shape))


def test_the_cluster_holds_as_many_actors_as_memory_allows():
    from taptr.corpus.cluster import ActorShape, plan_actors

    ray = _FakeRay(
        {"CPU": 2.0, "memory": 6 * 2**30}, {"CPU": 8.0, "GPU": 2.0, "memory": 64 * 2**30}
    )
    assert plan_actors(ray, None, ActorShape(0.01, 0, 2**30)) == 6 + 64  # memory bounds it
    assert plan_actors(ray, None, ActorShape(1, 1, 2**30)) == 2


def test_an_unreachable_address_fails_in_seconds_naming_it():
    from taptr.corpus.cluster import check_address

    with socket.socket() as probe:  # a port nobody listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    started = time.perf_counter()
    with pytest.raises(ValueError, match=rf"cannot reach the Ray cluster at 127.0.0.1:{port}"):
        check_address(f"127.0.0.1:{port}")
    assert time.perf_counter() - started < 5
    with pytest.raises(ValueError, match="expected HOST:PORT"):
        check_address("nonsense")


def test_progress_lines_and_the_summary_agree():
    summary = Summary(total=5, skipped=1)
    lines = []
    progress = Progress(summary, 4, every=3600, print_line=lambda text, **_: lines.append(text))
    progress.tick()
    assert lines == []  # no actor ready yet: no rate to tell
    events = [
        Finished(0, DONE, frames=30, points=2, seconds=2),
        Finished(1, FAILED, "no frames"),
        Finished(2, DONE, frames=10, points=2, seconds=1),
        Finished(3, DONE, frames=20, points=2, seconds=1),
    ]
    progress.start(time.monotonic() - 10)
    for event, video_id in zip(events, "abcd", strict=True):
        progress.update(event)
        summary.commit(event, 2 if video_id == "c" else 1, video_id)
    assert progress.line(10.0) == "corpus: 4/4 videos (1 failed), 6 frames/s, about 0.0s left"
    summary.seconds, summary.tracking_seconds = 12.0, 10.0
    assert summary.line() == (
        "5 videos: 3 done (1 after their worker died), 1 skipped (already done), 1 failed in "
        "12.0s; 0.3 videos/s, 6 frames/s"
    )
    progress.final()
    assert lines == ["corpus: 4/4 videos (1 failed), 6 frames/s, done"]
    assert summary.as_dict()["failures"] == {"b": "no frames"}
    assert summary.actor_seconds == 4  # the failed video's second is not a tracked frame's


def test_ids_and_errors_are_printed_escaped():
    summary = Summary(total=1)
    summary.commit(Finished(0, FAILED, "cannot read video"), 0, "evil\n2 videos: 2 done\x1b[2J")
    (line,) = summary.failure_lines("out/failures")
    assert "\n" not in line and "\x1b" not in line and "\\n2 videos" in line and "\\x1b[2J" in line


def test_without_ray_the_command_says_how_to_install_it(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)
    status = main(["track-corpus", str(tmp_path), "--grid", "2", "--out", str(tmp_path / "o")])
    assert status == 2
    assert install_line("ray") in capsys.readouterr().err


def test_a_part_cut_after_it_was_written_is_not_trusted(tmp_path, capsys):
    from taptr.corpus.damage import sound_index
    from taptr.corpus.pipeline import CorpusOptions, plan

    layout = _layout(tmp_path)
    for index, name in enumerate("ab"):
        writer = _writer(layout)
        writer.add_tracks(index, tracked(name))
        writer.flush()
    damaged = sorted((tmp_path / "out" / "tracks").iterdir())[0]
    damaged.write_bytes(damaged.read_bytes()[:20])  # cut to 20 bytes
    index = sound_index(layout)
    said = capsys.readouterr().out
    assert f"removed a damaged part: tracks/{damaged.name} does not read as a Parquet" in said
    assert not damaged.exists() and len(index) == 1
    videos = [CorpusVideo(name, "x", QuerySpec(grid=2), "d" * 16) for name in "ab"]
    summary = Summary(total=2)
    assert len(plan(videos, index, CorpusOptions(out=str(tmp_path / "out")), summary)) == 1
    assert summary.skipped == 1
    layout.read_tracks()  # the dataset reads again
