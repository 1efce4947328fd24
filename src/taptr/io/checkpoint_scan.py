"""What a checkpoint file declares, read before ``torch.load`` materialises any of it.

``torch.load(weights_only=True)`` never runs code from a file, but it trusts the sizes the
file declares: a length prefix, ``bytearray(n)``, a legacy tensor constructor
``torch.FloatTensor(n)`` or a legacy-format storage of ``numel`` elements are allocated
before anything checks that the file holds that much data. `scan_checkpoint` walks the
file's pickles without building anything (every global is replaced by an inert stand-in)
and checks, for both of PyTorch's formats:

- every length prefix fits in the bytes that follow it;
- no global that can allocate from a declared number is called (`REFUSED_CALLS`);
- the tensor storages the pickle declares are held by the file (the ``data/*`` records of a
  zip-format file, the bytes after the pickles of a legacy one), and their total is within
  the ``checkpoint_bytes`` limit of `taptr.io.limits`.
"""

from __future__ import annotations

import io
import os
import pickle
import warnings
import zipfile
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


class ScanError(ValueError):
    """The file declares more than it holds or asks for an allocation; one line, no path."""


@dataclass
class Scan:
    """What a checkpoint file declares.

    Attributes:
        globals: every global its pickles name, as ``module.name``.
        storage_bytes: bytes of tensor data it declares, in total.
        zip_format: whether it is PyTorch's zip format (else the legacy one).
    """

    globals: list[str] = field(default_factory=list)
    storage_bytes: int = 0
    zip_format: bool = True


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
        self._classes: dict[str, type] = {}

    def find_class(self, module: str, name: str) -> Any:
        qualified = f"{module}.{name}"
        self.globals.append(qualified)
        if qualified not in self._classes:
            check = _checker(qualified)

            def new(cls: type, *args: Any, **kwargs: Any) -> Any:
                check(*args)  # NEWOBJ calls __new__ only
                return object.__new__(cls)

            def init(self: Any, *args: Any, **kwargs: Any) -> None:
                check(*args)

            self._classes[qualified] = type(name, (_Inert,), {"__new__": new, "__init__": init})
        return self._classes[qualified]

    def persistent_load(self, pid: Any) -> Any:
        if isinstance(pid, tuple) and pid and pid[0] == "storage":
            self.storages.append(pid)
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


def _walk(stream: BinaryIO, end: int, count: int) -> tuple[list[str], list[tuple[Any, ...]]]:
    """Globals and storage ids of ``count`` consecutive pickles; leaves ``stream`` after them."""
    names: list[str] = []
    storages: list[tuple[Any, ...]] = []
    for _ in range(count):
        start = stream.tell()
        try:  # lengths and memo indices first: the walker's unpickler allocates them
            scan_opcodes(stream, end - start)
        except PickleBombError as error:
            raise ScanError(str(error)) from None
        stream.seek(start)
        walker = _Walker(cast(BinaryIO, _Bounded(stream, end)))
        walker.load()
        names += walker.globals
        storages += walker.storages
    return names, storages


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


def _scan_zip(path: Path) -> Scan:
    with zipfile.ZipFile(path) as archive:
        records = archive.infolist()
        total = sum(r.file_size for r in records)
        limits.check("checkpoint_bytes", total, f"{path}: records of {total:,} bytes")
        pickles = [r for r in records if r.filename.endswith("data.pkl")]
        if len(pickles) != 1:
            raise ScanError(f"{len(pickles)} data.pkl records, expected 1")
        prefix = pickles[0].filename[: -len("data.pkl")]
        data = archive.read(pickles[0])
    held = {
        r.filename[len(prefix) + len("data/") :]: r.file_size
        for r in records
        if r.filename.startswith(prefix + "data/")
    }
    names, storages = _walk(io.BytesIO(data), len(data), 1)
    scan = Scan(names)
    for key, nbytes in dict(map(_declared, storages)).items():
        if nbytes > held.get(key, -1):
            raise ScanError(
                f"tensor storage {key!r} declares {nbytes:,} bytes but its record holds "
                f"{max(held.get(key, 0), 0):,}"
            )
        scan.storage_bytes += nbytes
    return scan


def _scan_legacy(path: Path) -> Scan:
    size = path.stat().st_size
    with path.open("rb") as stream:
        names, storages = _walk(stream, size, LEGACY_PICKLES)
        held = size - stream.tell()
    declared = dict(map(_declared, storages))
    # each storage follows the pickles as an 8-byte element count and its data
    needed = sum(declared.values()) + 8 * len(declared)
    if needed > held:
        raise ScanError(
            f"its pickles declare {needed:,} bytes of tensor data but {held:,} bytes follow them"
        )
    return Scan(names, needed, zip_format=False)


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
    try:
        return _scan_zip(path) if magic == ZIP_MAGIC else _scan_legacy(path)
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
        raise ScanError(f"not a PyTorch checkpoint ({reason})") from None
