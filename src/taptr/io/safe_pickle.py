"""A restricted, size-bounded unpickler for dataset files (TAP-Vid pickles; `.npy`: safe_npy).

These files are pickles of numpy arrays in plain containers. Unpickling them with
``pickle.load`` or ``np.load(allow_pickle=True)`` would run any code a crafted file asks
for; this reader rebuilds numpy arrays, numpy scalars and builtin containers only, and
refuses everything else with an error naming the object.

A pickle can also ask for memory it does not hold: a length prefix larger than the file,
``bytearray(12 * 2**30)``, an array whose declared shape is far larger than its data, or the
same small object copied thousands of times. Before anything is unpickled, every opcode is
scanned so that no length prefix reaches past the end of the file (CPython allocates the
declared length before reading it); while unpickling, every allocation an allowed callable
makes is charged to a budget of a few times the file's size (`BUDGET_FACTOR`), so the
memory a file can ask for is proportional to the file itself. The file's size is bounded
by `taptr.io.limits` (``file_bytes``).
"""

from __future__ import annotations

import codecs
import collections
import math
import os
import pickle
import pickletools
from pathlib import Path
from typing import Any, BinaryIO, cast

import numpy as np

try:  # numpy >= 2 moved the pickle helpers to numpy._core
    from numpy._core.multiarray import scalar as _numpy_scalar
except ImportError:  # pragma: no cover - numpy 1.x
    from numpy.core.multiarray import scalar as _numpy_scalar  # type: ignore[no-redef]

from taptr.io import limits
from taptr.io.file_kind import kind, require_file
from taptr.io.nesting import check_nesting

BUDGET_FACTOR = 3
"""Bytes a pickle may allocate per byte of file (protocol 2 copies array data twice)."""

BUDGET_SLACK = 1 << 20
"""Bytes every pickle may allocate beyond `BUDGET_FACTOR` × its size (small object arrays)."""

_NUMPY_CORE = ("numpy.core", "numpy._core")
_BUILTINS = ("builtins", "__builtin__")  # protocols 0-2 name them as Python 2 did
ALLOWED = frozenset(
    {
        *((f"{core}.multiarray", "_reconstruct") for core in _NUMPY_CORE),
        *((f"{core}.multiarray", "scalar") for core in _NUMPY_CORE),
        *((f"{core}.numeric", "_frombuffer") for core in _NUMPY_CORE),  # protocol 5
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
        ("_codecs", "encode"),  # protocol-2 pickles encode raw array bytes through it
        ("collections", "OrderedDict"),
        *(
            (module, name)
            for module in _BUILTINS
            # bytes and bytearray are bounded: only from bytes or text held in the file
            for name in ("set", "frozenset", "slice", "complex", "bytes", "bytearray")
        ),
    }
)
"""The globals a dataset pickle may name; each is resolved to a size-checked wrapper."""


class UnsafePickleError(pickle.UnpicklingError, ValueError):
    """The file asks to rebuild an object that is not numpy data or a plain container."""


class PickleBombError(UnsafePickleError):
    """The file asks for far more memory than it holds (a length, shape or copy count)."""


class _NdarrayType:
    """Stands for ``numpy.ndarray``: usable as ``_reconstruct``'s subtype, not callable."""


_NDARRAY = _NdarrayType()


class _CheckedArray(np.ndarray):
    """An array being unpickled; `_Budget` checks its state before numpy allocates it."""

    _budget: _Budget

    def __setstate__(self, state: Any) -> None:
        self._budget.check_array_state(state)
        super().__setstate__(state)


class _Budget:
    """Bytes the allowed callables of one pickle may still allocate, and the callables."""

    def __init__(self, allowed_bytes: int) -> None:
        self.left = allowed_bytes
        self.array_type = type("_Array", (_CheckedArray,), {"_budget": self})

    def charge(self, nbytes: int, what: str) -> None:
        if nbytes > self.left:
            raise PickleBombError(
                f"{what} asks for {nbytes:,} bytes, more than the file can hold "
                f"({max(self.left, 0):,} bytes left of its allocation budget)"
            )
        self.left -= nbytes

    def reconstruct(self, subtype: Any, shape: Any, dtype: Any) -> np.ndarray:
        if subtype is not _NDARRAY:
            raise UnsafePickleError("numpy _reconstruct of something other than numpy.ndarray")
        dtype = np.dtype(dtype)
        self.charge(_count(shape) * dtype.itemsize, f"an array of shape {shape}")
        return np.ndarray.__new__(self.array_type, shape, dtype)

    def check_array_state(self, state: Any) -> None:
        if not isinstance(state, tuple) or len(state) not in (4, 5):
            raise UnsafePickleError(f"malformed numpy array state ({type(state).__name__})")
        shape, dtype, _, data = state[-4:]
        dtype = np.dtype(dtype)
        count = _count(shape)
        if dtype.hasobject:
            # the elements themselves are in the file; numpy allocates before checking
            if not isinstance(data, list) or len(data) != count:
                raise UnsafePickleError(f"object array of shape {shape} without its elements")
        elif not isinstance(data, (bytes, bytearray, str)) or len(data) != count * dtype.itemsize:
            raise UnsafePickleError(f"array of shape {shape} {dtype} without matching data")
        self.charge(count * dtype.itemsize, f"an array of shape {shape} {dtype}")

    def scalar(self, dtype: Any, *args: Any) -> Any:
        dtype = np.dtype(dtype)
        self.charge(dtype.itemsize, f"a {dtype} scalar")
        return _numpy_scalar(dtype, *args)

    def encode(self, text: Any, encoding: str = "utf-8", *args: Any) -> bytes:
        # protocol 2 stores array bytes as latin-1 text; other codecs could expand data
        try:
            latin1 = isinstance(text, str) and codecs.lookup(encoding).name == "iso8859-1"
        except (LookupError, TypeError):
            latin1 = False
        if not latin1:
            raise UnsafePickleError(f"_codecs.encode with codec {encoding!r}")
        self.charge(len(text), "encoded text")
        return codecs.encode(text, "latin-1")

    def frombuffer(
        self, buffer: Any, dtype: Any, shape: Any, order: str, axis_order: Any = None
    ) -> np.ndarray:
        dtype = np.dtype(dtype)
        nbytes = _count(shape) * dtype.itemsize
        if not isinstance(buffer, (bytes, bytearray)) or len(buffer) != nbytes or dtype.hasobject:
            raise UnsafePickleError(f"array of shape {shape} {dtype} without matching data")
        self.charge(nbytes, f"an array of shape {shape} {dtype}")
        array = np.frombuffer(buffer, dtype=dtype)
        if order == "K" and axis_order is not None:  # numpy's layout for permuted strides
            return array.reshape(shape, order="C").transpose(axis_order)
        if order not in ("C", "F"):
            raise UnsafePickleError(f"array order {order!r}")
        return array.reshape(shape, order="F" if order == "F" else "C")

    def buffer(self, kind: type) -> Any:
        def build(*args: Any) -> Any:
            if args and not isinstance(args[0], (bytes, bytearray, str)):
                raise UnsafePickleError(f"{kind.__name__} of anything but bytes or text")
            self.charge(len(args[0]) if args else 0, f"a {kind.__name__}")
            return kind(*args)

        return build

    def container(self, kind: type) -> Any:
        def build(*args: Any) -> Any:
            if args and hasattr(args[0], "__len__"):
                self.charge(64 * len(args[0]), f"a {kind.__name__}")
            return kind(*args)

        return build


def _count(shape: Any) -> int:
    """Elements of an array of ``shape``; refuses shapes that are not non-negative ints."""
    dims = (shape,) if isinstance(shape, int) else shape
    if not isinstance(dims, tuple) or not all(
        isinstance(d, (int, np.integer)) and d >= 0 for d in dims
    ):
        raise UnsafePickleError(f"malformed array shape {shape!r}")
    return math.prod(int(d) for d in dims)


class RestrictedUnpickler(pickle.Unpickler):
    """Unpickler that only resolves the globals in `ALLOWED`, to size-checked wrappers.

    Args:
        stream: the binary stream, positioned at the pickle.
        budget: bytes the allowed callables may allocate in total.
    """

    def __init__(self, stream: BinaryIO, budget: int = BUDGET_SLACK) -> None:
        super().__init__(stream, encoding="latin1")
        self.budget = _Budget(budget)

    def find_class(self, module: str, name: str) -> Any:
        """Resolves allow-listed globals; refuses the rest by name."""
        if (module, name) not in ALLOWED:
            raise UnsafePickleError(
                f"refusing to unpickle {module}.{name}: dataset files may only hold numpy "
                "arrays and plain containers"
            )
        guards: dict[str, Any] = {
            "_reconstruct": self.budget.reconstruct,
            "scalar": self.budget.scalar,
            "ndarray": _NDARRAY,
            "dtype": np.dtype,
            "encode": self.budget.encode,
            "_frombuffer": self.budget.frombuffer,
            "bytes": self.budget.buffer(bytes),
            "bytearray": self.budget.buffer(bytearray),
            "slice": slice,
            "complex": complex,
        }
        if name in guards:
            return guards[name]
        kinds = {"set": set, "frozenset": frozenset, "OrderedDict": collections.OrderedDict}
        return self.budget.container(kinds[name])


class _BoundedReader:
    """A file view that refuses, before allocating, to read past ``size`` bytes."""

    def __init__(self, stream: Any, size: int) -> None:
        self._stream = stream
        self._end = stream.tell() + size

    def read(self, n: int = -1) -> bytes:
        left = self._end - self._stream.tell()
        if n is None or n < 0:
            n = left
        if n > left:
            raise PickleBombError(f"a length of {n:,} bytes where only {left:,} remain")
        return self._stream.read(n)

    def readinto(self, buffer: Any) -> int:
        if len(memoryview(buffer)) > self._end - self._stream.tell():
            raise PickleBombError("a length that reaches past the end of the file")
        return self._stream.readinto(buffer)

    def readline(self, limit: int = -1) -> bytes:
        left = self._end - self._stream.tell()
        return self._stream.readline(left if limit is None or limit < 0 else min(limit, left))

    def tell(self) -> int:
        return self._stream.tell()


def remaining_bytes(stream: BinaryIO) -> int:
    """Bytes between the stream's position and its end (the position is kept)."""
    start = stream.tell()
    end = stream.seek(0, os.SEEK_END)
    stream.seek(start)
    return end - start


_MEMO_PUTS = frozenset({"PUT", "BINPUT", "LONG_BINPUT"})


def scan_opcodes(stream: BinaryIO, size: int) -> None:
    """Reads one pickle's opcodes without running them, refusing the ones that allocate.

    CPython's unpickler allocates a length-prefixed argument before reading it, and grows
    its memo table to the largest index a ``PUT`` names; a few bytes can ask for gigabytes
    either way. Here every length must fit in the ``size`` bytes that follow and every memo
    index must be one a real pickler would write (no larger than the memo entries so far).
    Leaves ``stream`` after the pickle.

    Raises:
        PickleBombError: a length or memo index beyond those bounds.
        ValueError, EOFError, ...: not a pickle (from `pickletools.genops`).
    """
    end = stream.tell() + size
    memo = 0
    for opcode, arg, _ in pickletools.genops(cast(BinaryIO, _BoundedReader(stream, size))):
        if opcode.name in _MEMO_PUTS:
            if not isinstance(arg, int) or not 0 <= arg <= memo:
                raise PickleBombError(f"a memo index of {arg:,} after {memo:,} entries")
            memo = max(memo, arg + 1)
        elif opcode.name == "MEMOIZE":
            memo += 1
        elif opcode.name == "FRAME" and isinstance(arg, int) and arg > end - stream.tell():
            raise PickleBombError(f"a frame of {arg:,} bytes where fewer remain")


def load_pickle_stream(stream: BinaryIO) -> Any:
    """Unpickles numpy data and plain containers from a seekable binary stream.

    The opcodes are scanned first (no length may reach past the end of the stream), then
    the pickle is loaded with a budget of `BUDGET_FACTOR` × its size plus `BUDGET_SLACK`.

    Raises:
        UnsafePickleError: the stream names a global outside `ALLOWED`.
        PickleBombError: the stream asks for more memory than it holds.
        pickle.UnpicklingError, ValueError, EOFError, ...: the stream is not a pickle.
    """
    start = stream.tell()
    size = remaining_bytes(stream)
    scan_opcodes(stream, size)
    stream.seek(start)
    reader = cast(BinaryIO, _BoundedReader(stream, size))
    unpickler = RestrictedUnpickler(reader, BUDGET_FACTOR * size + BUDGET_SLACK)
    value = unpickler.load()
    check_nesting(value, "the pickle")  # _plain and every later reader recurse into it
    return _plain(value)


def _plain(value: Any) -> Any:
    """``value`` with every unpickled array turned back into a plain ``numpy.ndarray``."""
    if isinstance(value, np.ndarray):
        array = value.view(np.ndarray) if type(value) is not np.ndarray else value
        if array.dtype == object:
            for index in np.ndindex(array.shape):
                array[index] = _plain(array[index])
        return array
    if isinstance(value, dict):
        for key, item in value.items():
            value[key] = _plain(item)
    elif isinstance(value, list):
        value[:] = [_plain(item) for item in value]
    elif type(value) is tuple:
        return tuple(_plain(item) for item in value)
    return value


_NOT_A_PICKLE = (
    pickle.UnpicklingError,
    EOFError,
    AttributeError,
    ImportError,
    IndexError,
    KeyError,
    TypeError,
    ValueError,
    OverflowError,
    LookupError,
    RecursionError,
    MemoryError,
)


def load_checked(stream: BinaryIO, path: Path, what: str) -> Any:
    """`load_pickle_stream` with every failure turned into a one-line error naming ``path``."""
    try:
        return load_pickle_stream(stream)
    except UnsafePickleError as error:
        raise type(error)(f"{path}: {error}") from None
    except _NOT_A_PICKLE as error:
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise ValueError(f"{path} {what} ({reason})") from None


def checked_file(path: str | os.PathLike[str]) -> Path:
    """``path`` as a `Path`, once it is known to be a file within the ``file_bytes`` limit."""
    path = Path(path)
    if kind(path, "dataset file") is None:
        raise FileNotFoundError(f"no such file: {path}")
    require_file(path, "dataset file")  # a folder, FIFO or device is named, never opened
    limits.check("file_bytes", path.stat().st_size, f"{path}: {path.stat().st_size:,} bytes")
    return path


def load_pickle(path: str | os.PathLike[str]) -> Any:
    """Reads a pickle file with the restricted, size-bounded unpickler.

    Raises:
        FileNotFoundError: the file does not exist.
        UnsafePickleError: the file holds other Python objects, or asks for more memory
            than it holds (`PickleBombError`).
        ValueError: the file is not a readable pickle, or is larger than the ``file_bytes``
            limit (the message names it).
    """
    path = checked_file(path)
    with path.open("rb") as stream:
        return load_checked(stream, path, "is not a readable pickle")
