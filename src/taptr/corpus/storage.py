"""Where a corpus's results live: a local folder or any filesystem pyarrow opens by URI.

``OUT`` is a local path (a folder every node mounts, on a cluster) or a URI such as
``s3://bucket/prefix``, ``gs://bucket/prefix`` or ``hdfs://...``; a URI's own parameters
(``?endpoint_override=...&scheme=http`` for an S3-compatible store) and the usual
credentials of its store (``AWS_*`` variables, instance roles) apply as pyarrow reads them.

A file is published whole or not at all without asking the store for an atomic rename:
on a local filesystem it is written under ``_staging/`` and renamed into place (same
filesystem), on an object store it is uploaded in one request, which the store makes
visible only once complete. Nothing here lists more than one folder at a time.
"""

from __future__ import annotations

import os
import re
import stat
import uuid
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import pyarrow as pa
    import pyarrow.fs as pafs

URI = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*://")
"""A URI's scheme: what tells ``s3://bucket/out`` from a local path."""

STAGING = "_staging"
"""The folder where local files are written before their rename."""


@dataclass(frozen=True)
class Entry:
    """One name in a folder.

    Attributes:
        name: the name inside the folder; kind: ``file``, ``folder``, ``link`` or ``other``.
        size: bytes (files only, else 0).
    """

    name: str
    kind: str
    size: int = 0


class Storage:
    """A folder of a pyarrow filesystem, with whole-or-nothing writes.

    Args:
        out: a local path or a URI that `pyarrow.fs.FileSystem.from_uri` opens.

    Raises:
        ValueError: a URI pyarrow cannot open (its message, in one line).
    """

    def __init__(self, out: str) -> None:
        import pyarrow.fs as pafs

        self.out = out
        if URI.match(out) and not out.startswith("file://"):
            try:
                self.fs, root = pafs.FileSystem.from_uri(out)
            except (ValueError, OSError) as error:  # ArrowInvalid is a ValueError
                raise ValueError(
                    f"cannot open --out {out}: {' '.join(str(error).split())}"
                ) from None
            self.local = False
        else:
            self.fs = pafs.LocalFileSystem()
            root = os.path.abspath(out.removeprefix("file://"))
            self.local = True
        self.root = root.rstrip("/")

    def __reduce__(self) -> tuple[type[Storage], tuple[str]]:
        # actors open their own filesystem from the same text (credentials are theirs)
        return (Storage, (self.out,))

    def path(self, relative: str) -> str:
        """The filesystem path of ``relative`` (``tracks/part-....parquet``)."""
        return f"{self.root}/{relative}" if relative else self.root

    def make_folder(self, relative: str) -> None:
        """Creates a folder (object stores have none: nothing to do there)."""
        if self.local:
            os.makedirs(self.path(relative), exist_ok=True)

    def list(self, relative: str) -> list[Entry]:
        """The names in a folder, links told apart (an empty list when it does not exist)."""
        if self.local:
            return _local_entries(self.path(relative))
        import pyarrow.fs as pafs

        selector = pafs.FileSelector(self.path(relative), allow_not_found=True)
        return [_entry(info) for info in self.fs.get_file_info(selector)]

    def exists(self, relative: str) -> bool:
        """Whether a file or folder is there."""
        import pyarrow.fs as pafs

        return self.fs.get_file_info(self.path(relative)).type != pafs.FileType.NotFound

    def write(self, relative: str, data: bytes | pa.Buffer) -> None:
        """Publishes ``data`` at ``relative``, whole or not at all (see the module)."""
        if not self.local:
            with self.fs.open_output_stream(self.path(relative)) as stream:
                stream.write(data)
            return
        staged = self.path(f"{STAGING}/{uuid.uuid4().hex}.tmp")
        os.makedirs(os.path.dirname(staged), exist_ok=True)
        os.makedirs(os.path.dirname(self.path(relative)), exist_ok=True)
        try:
            with open(staged, "wb") as stream:
                stream.write(data)
                stream.flush()
                os.fsync(stream.fileno())  # the rename must not publish unwritten blocks
            os.replace(staged, self.path(relative))
        finally:
            if os.path.lexists(staged):
                os.unlink(staged)

    def read(self, relative: str, limit: int) -> bytes:
        """A file's bytes.

        Raises:
            ValueError: it is larger than ``limit`` bytes.
        """
        with self.fs.open_input_file(self.path(relative)) as stream:
            if stream.size() > limit:
                raise ValueError(f"{self.path(relative)} is larger than {limit} bytes")
            return stream.read()

    def delete(self, relative: str) -> None:
        """Removes a file; a missing one is no error."""
        import pyarrow.fs as pafs

        if self.fs.get_file_info(self.path(relative)).type == pafs.FileType.NotFound:
            return
        self.fs.delete_file(self.path(relative))

    def delete_folder(self, relative: str) -> None:
        """Removes a folder and what it holds; a missing one is no error."""
        import pyarrow.fs as pafs

        if self.fs.get_file_info(self.path(relative)).type == pafs.FileType.Directory:
            self.fs.delete_dir(self.path(relative))


def _local_entries(folder: str) -> list[Entry]:
    try:
        scanned = list(os.scandir(folder))
    except FileNotFoundError:
        return []
    entries = []
    for item in scanned:
        mode = item.stat(follow_symlinks=False).st_mode
        kind = (
            "link"
            if stat.S_ISLNK(mode)
            else "folder"
            if stat.S_ISDIR(mode)
            else "file"
            if stat.S_ISREG(mode)
            else "other"
        )
        entries.append(Entry(item.name, kind, item.stat(follow_symlinks=False).st_size))
    return entries


def _entry(info: pafs.FileInfo) -> Entry:
    import pyarrow.fs as pafs

    kinds = {pafs.FileType.File: "file", pafs.FileType.Directory: "folder"}
    return Entry(info.base_name, kinds.get(info.type, "other"), info.size or 0)
