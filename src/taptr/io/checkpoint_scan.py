"""What a checkpoint file declares, read before ``torch.load`` materialises any of it.

``torch.load(weights_only=True)`` never runs code from a file, but it trusts the sizes the
file declares: a length prefix, ``bytearray(n)``, a legacy tensor constructor
``torch.FloatTensor(n)`` or a legacy-format storage of ``numel`` elements are allocated
before anything checks that the file holds that much data. `scan_checkpoint` walks the
file's pickles without building anything (every global is replaced by an inert stand-in)
and checks, for both of PyTorch's formats:

- every length prefix fits in the bytes that follow it;
- no global that can allocate from a declared number is called (`REFUSED_CALLS`);
- the records of a zip-format file are what they really are, not what the zip's directory
  says: a stored record must store the bytes it declares inside the file, a compressed one
  is inflated (in 1 MiB pieces, nothing kept) to count its real size, and all of them
  together may inflate to at most `INFLATION_FACTOR` × the file's size (``torch.load`` reads
  every record whole, so a few megabytes of deflated zeros would otherwise become
  gigabytes);
- the tensor storages the pickle declares are held by the file (the ``data/*`` records of a
  zip-format file, each exactly its storage's size; the bytes after the pickles of a legacy
  one), and their total is within the ``checkpoint_bytes`` limit of `taptr.io.limits`;
- every tensor is a view its storage can hold (offset + Σ (size − 1) × stride < elements
  held) with non-negative sizes and strides, and the tensors' *logical* sizes (the elements
  a view shows, which a zero stride can make far larger than its storage) add up to within
  the same limit, so nothing that computes on a whole tensor can be made to allocate more.
"""

from __future__ import annotations

import io
import math
import os
import pickle
import struct
import warnings
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, cast

import torch

from taptr.io import limits
from taptr.io.safe_pickle import PickleBombError, scan_opcodes

REFUSED_CALLS = {
    "torch._utils._rebuild_qtensor": "a quantized tensor (allocated from its declared size)",
    "torch._utils._rebuild_sparse_tensor": "a sparse tensor",
    "torch._utils._rebuild_nested_tensor": "a nested tensor",
    "torch._utils._rebuild_wrapper_subclass": "a tensor subclass",
    "torch._utils._rebuild_meta_tensor_no_storage": "a tensor without data",
}
"""Calls that taptr's files never make and that allocate from declared numbers."""

LEGACY_PICKLES = 5
"""Pickles at the start of a legacy-format file: magic, version, sys info, object, keys."""

ZIP_MAGIC = b"PK\x03\x04"
PICKLE_PROTOCOL = b"\x80"
"""First byte of a pickle of protocol 2 or later, as every ``torch.save`` writes."""

INFLATION_FACTOR = 4
"""Records may inflate to at most this many times the file's size (plus `INFLATION_SLACK`):
``torch.save`` stores records uncompressed, and deflating float weights saves about 10%."""

INFLATION_SLACK = 1 << 20

REBUILD_CALLS = ("torch._utils._rebuild_tensor_v2", "torch._utils._rebuild_tensor")
"""Calls that make a tensor as a view (offset, size, stride) of a storage."""

MAX_DIMS = 64
"""Most dimensions of a tensor view (PyTorch's own limit is 64 too)."""

_LOCAL_HEADER = struct.Struct("<4s5H3L2H")
"""A zip local file header; its last two fields are the name and extra-field lengths."""

_PIECE = 1 << 20


class ScanError(ValueError):
    """The file declares more than it holds or asks for an allocation; one line, no path."""


@dataclass
class Scan:
    """What a checkpoint file declares.

    Attributes:
        globals: every global its pickles name, as ``module.name``.
        storage_bytes: bytes of tensor data it declares, in total.
        zip_format: whether it is PyTorch's zip format (else the legacy one).
        logical_bytes: bytes its tensor views show, in total (≥ storage bytes when views
            overlap or repeat elements).
    """

    globals: list[str] = field(default_factory=list)
    storage_bytes: int = 0
    zip_format: bool = True
    logical_bytes: int = 0


@dataclass(frozen=True)
class _Storage:
    """Stands in for a storage the pickle names: its record key and element count."""

    key: str
    numel: int
    element_size: int


class _Inert:
    """Stands in for every global: accepts any construction or state, builds nothing."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __setstate__(self, state: Any) -> None:
        pass

    def __setitem__(self, key: Any, value: Any) -> None:
        pass

    def append(self, item: Any) -> None:
        pass

    def extend(self, items: Any) -> None:
        pass


class _Walker(pickle.Unpickler):
    """Runs a pickle with every global inert, recording globals, calls and storages."""

    def __init__(self, stream: BinaryIO) -> None:
        super().__init__(stream)
        self.globals: list[str] = []
        self.storages: list[tuple[Any, ...]] = []
        self.logical_bytes = 0
        self._classes: dict[str, type] = {}

    def find_class(self, module: str, name: str) -> Any:
        qualified = f"{module}.{name}"
        self.globals.append(qualified)
        if qualified not in self._classes:
            check = _checker(qualified)
            walker = self

            def new(cls: type, *args: Any, **kwargs: Any) -> Any:
                check(*args)  # NEWOBJ calls __new__ only; REDUCE calls both
                if qualified in REBUILD_CALLS:
                    walker.logical_bytes += _view_bytes(args)
                return object.__new__(cls)

            def init(self: Any, *args: Any, **kwargs: Any) -> None:
                check(*args)

            self._classes[qualified] = type(name, (_Inert,), {"__new__": new, "__init__": init})
        return self._classes[qualified]

    def persistent_load(self, pid: Any) -> Any:
        if isinstance(pid, tuple) and pid and pid[0] == "storage":
            self.storages.append(pid)
            key, nbytes = _declared(pid)
            size = _element_size(pid[1])
            return _Storage(key, nbytes // size, size)
        return None


def _checker(qualified: str) -> Any:
    """A check of the arguments of a call to a global: refuses calls that allocate from numbers."""
    short = qualified.rsplit(".", 1)[-1]

    def check(*args: Any) -> None:
        if qualified in REFUSED_CALLS:
            raise ScanError(f"it builds {REFUSED_CALLS[qualified]} ({qualified})")
        if qualified.startswith("torch.") and short.endswith("Tensor"):
            raise ScanError(f"it calls the legacy tensor constructor {qualified}")
        if short in ("bytearray", "bytes") and args and not isinstance(args[0], (bytes, str)):
            raise ScanError(f"it calls {qualified} with a size")
        if qualified == "_codecs.encode" and (
            len(args) < 2 or args[1] not in ("latin1", "latin-1")
        ):
            raise ScanError("it calls _codecs.encode with a codec other than latin1")

    return check


class _Bounded:
    """A read-only view that refuses, before allocating, reads past ``end``."""

    def __init__(self, stream: BinaryIO, end: int) -> None:
        self._stream, self._end = stream, end

    def read(self, n: int = -1) -> bytes:
        left = self._end - self._stream.tell()
        if n is None or n < 0:
            n = left
        if n > left:
            raise ScanError(f"a length of {n:,} bytes where {left:,} remain")
        return self._stream.read(n)

    def readline(self, limit: int = -1) -> bytes:
        left = self._end - self._stream.tell()
        return self._stream.readline(left if limit is None or limit < 0 else min(limit, left))

    def tell(self) -> int:
        return self._stream.tell()


@dataclass
class _Walked:
    """What `_walk` found: globals, storage ids and the tensors' logical bytes."""

    globals: list[str] = field(default_factory=list)
    storages: list[tuple[Any, ...]] = field(default_factory=list)
    logical_bytes: int = 0


def _walk(stream: BinaryIO, end: int, count: int) -> _Walked:
    """Walks ``count`` consecutive pickles; leaves ``stream`` after them."""
    found = _Walked()
    for _ in range(count):
        start = stream.tell()
        try:  # lengths and memo indices first: the walker's unpickler allocates them
            scan_opcodes(stream, end - start)
        except PickleBombError as error:
            raise ScanError(str(error)) from None
        stream.seek(start)
        walker = _Walker(cast(BinaryIO, _Bounded(stream, end)))
        walker.load()
        found.globals += walker.globals
        found.storages += walker.storages
        found.logical_bytes += walker.logical_bytes
    return found


def _view_bytes(args: tuple[Any, ...]) -> int:
    """Logical bytes of ``_rebuild_tensor_v2(storage, offset, size, stride, ...)``, checked.

    Raises:
        ScanError: the view is malformed or reaches past its storage.
    """
    if len(args) < 4 or not isinstance(args[0], _Storage):
        raise ScanError("a tensor without a storage record")
    storage, offset, size, stride = args[:4]
    numbers = (
        [offset, *size, *stride] if isinstance(size, tuple) and isinstance(stride, tuple) else None
    )
    if (
        numbers is None
        or len(size) != len(stride)
        or len(size) > MAX_DIMS
        or not all(type(n) is int and 0 <= n < 2**63 for n in numbers)
    ):
        raise ScanError(f"a malformed tensor view of storage {storage.key!r}")
    numel = math.prod(size)
    reach = offset + sum((n - 1) * step for n, step in zip(size, stride, strict=True)) + 1
    if numel and reach > storage.numel:
        raise ScanError(
            f"a tensor view of storage {storage.key!r} reaches element {reach:,} of "
            f"{storage.numel:,}"
        )
    return numel * storage.element_size


def _element_size(storage_type: Any) -> int:
    """Bytes per element of a storage class named in a pickle (1 when unknown)."""
    name = getattr(storage_type, "__name__", "")
    cls = getattr(torch, name, None) if name.endswith("Storage") else None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # TypedStorage is deprecated
        dtype = getattr(cls, "dtype", None) if name != "UntypedStorage" else None
    return dtype.itemsize if isinstance(dtype, torch.dtype) else 1


def _declared(pid: tuple[Any, ...]) -> tuple[str, int]:
    """(key, bytes) of a storage id ``('storage', type, key, location, numel, ...)``."""
    if len(pid) < 5 or not isinstance(pid[4], int) or pid[4] < 0:
        raise ScanError(f"malformed storage record {pid[:3]!r}")
    return str(pid[2]), pid[4] * _element_size(pid[1])


def _inflated_size(path: Path, record: zipfile.ZipInfo, allowed: int) -> int:
    """The real size of a deflated record, counted piece by piece; stops past ``allowed``."""
    with path.open("rb") as stream:
        stream.seek(record.header_offset)
        header = stream.read(_LOCAL_HEADER.size)
        if len(header) != _LOCAL_HEADER.size or header[:4] != ZIP_MAGIC:
            raise ScanError(f"record {record.filename!r} has no local header")
        *_, name_length, extra_length = _LOCAL_HEADER.unpack(header)
        stream.seek(name_length + extra_length, os.SEEK_CUR)
        inflate = zlib.decompressobj(-zlib.MAX_WBITS)
        left, size = record.compress_size, 0
        while left and not inflate.eof:
            data = stream.read(min(left, _PIECE))
            if not data:
                break
            left -= len(data)
            while data and size <= allowed:
                size += len(inflate.decompress(data, _PIECE))
                data = inflate.unconsumed_tail
            if size > allowed:
                break
        return size + len(inflate.flush()) if size <= allowed else size


def _record_sizes(path: Path, records: list[zipfile.ZipInfo]) -> dict[str, int]:
    """Each record's real uncompressed size, checked against what the file holds.

    Raises:
        ScanError: a duplicate name, a record past the end of the file, a stored record
            whose sizes disagree, a compressed record that inflates to another size than
            declared, an unknown compression, or more than `INFLATION_FACTOR` × the file.
        taptr.io.limits.LimitError: the records exceed ``checkpoint_bytes``.
    """
    file_size = path.stat().st_size
    budget = INFLATION_FACTOR * file_size + INFLATION_SLACK
    sizes: dict[str, int] = {}
    for record in records:
        name = record.filename
        if name in sizes:
            raise ScanError(f"two records named {name!r}")
        if record.header_offset + record.compress_size > file_size:
            raise ScanError(f"record {name!r} reaches past the end of the file")
        if record.compress_type == zipfile.ZIP_STORED:
            real = record.compress_size
        elif record.compress_type == zipfile.ZIP_DEFLATED:
            real = _inflated_size(path, record, budget - sum(sizes.values()))
        else:
            raise ScanError(f"record {name!r} uses compression {record.compress_type}")
        if real != record.file_size and sum(sizes.values()) + real <= budget:
            raise ScanError(
                f"record {name!r} declares {record.file_size:,} bytes but holds {real:,}"
            )
        sizes[name] = real
        total = sum(sizes.values())
        limits.check("checkpoint_bytes", total, f"{path}: records of at least {total:,} bytes")
        if total > budget:
            raise ScanError(
                f"its compressed records inflate to more than {budget:,} bytes, "
                f"{INFLATION_FACTOR}x the file's {file_size:,} (torch.save stores records "
                "uncompressed)"
            )
    return sizes


def _scan_zip(path: Path) -> Scan:
    with zipfile.ZipFile(path) as archive:
        records = archive.infolist()
        sizes = _record_sizes(path, records)
        pickles = [r for r in records if r.filename.endswith("data.pkl")]
        if len(pickles) != 1:
            raise ScanError(f"{len(pickles)} data.pkl records, expected 1")
        prefix = pickles[0].filename[: -len("data.pkl")]
        data = archive.read(pickles[0])
    held = {
        name[len(prefix) + len("data/") :]: size
        for name, size in sizes.items()
        if name.startswith(prefix + "data/")
    }
    walker = _walk(io.BytesIO(data), len(data), 1)
    scan = Scan(walker.globals, logical_bytes=walker.logical_bytes)
    for key, nbytes in dict(map(_declared, walker.storages)).items():
        # torch.load reads a storage's whole record: it must be the storage's size exactly
        if nbytes != held.get(key, -1):
            raise ScanError(
                f"tensor storage {key!r} declares {nbytes:,} bytes but its record holds "
                f"{max(held.get(key, 0), 0):,}"
            )
        scan.storage_bytes += nbytes
    return scan


def _scan_legacy(path: Path) -> Scan:
    size = path.stat().st_size
    with path.open("rb") as stream:
        walker = _walk(stream, size, LEGACY_PICKLES)
        held = size - stream.tell()
    declared = dict(map(_declared, walker.storages))
    # each storage follows the pickles as an 8-byte element count and its data
    needed = sum(declared.values()) + 8 * len(declared)
    if needed > held:
        raise ScanError(
            f"its pickles declare {needed:,} bytes of tensor data but {held:,} bytes follow them"
        )
    return Scan(walker.globals, needed, zip_format=False, logical_bytes=walker.logical_bytes)


def scan_checkpoint(path: str | os.PathLike[str]) -> Scan:
    """Checks what a checkpoint file declares against what it holds and the size limit.

    Raises:
        taptr.io.limits.LimitError: the file or its tensors exceed ``checkpoint_bytes``.
        ScanError: it declares data it does not hold, calls an allocating global, or is
            not a PyTorch file (the message does not name the file; the caller adds it).
    """
    path = Path(path)
    size = path.stat().st_size
    limits.check("checkpoint_bytes", size, f"{path}: {size:,} bytes")
    with path.open("rb") as stream:
        magic = stream.read(len(ZIP_MAGIC))
    if not magic:
        raise ScanError("the file is empty (0 bytes): an incomplete download or copy")
    if magic != ZIP_MAGIC and magic[:1] != PICKLE_PROTOCOL:
        raise ScanError(
            "not a PyTorch checkpoint: neither a zip archive (torch.save) nor a pickle "
            "(torch.save before PyTorch 1.6)"
        )
    try:
        scan = _scan_zip(path) if magic == ZIP_MAGIC else _scan_legacy(path)
    except (limits.LimitError, ScanError):
        raise
    except zipfile.BadZipFile as error:
        raise ScanError(f"a damaged zip archive ({error})") from None
    except (
        pickle.UnpicklingError,
        EOFError,
        ValueError,
        TypeError,
        AttributeError,
        IndexError,
        KeyError,
        OverflowError,
        RecursionError,
        MemoryError,
        OSError,
        NotImplementedError,
    ) as error:
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise ScanError(f"not a PyTorch checkpoint ({reason[:200]})") from None
    what = f"{path}: tensor views of {scan.logical_bytes:,} bytes"
    limits.check("checkpoint_bytes", scan.logical_bytes, what)
    return scan
