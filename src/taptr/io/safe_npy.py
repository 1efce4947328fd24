"""Bounded ``.npy`` reading (Kubric's track files): the header checked before the data.

A ``.npy`` header declares a shape and a dtype; a crafted file can declare far more than
it holds, and ``np.load`` would allocate the declared size first. The header is read and
compared with the bytes that follow before anything is allocated; object arrays (how
``np.save`` stores a dict) go through the restricted unpickler of `taptr.io.safe_pickle`.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from tokenize import TokenError
from typing import Any, BinaryIO

import numpy as np
from numpy.lib import format as npy_format

from taptr.io.safe_pickle import checked_file, load_checked, remaining_bytes


def read_npy_header(stream: BinaryIO, path: Path) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of a ``.npy`` stream, checked against the bytes that follow.

    Leaves the stream at the start of the data.

    Raises:
        ValueError: not a ``.npy`` file, or it declares more data than it holds.
    """
    try:
        version = npy_format.read_magic(stream)
        if version == (1, 0):
            shape, _, dtype = npy_format.read_array_header_1_0(stream)
        else:
            shape, _, dtype = npy_format.read_array_header_2_0(stream)
    except (ValueError, OverflowError, SyntaxError, TypeError, EOFError, TokenError) as error:
        reason = str(error).strip().splitlines()[0] if str(error).strip() else "bad header"
        raise ValueError(f"{path} is not a .npy file ({reason})") from None
    if any(side < 0 for side in shape):
        raise ValueError(f"{path}: the header declares a negative shape {shape}")
    if not dtype.hasobject:
        declared = math.prod(shape) * dtype.itemsize
        held = remaining_bytes(stream)
        if declared > held:
            raise ValueError(
                f"{path}: the header declares a {'x'.join(map(str, shape)) or 'scalar'} "
                f"{dtype} array ({declared:,} bytes) but the file holds {held:,} bytes of data"
            )
    return shape, dtype


def load_npy(path: str | os.PathLike[str]) -> Any:
    """Reads a ``.npy`` file; object arrays go through the restricted unpickler.

    The header is checked before any data is read: a file declaring more bytes than it
    holds is refused. ``np.save`` of a dict writes a 0-d object array holding a pickle of
    the dict.

    Returns:
        The array, or the pickled object itself when the file holds a 0-d object array
        (how ``np.save`` stores a dict).

    Raises:
        FileNotFoundError: the file does not exist.
        UnsafePickleError: its pickled objects are not plain data or ask for too much memory.
        ValueError: not a readable ``.npy`` file, or larger than the ``file_bytes`` limit.
    """
    path = checked_file(path)
    with path.open("rb") as stream:
        shape, dtype = read_npy_header(stream, path)
        if not dtype.hasobject:
            stream.seek(0)
            return np.load(stream, allow_pickle=False)
        array = load_checked(stream, path, "holds an unreadable pickled object")
    if isinstance(array, np.ndarray) and array.shape == () and shape == ():
        return array.item()
    return array
