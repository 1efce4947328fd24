"""A corpus's output folder that others have written in (issue 51), without a Ray job.

OUT is shared in practice: an index whose names point outside it, a part replaced by
another table of the same length, index files cut, emptied, copied, re-pointed, padded
with millions of stray rows or written with other column types, a marker that overflows,
``file:`` URIs written by hand, unsupported schemes and stores that do not answer. The
job must touch nothing outside OUT, trust nothing it did not write, and say in one line
what is wrong, naming the file.
"""

from __future__ import annotations

import contextlib
import io
import json
import time
from pathlib import Path

import pytest

from taptr.cli.main import main
from taptr.corpus.inputs import CorpusVideo, QuerySpec
from taptr.corpus.progress import Summary
from taptr.corpus.storage import AWS_CREDENTIAL_VARIABLES
from tests.corpus_helpers import (
    DIGEST,
    inside,
    prepared,
    s3_on_loopback,
    snapshot,
    touched_paths,
    write_part,
)

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")


def _sound(layout) -> tuple[pa.Table, list[str]]:
    from taptr.corpus.damage import sound_index

    lines: list[str] = []
    index = sound_index(layout, lambda text, **_: lines.append(text))
    return index, lines


def _rewrite_index(out: Path, part: str, change) -> Path:
    """Rewrites ``_index/{part}.parquet`` with ``change(table)``, keeping its metadata."""
    path = out / "_index" / f"{part}.parquet"
    table = change(pq.read_table(path))
    pq.write_table(table, path)
    return path


def _with_column(table: pa.Table, name: str, values: list) -> pa.Table:
    position = table.schema.get_field_index(name)
    return table.set_column(position, table.schema.field(name), pa.array(values, pa.string()))


def _planned(out: Path, index: pa.Table, names: str) -> list[str]:
    from taptr.corpus.pipeline import CorpusOptions, plan

    videos = [CorpusVideo(name, "x.mp4", QuerySpec(grid=2), DIGEST) for name in names]
    return [task.video_id for task in plan(videos, index, CorpusOptions(out=str(out)), Summary(3))]


def test_an_index_naming_paths_outside_out_touches_nothing_there(tmp_path):
    from taptr.corpus.compaction import compact

    out = tmp_path / "shared" / "out"
    layout = prepared(out)
    part = write_part(layout, ["a", "b"])
    write_part(layout, ["a"], run="20261208T000000000000Z")  # a is compacted later
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "precious.parquet").write_bytes((out / "tracks" / f"{part}.parquet").read_bytes())
    outside = snapshot(tmp_path / "victim")
    _rewrite_index(out, part, lambda t: _with_column(t, "part", ["../../victim/precious"] * 2))
    with touched_paths() as touched:
        index, lines = _sound(layout)
        compact(layout, "20261209T000000000000Z", index)
        compact(layout, "20261209T000000000000Z")
    assert snapshot(tmp_path / "victim") == outside  # nothing outside OUT changed
    assert touched and all(inside(path, out) for path in touched), touched
    (line,) = lines
    assert f"_index/{part}.parquet names another part ('../../victim/precious')" in line
    assert not (out / "tracks" / f"{part}.parquet").exists()  # dropped whole, by its own name
    assert _planned(out, index, "ab") == ["b"]  # b runs again; a stands in its other part
    tracks = layout.read_tracks()["video_id"].to_pylist()
    assert sorted(tracks) == ["a"] * 3  # each video's rows once
    assert _sound(layout)[1] == []  # the damage is gone: a rerun says nothing


def test_a_forged_part_with_the_same_row_count_is_not_trusted(tmp_path):
    out = tmp_path / "out"
    layout = prepared(out)
    part = write_part(layout, ["a"])
    forged = pa.table({"video_id": ["forged"] * 3, "score": [1.0, 2.0, 3.0]})
    pq.write_table(forged, out / "tracks" / f"{part}.parquet")  # 3 rows, as indexed
    index, (line,) = _sound(layout)
    assert f"tracks/{part}.parquet holds other columns than the tracks table" in line
    assert "(video_id, score)" in line and len(index) == 0
    assert layout.read_tracks().num_rows == 0  # no forged column reaches pandas
    # the same columns under another schema version are not trusted either
    part = write_part(layout, ["b"])
    table = pq.read_table(out / "tracks" / f"{part}.parquet")
    pq.write_table(
        table.replace_schema_metadata({"taptr.schema": "9"}), out / "tracks" / f"{part}.parquet"
    )
    assert "has schema version '9', not 2" in _sound(layout)[1][0]


@pytest.mark.parametrize(
    ("tamper", "problem"),
    [
        (lambda path: path.write_bytes(path.read_bytes()[:30]), "does not read as a Parquet file"),
        (lambda path: path.write_bytes(b""), "does not read as a Parquet file"),
        (
            lambda path: pq.write_table(
                pa.table(
                    {
                        name: ["four"]
                        for name in ("video_id", "settings_digest", "status", "rows", "run", "part")
                    }
                ),
                path,
            ),
            "holds other columns than the index (video_id, settings_digest, status, rows,",
        ),
        (
            lambda path: pq.write_table(pq.read_table(path).slice(0, 0), path),
            "holds no entries",
        ),
    ],
    ids=["truncated", "empty", "other-types", "no-entries"],
)
def test_a_damaged_index_file_is_removed_with_one_line_and_its_videos_run_again(
    tmp_path, tamper, problem
):
    out = tmp_path / "out"
    layout = prepared(out)
    part = write_part(layout, ["a", "b", "c"])
    tamper(out / "_index" / f"{part}.parquet")
    index, (line,) = _sound(layout)
    assert line.startswith(f"removed a damaged part: _index/{part}.parquet {problem}"), line
    assert "\n" not in line and len(index) == 0
    assert not any((out / folder / f"{part}.parquet").exists() for folder in ("_index", "tracks"))
    assert _planned(out, index, "abc") == ["a", "b", "c"]
    assert _sound(layout)[1] == []  # removed: not said again, not left for the user


def test_a_copied_or_repointed_index_file_drops_only_itself(tmp_path):
    out = tmp_path / "out"
    layout = prepared(out)
    good = write_part(layout, ["a", "b", "c"])
    other = write_part(layout, ["d", "e", "f"])
    copy = good.replace(good.split("-")[2], "0c0c0c0c")  # a well-formed name of its own
    (out / "_index" / f"{copy}.parquet").write_bytes(
        (out / "_index" / f"{good}.parquet").read_bytes()
    )
    _rewrite_index(out, other, lambda t: _with_column(t, "part", [good] * 3))
    index, lines = _sound(layout)
    assert sorted(lines) == sorted(
        [
            f"removed a damaged part: _index/{copy}.parquet names another part ('{good}'); "
            "the videos only it held count as not done",
            f"removed a damaged part: _index/{other}.parquet names another part ('{good}'); "
            "the videos only it held count as not done",
        ]
    )
    assert sorted(index["video_id"].to_pylist()) == ["a", "b", "c"]
    assert _planned(out, index, "abcdef") == ["d", "e", "f"]  # the copy's videos stay done
    assert sorted(layout.read_tracks()["video_id"].to_pylist()) == sorted("abc" * 3)
    assert _sound(layout)[1] == []  # every rerun after that says nothing


def test_stray_and_duplicated_index_rows_do_not_mislead(tmp_path):
    out = tmp_path / "out"
    layout = prepared(out)
    good = write_part(layout, ["a", "b", "c"])
    stray = good.replace(good.split("-")[2], "5e5e5e5e")
    rows = 30_000
    entries = {
        "video_id": [f"x{i}" for i in range(rows)], "settings_digest": [DIGEST] * rows,
        "status": ["done"] * rows, "rows": pa.array([3] * rows, pa.int32()),
        "run": [stray.split("-")[1]] * rows, "part": [stray] * rows,
    }  # fmt: skip
    from taptr.corpus.schema import index_schema

    pq.write_table(pa.table(entries, schema=index_schema()), out / "_index" / f"{stray}.parquet")
    twice = write_part(layout, ["d", "e", "f"])
    _rewrite_index(out, twice, lambda t: pa.concat_tables([t, t]))
    index, lines = _sound(layout)
    assert len(lines) == 2 and not any(str(rows) in line for line in lines), lines
    assert f"removed a damaged part: tracks/{stray}.parquet is missing" in lines[0] + lines[1]
    assert f"_index/{twice}.parquet gave 3 entries more than once; written again" in " ".join(lines)
    assert not (out / "_index" / f"{stray}.parquet").exists()
    assert sorted(index["video_id"].to_pylist()) == list("abcdef")  # the good part stays
    assert pq.read_table(out / "_index" / f"{twice}.parquet").num_rows == 3
    assert _sound(layout)[1] == []


def test_files_no_sound_entry_names_are_removed(tmp_path):
    out = tmp_path / "out"
    layout = prepared(out)
    part = write_part(layout, ["a"], failed=("b",))
    only_failures = write_part(layout, [], failed=("c",))
    planted = out / "tracks" / f"{only_failures}.parquet"  # its index names no tracks
    planted.write_bytes((out / "tracks" / f"{part}.parquet").read_bytes())
    index, lines = _sound(layout)
    assert lines == [] and len(index) == 3
    assert not planted.exists()
    assert sorted(layout.read_tracks()["video_id"].to_pylist()) == ["a"] * 3


def test_a_marker_that_overflows_is_not_a_marker(tmp_path):
    out = tmp_path / "out"
    prepared(out)
    for text in ('{"layout": 1e999}', '{"layout": "2"}', '{"layout": true}', "[]", "{"):
        (out / "_corpus.json").write_text(text)
        with pytest.raises(ValueError, match=r"_corpus.json is not a taptr corpus marker$"):
            prepared(out)


@pytest.mark.parametrize(
    ("out", "message"),
    [
        ("file://localhost/{tmp}/x", "Unsupported hostname in non-Windows local URI"),
        ("file://out/X", "Unsupported hostname in non-Windows local URI"),
        ("file:out/X", "File URI cannot be relative"),
        ("file:///{tmp}/a b", "syntax error"),
        (
            "mock:///res",
            "a local folder or a URI of file:, s3:, gs:, gcs:, hdfs:, .* or abfss:, not mock:",
        ),
    ],
)
def test_malformed_uris_are_refused_by_pyarrow_s_own_parsing(tmp_path, monkeypatch, out, message):
    from taptr.corpus.layout import ResultLayout

    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match=message) as error:
        ResultLayout.at(out.format(tmp=tmp_path))
    assert "\n" not in str(error.value)
    assert sorted(tmp_path.iterdir()) == []  # no ./localhost, ./out or ./file:out made


def test_file_uris_are_decoded_and_kept_local(tmp_path):
    from taptr.corpus.layout import ResultLayout

    layout = ResultLayout.at(f"file://{tmp_path}/a%20b")
    layout.prepare()
    assert layout.storage.local and (tmp_path / "a b" / "_corpus.json").is_file()
    assert layout.tracks == f"file://{tmp_path}/a%20b/tracks"
    write_part(layout, ["a"])
    assert layout.read_tracks().num_rows == 3
    # a folder whose name has a colon is still a folder
    assert ResultLayout.at(str(tmp_path / "results:v2")).storage.local


def test_an_unexpected_error_ends_the_summary_as_failed(tmp_path, monkeypatch):
    from taptr.corpus import pipeline

    out = tmp_path / "out"
    write_part(prepared(out), ["a"])

    def broken(*args, **kwargs):
        raise TypeError("unsupported operand type(s) for +: 'int' and 'NoneType'")

    monkeypatch.setattr(pipeline, "compact", broken)
    videos = [CorpusVideo("a", "x.mp4", QuerySpec(grid=2), DIGEST)]
    with pytest.raises(TypeError):
        pipeline.run_corpus(videos, None, pipeline.CorpusOptions(out=str(out)), print_line=print)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["state"] == "failed" and "unsupported operand" in summary["error"]


def test_failures_read_back_with_their_columns_when_nothing_failed(tmp_path):
    from taptr.corpus import read_failures, read_tracks
    from taptr.corpus.schema import failures_schema, tracks_schema

    out = tmp_path / "out"
    write_part(prepared(out), ["a"])
    failures = read_failures(str(out)).to_pandas()
    assert list(failures.columns) == failures_schema().names and len(failures) == 0
    assert failures[failures.video_id == "a"].empty  # the docs' snippet works as written
    assert read_tracks(str(out)).schema.names == tracks_schema().names


def _track_corpus_exit(argv: list[str], capsys) -> tuple[int, str]:
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        status = main(argv)
    return status, capsys.readouterr().err


def test_a_store_that_does_not_answer_is_a_user_error(tmp_path, capsys):
    pytest.importorskip("ray")
    clip = tmp_path / "clip.mp4"
    clip.write_bytes(b"")  # never read: the store is asked first
    out = "s3://bucket/res?endpoint_override=127.0.0.1:1&scheme=http"
    argv = ["track-corpus", str(clip), "--grid", "2", "--checkpoint", "tiny", "--out", out]
    started = time.perf_counter()
    status, error = _track_corpus_exit(argv, capsys)
    assert status == 2, error
    assert "bug in taptr" not in error and error.count("\n") == 1
    assert "cannot use s3://bucket/res" in error and "Could not connect to server" in error
    assert time.perf_counter() - started < 60


def test_missing_credentials_are_named_in_one_line(tmp_path, capsys, monkeypatch):
    """The AWS SDK's bare INTERNAL_FAILURE for an S3 store without credentials gets a cause."""
    pytest.importorskip("ray")
    pytest.importorskip("moto")
    for name in (*AWS_CREDENTIAL_VARIABLES, "AWS_SECRET_ACCESS_KEY", "AWS_SESSION_TOKEN"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))  # no ~/.aws
    monkeypatch.setenv("AWS_EC2_METADATA_DISABLED", "true")  # no metadata server to ask
    clip = tmp_path / "clip.mp4"
    clip.write_bytes(b"")
    with s3_on_loopback(INITIAL_NO_AUTH_ACTION_COUNT="0") as endpoint:
        if endpoint is None:
            pytest.skip("the S3 server did not start")
        out = f"s3://bucket/res?{endpoint}"
        argv = ["track-corpus", str(clip), "--grid", "2", "--checkpoint", "tiny", "--out", out]
        status, error = _track_corpus_exit(argv, capsys)
    assert status == 2, error
    assert "bug in taptr" not in error and error.count("\n") == 1
    assert "no AWS credentials were found" in error and "cannot use s3://bucket/res" in error


def test_an_unsupported_scheme_says_so_on_the_command_line(tmp_path, capsys):
    pytest.importorskip("ray")
    argv = ["track-corpus", str(tmp_path), "--grid", "2", "--out", "mock:///res"]
    status, error = _track_corpus_exit(argv, capsys)
    assert status == 2 and "not mock:" in error and "Path does not exist" not in error


def test_another_part_s_table_of_the_same_length_is_found_by_its_ids(tmp_path):
    out = tmp_path / "out"
    layout = prepared(out)
    first = write_part(layout, ["a", "b"])
    second = write_part(layout, ["d", "e"])
    swapped = out / "tracks" / f"{first}.parquet"
    swapped.write_bytes((out / "tracks" / f"{second}.parquet").read_bytes())  # 6 rows, as counted
    _, (line,) = _sound(layout)
    assert f"tracks/{first}.parquet holds other videos than its index names" in line
    assert sorted(layout.read_tracks()["video_id"].to_pylist()) == sorted("de" * 3)


def test_compaction_checks_each_video_s_rows_of_the_parts_it_rewrites(tmp_path):
    from taptr.corpus.compaction import compact

    out = tmp_path / "out"
    layout = prepared(out)
    first = write_part(layout, ["a", "b", "c"])
    write_part(layout, ["a"], run="20261208T000000000000Z")  # supersedes a in the first
    path = out / "tracks" / f"{first}.parquet"
    table = pq.read_table(path)
    ids = ["a", "a", "a", "a", "b", "b", "c", "c", "c"]  # b gave one row to a: same ends, count
    pq.write_table(table.set_column(0, "video_id", pa.array(ids, pa.string())), path)
    index, lines = _sound(layout)
    assert lines == []  # the footer cannot see it ...
    said: list[str] = []
    compact(layout, "20261209T000000000000Z", index, lambda text, **_: said.append(text))
    (line,) = said  # ... the rewrite, which reads the rows, does
    assert f"tracks/{first}.parquet does not hold the rows its index counts" in line
    assert not path.exists() and _sound(layout)[1] == []
    assert sorted(layout.read_tracks()["video_id"].to_pylist()) == ["a"] * 3
