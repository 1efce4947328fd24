"""Where a corpus's results live: a local folder or a filesystem pyarrow opens by URI.

``OUT`` is a local path (a folder every node mounts, on a cluster) or a URI of one of
`SCHEMES`: ``file:///abs/path``, ``s3://bucket/prefix``, ``gs://bucket/prefix``,
``hdfs://...``, ``abfs://...``. URIs are parsed by pyarrow alone
(`pyarrow.fs.FileSystem.from_uri`: percent-escapes decoded, a host in a ``file:`` URI or a
relative ``file:`` path refused); a URI's own parameters (``?endpoint_override=...&scheme=
http`` for an S3-compatible store) and the usual credentials of its store (``AWS_*``
variables, instance roles) apply as pyarrow reads them.

A file is published whole or not at all without asking the store for an atomic rename:
on a local filesystem it is written under ``_staging/`` and renamed into place (same
filesystem), on an object store it is uploaded in one request, which the store makes
visible only once complete. Nothing here lists more than one folder at a time.

Every path is made here from OUT and a relative name whose parts are plain names (no
``..``, no leading ``/``): nothing outside OUT is ever opened, renamed or removed. A store
that cannot be reached or refuses a request (no such bucket, no credentials) is a
`StoreError`: its own message, in one line.
"""

from __future__ import annotations

import contextlib
import os
import re
import stat
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import pyarrow as pa
    import pyarrow.fs as pafs
    import pyarrow.parquet as pq

SCHEMES = ("file", "s3", "gs", "gcs", "hdfs", "viewfs", "abfs", "abfss")
"""URI schemes of the filesystems a corpus is written to (pyarrow's real ones; its
``mock:`` filesystem lives in one process's memory and would lose the results)."""

SCHEME = re.compile(r"^(?P<scheme>[A-Za-z][A-Za-z0-9+.-]+):(?P<slashes>//)?")
"""A URI's scheme (two letters or more: ``C:`` is a drive, not a scheme)."""

STAGING = "_staging"
"""The folder where local files are written before their rename."""


class StoreError(ValueError):
    """The store holding OUT cannot be reached or refuses a request (its message, one line)."""


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


def uri_scheme(out: str) -> str | None:
    """The scheme of ``out`` when it is written as a URI, else None (a local path).

    ``scheme://...`` is a URI whatever the scheme, and so is ``file:...`` or ``s3:...``
    without the slashes (pyarrow then says what is wrong with it); ``results:v2`` is a
    local folder.
    """
    match = SCHEME.match(out)
    if match is None:
        return None
    scheme = match["scheme"]
    return scheme if match["slashes"] or scheme.lower() in SCHEMES else None


def check_scheme(out: str) -> None:
    """Refuses a URI of a scheme not in `SCHEMES`, without opening anything.

    Raises:
        ValueError: names the scheme and those a corpus is written to.
    """
    scheme = uri_scheme(out)
    if scheme is not None and scheme not in SCHEMES:
        known = ", ".join(name + ":" for name in SCHEMES[:-1]) + f" or {SCHEMES[-1]}:"
        raise ValueError(
            f"cannot write to {out}: the output is a local folder or a URI of {known}, "
            f"not {scheme}:"
        )


class Storage:
    """A folder of a pyarrow filesystem, with whole-or-nothing writes.

    Args:
        out: a local path or a URI of one of `SCHEMES`.

    Raises:
        ValueError: a URI of another scheme, or one pyarrow refuses (its message, one line).
    """

    def __init__(self, out: str) -> None:
        import pyarrow.fs as pafs

        self.out = out
        scheme = uri_scheme(out)
        if scheme is None:
            self.fs: pafs.FileSystem = pafs.LocalFileSystem()
            root = os.path.abspath(out)
        else:
            self.fs, root = _open_uri(out, scheme)
        self.local = isinstance(self.fs, pafs.LocalFileSystem)
        self.root = root.rstrip("/") or "/"

    def __reduce__(self) -> tuple[type[Storage], tuple[str]]:
        # actors open their own filesystem from the same text (credentials are theirs)
        return (Storage, (self.out,))

    def path(self, relative: str) -> str:
        """The filesystem path of ``relative`` (``tracks/part-....parquet``) inside OUT.

        Raises:
            ValueError: ``relative`` is not made of plain names (``..``, an absolute path).
        """
        if not relative:
            return self.root
        if any(part in ("", ".", "..") or "\0" in part for part in relative.split("/")):
            raise ValueError(f"{relative!r} is not a name inside {self.out}")
        return f"{self.root}/{relative}"

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
        with self.answering():
            return [_entry(info) for info in self.fs.get_file_info(selector)]

    def exists(self, relative: str) -> bool:
        """Whether a file or folder is there."""
        import pyarrow.fs as pafs

        with self.answering():
            return self.fs.get_file_info(self.path(relative)).type != pafs.FileType.NotFound

    def write(self, relative: str, data: bytes | pa.Buffer) -> None:
        """Publishes ``data`` at ``relative``, whole or not at all (see the module)."""
        target = self.path(relative)
        if not self.local:
            with self.answering(), self.fs.open_output_stream(target) as stream:
                stream.write(data)
            return
        staged = self.path(f"{STAGING}/{uuid.uuid4().hex}.tmp")
        os.makedirs(os.path.dirname(staged), exist_ok=True)
        os.makedirs(os.path.dirname(target), exist_ok=True)
        try:
            with open(staged, "wb") as stream:
                stream.write(data)
                stream.flush()
                os.fsync(stream.fileno())  # the rename must not publish unwritten blocks
            os.replace(staged, target)
        finally:
            if os.path.lexists(staged):
                os.unlink(staged)

    def read(self, relative: str, limit: int) -> bytes:
        """A file's bytes.

        Raises:
            ValueError: it is larger than ``limit`` bytes.
        """
        with self.answering(), self.fs.open_input_file(self.path(relative)) as stream:
            if stream.size() > limit:
                raise ValueError(f"{self.path(relative)} is larger than {limit} bytes")
            return stream.read()

    def footer(self, relative: str) -> pq.FileMetaData:
        """A Parquet file's footer: its rows, schema and metadata, without its data.

        Raises:
            FileNotFoundError: it is not there; ValueError: not a Parquet file
            (``ArrowInvalid``); StoreError: the store did not answer.
        """
        import pyarrow.parquet as pq

        with self.answering(), self.fs.open_input_file(self.path(relative)) as stream:
            return pq.read_metadata(stream)

    def read_table(self, relative: str) -> pa.Table:
        """A Parquet file's rows (errors as `footer`)."""
        import pyarrow.parquet as pq

        with self.answering(), self.fs.open_input_file(self.path(relative)) as stream:
            return pq.read_table(stream)

    def delete(self, relative: str) -> None:
        """Removes a file; a missing one is no error."""
        import pyarrow.fs as pafs

        path = self.path(relative)
        with self.answering():
            if self.fs.get_file_info(path).type == pafs.FileType.NotFound:
                return
            self.fs.delete_file(path)

    def delete_folder(self, relative: str) -> None:
        """Removes a folder and what it holds; a missing one is no error."""
        import pyarrow.fs as pafs

        path = self.path(relative)
        with self.answering():
            if self.fs.get_file_info(path).type == pafs.FileType.Directory:
                self.fs.delete_dir(path)

    @contextlib.contextmanager
    def answering(self) -> Iterator[None]:
        """Turns a store's own failure (not reached, refused) into a one-line `StoreError`.

        A missing file stays a FileNotFoundError and an unreadable one a ValueError
        (``ArrowInvalid``): those are about the file, not the store. A local folder's
        errors are left as they are (a full disk, a permission: the command says them).
        """
        try:
            yield
        except (FileNotFoundError, ValueError):
            raise
        except OSError as error:
            if self.local:
                raise
            raise StoreError(
                f"cannot use {self.out}: {_clipped(error)}{credentials_hint(self.out)}"
            ) from None


AWS_CREDENTIAL_VARIABLES = (
    "AWS_ACCESS_KEY_ID",
    "AWS_PROFILE",
    "AWS_WEB_IDENTITY_TOKEN_FILE",
    "AWS_CONTAINER_CREDENTIALS_RELATIVE_URI",
    "AWS_CONTAINER_CREDENTIALS_FULL_URI",
)
"""Where the AWS SDK finds credentials before its files and the machine's metadata server."""


def credentials_hint(out: str) -> str:
    """A clause naming the missing credentials of an S3 URI, or "" where some may exist.

    Without credentials the AWS SDK asks the machine's metadata server, then reports a bare
    ``INTERNAL_FAILURE`` that never says credentials were missing.
    """
    if not out.lower().startswith("s3:") or "anonymous=true" in out.lower():
        return ""
    files = (
        os.environ.get("AWS_SHARED_CREDENTIALS_FILE", "~/.aws/credentials"),
        os.environ.get("AWS_CONFIG_FILE", "~/.aws/config"),
    )
    if any(os.environ.get(name) for name in AWS_CREDENTIAL_VARIABLES) or any(
        os.path.isfile(os.path.expanduser(path)) for path in files
    ):
        return ""
    return (
        " (no AWS credentials were found in the environment or ~/.aws: set AWS_ACCESS_KEY_ID "
        "and AWS_SECRET_ACCESS_KEY, or add anonymous=true to the URI for a public bucket)"
    )


def _open_uri(out: str, scheme: str) -> tuple[pafs.FileSystem, str]:
    """(filesystem, root path) of a URI, parsed by pyarrow alone.

    Raises:
        ValueError: an unsupported scheme, or a URI pyarrow refuses (one line).
    """
    import pyarrow.fs as pafs

    check_scheme(out)
    try:
        return pafs.FileSystem.from_uri(out)
    except (ValueError, OSError) as error:  # ArrowInvalid is a ValueError
        raise ValueError(f"cannot open {out}: {_clipped(error)}") from None


def _clipped(error: BaseException, limit: int = 300) -> str:
    """The first line of an error, at most ``limit`` characters (a JVM search is long)."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    text = lines[0] if lines else type(error).__name__
    return text if len(text) <= limit else text[:limit] + " ..."


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
