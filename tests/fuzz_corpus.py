"""Fuzz categories of issue 51: a corpus's output folder tampered with by others.

Each input builds a small OUT (three parts, a failure among them) beside a ``victim``
folder, tampers with it, and runs what a rerun runs before any actor: the folder check,
the sound index (damaged parts removed, copies mended), the plan, both compactions and
the dataset read back. A tampering is one of:

- an index file's cells (``part`` naming ``..`` paths, absolute paths, another part,
  any text; ids, statuses, counts, nulls), its column types, its bytes (cut, replaced,
  emptied), its rows (doubled, another part's), or the file copied under another name;
- a part's tracks or failures file: another table of the same length, a column gone,
  another schema version, cut, replaced, removed, or another part's file in its place;
- the marker's bytes, or names planted in OUT: links (to the victim, dangling), folders
  named as parts, files named as nothing the layout makes.

The oracle: no path outside OUT is made (`tests.corpus_helpers.touched_paths`) and the
victim's files are unchanged; the check refuses (a clean ValueError) or the run goes on
with a dataset holding exactly what the sound index counts, each video's rows once, every
line said on one line, and a second look finding nothing left to say.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hypothesis import strategies as st

from tests.corpus_helpers import RUN, inside, prepared, snapshot, touched_paths, write_part
from tests.fuzz_hostile import SilentError

NAMES = ["a", "b", "c", "d", "e"]
"""The corpus's videos: parts hold a, b (done) and c (failed); d, e; a again, newer."""

HOSTILE_TEXT = st.sampled_from(
    [
        "../../victim/precious", "../victim", "/etc/passwd", "/tmp", "..", ".", "",
        "part-20261207T000000000000Z-0badc0de-000000", "tracks/../../victim",
        "part-20261207T000000000000Z-0badc0de-000000/../../victim", "a\x00b", "\n",
        "C:\\victim", "file:///victim", "s3://bucket/x",
    ]
) | st.text(max_size=40)  # fmt: skip
"""Values a hostile index holds where a name is expected."""

CELLS = {
    "video_id": HOSTILE_TEXT,
    "settings_digest": HOSTILE_TEXT,
    "status": st.sampled_from(["done", "failed", "DONE", ""]) | st.text(max_size=8),
    "rows": st.integers(-(2**31), 2**31 - 1),
    "run": HOSTILE_TEXT,
    "part": HOSTILE_TEXT,
}


@st.composite
def index_tamperings(draw: st.DrawFn) -> tuple:
    """One tampering of an index file (see the module docstring)."""
    part = draw(st.integers(0, 2))
    kind = draw(st.sampled_from(["cells", "nulls", "types", "bytes", "rows", "copy"]))
    if kind == "cells":
        column = draw(st.sampled_from(sorted(CELLS)))
        return ("cells", part, column, draw(CELLS[column]), draw(st.booleans()))
    if kind == "nulls":
        return ("nulls", part, draw(st.sampled_from(sorted(CELLS))))
    if kind == "types":
        return ("types", part, draw(st.sampled_from(sorted(CELLS))))
    if kind == "bytes":
        return ("bytes", part, draw(st.integers(0, 4000)), draw(st.binary(max_size=64)))
    if kind == "rows":
        return ("rows", part, draw(st.sampled_from(["double", "other", "empty", "reverse"])))
    return ("copy", part, draw(st.sampled_from(["fresh-name", "over-another"])))


@st.composite
def part_tamperings(draw: st.DrawFn) -> tuple:
    """One tampering of a tracks or failures file."""
    part = draw(st.integers(0, 2))
    folder = draw(st.sampled_from(["tracks", "failures"]))
    kind = draw(
        st.sampled_from(["forged", "dropped-column", "version", "bytes", "removed", "swapped"])
    )
    return (kind, part, folder, draw(st.integers(0, 4000)), draw(st.binary(max_size=64)))


@st.composite
def folder_tamperings(draw: st.DrawFn) -> tuple:
    """The marker's bytes, or a name planted in OUT."""
    kind = draw(st.sampled_from(["marker", "link", "dangling", "folder", "foreign"]))
    where = draw(st.sampled_from(["", "tracks", "failures", "_index", "_staging"]))
    marker = draw(
        st.sampled_from([b'{"layout": 1e999}', b'{"layout": "2"}', b'{"layout": 3}', b"[", b"null"])
        | st.binary(max_size=64)
        | st.builds(lambda v: json.dumps({"layout": v}).encode(), st.floats() | st.integers())
    )
    return (kind, where, marker)


def _part_name(index: int) -> str:
    return f"part-{RUN}-0000000{index}-000000"


def _build(root: Path) -> tuple[Any, Path, list[str]]:
    """OUT with three parts, and a victim folder beside it; returns (layout, out, parts)."""
    out = root / "shared" / "out"
    layout = prepared(out)
    parts = [
        write_part(layout, ["a", "b"], failed=("c",)),
        write_part(layout, ["d", "e"]),
        write_part(layout, ["a"], run="20261208T000000000000Z"),
    ]
    victim = root / "victim"
    victim.mkdir()
    (victim / "precious.parquet").write_bytes((out / "tracks" / f"{parts[1]}.parquet").read_bytes())
    (victim / "passwd").write_text("root:x:0:0")
    return layout, out, parts


def _tamper_index(out: Path, parts: list[str], case: tuple) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    kind, index = case[0], case[1]
    path = out / "_index" / f"{parts[index]}.parquet"
    table = pq.read_table(path)
    if kind == "cells":
        _, _, column, value, every = case
        values = table[column].to_pylist()
        values = [value] * len(values) if every else [value, *values[1:]]
        field = table.schema.field(column)
        table = table.set_column(
            table.schema.get_field_index(column), field, pa.array(values, field.type)
        )
    elif kind == "nulls":
        column = case[2]
        field = table.schema.field(column)
        nulls = pa.nulls(len(table), field.type)
        table = table.set_column(table.schema.get_field_index(column), field, nulls)
    elif kind == "types":
        column = case[2]
        values = pa.array([str(v) for v in table[column].to_pylist()], pa.string())
        if table.schema.field(column).type == pa.string():
            values = pa.array(range(len(table)), pa.int64())
        table = table.set_column(table.schema.get_field_index(column), column, values)
    elif kind == "bytes":
        data = path.read_bytes()
        path.write_bytes(data[: case[2]] + case[3])
        return
    elif kind == "rows":
        other = pq.read_table(out / "_index" / f"{parts[(index + 1) % 3]}.parquet")
        table = {
            "double": pa.concat_tables([table, table]),
            "other": pa.concat_tables([table, other]),
            "empty": table.slice(0, 0),
            "reverse": table.take(list(range(len(table)))[::-1]),
        }[case[2]]
    else:
        target = _part_name(7) if case[2] == "fresh-name" else parts[(index + 1) % 3]
        (out / "_index" / f"{target}.parquet").write_bytes(path.read_bytes())
        return
    pq.write_table(table, path)


def _tamper_part(out: Path, parts: list[str], case: tuple) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    kind, index, folder, cut, junk = case
    path = out / folder / f"{parts[index]}.parquet"
    if not path.exists():
        path.write_bytes(junk)  # a file the index does not name, planted
        return
    table = pq.read_table(path)
    if kind == "forged":
        pq.write_table(
            pa.table({"video_id": ["forged"] * len(table), "score": [1.0] * len(table)}), path
        )
    elif kind == "dropped-column":
        pq.write_table(table.drop_columns([table.column_names[-1]]), path)
    elif kind == "version":
        pq.write_table(table.replace_schema_metadata({"taptr.schema": "1"}), path)
    elif kind == "bytes":
        path.write_bytes(path.read_bytes()[:cut] + junk)
    elif kind == "removed":
        path.unlink()
    else:
        other = out / folder / f"{parts[(index + 1) % 3]}.parquet"
        if other.exists():
            path.write_bytes(other.read_bytes())


def _tamper_folder(root: Path, out: Path, case: tuple) -> None:
    kind, where, marker = case
    folder = out / where if where else out
    folder.mkdir(exist_ok=True)
    name = f"{_part_name(8)}.parquet" if where not in ("", "_staging") else "_corpus.json.bak"
    if kind == "marker":
        (out / "_corpus.json").write_bytes(marker)
    elif kind == "link":
        target = folder / name
        if target.exists():
            target.unlink()
        target.symlink_to(root / "victim" / "precious.parquet")
    elif kind == "dangling":
        (folder / name).symlink_to(root / "victim" / "missing")
    elif kind == "folder":
        (folder / name).mkdir()
    else:
        (folder / "notes.txt").write_text("mine")


def _run_over(tamper: Callable[[Path, Path, list[str]], None]) -> None:
    """Builds OUT, tampers with it, runs a rerun's steps, and checks the oracle."""
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        layout, out, parts = _build(root)
        tamper(root, out, parts)
        before = snapshot(root / "victim")
        with touched_paths() as touched:
            try:
                _rerun(layout, out)
            finally:
                outside = [path for path in touched if not inside(path, out)]
                if outside:
                    raise SilentError(f"paths outside OUT were made: {outside[:3]}")
                if snapshot(root / "victim") != before:
                    raise SilentError("files outside OUT changed")


def _rerun(layout: Any, out: Path) -> None:
    import pyarrow.compute as pc

    from taptr.corpus.compaction import compact
    from taptr.corpus.damage import sound_index
    from taptr.corpus.inputs import CorpusVideo, QuerySpec
    from taptr.corpus.pipeline import CorpusOptions, plan
    from taptr.corpus.progress import Summary

    layout.check()  # a ValueError here is a clean refusal before any work
    lines: list[str] = []
    index = sound_index(layout, lambda text, **_: lines.append(text))
    if any("\n" in line or "\r" in line for line in lines):
        raise SilentError(f"a line of several lines: {lines!r}")
    videos = [CorpusVideo(name, "x.mp4", QuerySpec(grid=2), "d" * 16) for name in NAMES]
    plan(videos, index, CorpusOptions(out=str(out)), Summary(len(NAMES)))
    compact(layout, "20261209T000000000000Z", index)
    compact(layout, "20261209T000000000000Z")
    tracks = layout.read_tracks()
    again: list[str] = []
    sound = sound_index(layout, lambda text, **_: again.append(text))
    if again:
        raise SilentError(f"a second look still finds damage: {again}")
    done = sound.filter(pc.equal(sound["status"], "done"))
    if tracks.num_rows != (pc.sum(done["rows"]).as_py() or 0):
        raise SilentError(f"the dataset holds {tracks.num_rows} rows, the index counts otherwise")
    ids = tracks["video_id"].to_pylist()
    if any(ids.count(video) > 3 for video in set(ids)):
        raise SilentError("a video's rows are in the dataset twice")
    for entry in os.scandir(out / "tracks"):
        if entry.is_symlink():
            raise SilentError("a link survived in OUT")


def tamper_index(case: tuple) -> None:
    """A rerun over OUT with one index file tampered with."""
    _run_over(lambda root, out, parts: _tamper_index(out, parts, case))


def tamper_part(case: tuple) -> None:
    """A rerun over OUT with one tracks or failures file tampered with."""
    _run_over(lambda root, out, parts: _tamper_part(out, parts, case))


def tamper_folder(case: tuple) -> None:
    """A rerun over OUT with its marker or its names tampered with."""
    _run_over(lambda root, out, parts: _tamper_folder(root, out, case))


CATEGORIES: dict[str, tuple[Any, Callable[[Any], Any]]] = {
    "corpus OUT, tampered index (names with .., absolute paths, copies)": (
        index_tamperings(),
        tamper_index,
    ),
    "corpus OUT, tampered tracks and failures parts": (part_tamperings(), tamper_part),
    "corpus OUT, tampered marker and planted links": (folder_tamperings(), tamper_folder),
}
"""The categories of this module, added to `tests.fuzz_targets.CATEGORIES`."""
