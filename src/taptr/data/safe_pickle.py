"""A restricted unpickler for dataset files (TAP-Vid pickles, Kubric ``.npy`` annotations).

These files are pickles of numpy arrays in plain containers. Unpickling them with
``pickle.load`` or ``np.load(allow_pickle=True)`` would run any code a crafted file asks
for; this reader rebuilds numpy arrays, numpy scalars and builtin containers only, and
refuses everything else with an error naming the object.
"""

from __future__ import annotations

import io
import os
import pickle
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from numpy.lib import format as npy_format

ALLOWED = frozenset(
    {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "scalar"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
        ("_codecs", "encode"),  # protocol-2 pickles encode raw array bytes through it
        ("collections", "OrderedDict"),
        ("builtins", "set"),
        ("builtins", "frozenset"),
        ("builtins", "slice"),
        ("builtins", "complex"),
        ("builtins", "bytearray"),
        ("__builtin__", "set"),
    }
)


class UnsafePickleError(pickle.UnpicklingError):
    """The file asks to rebuild an object that is not numpy data or a plain container."""


class RestrictedUnpickler(pickle.Unpickler):
    """Unpickler that only resolves the globals in `ALLOWED`."""

    def find_class(self, module: str, name: str) -> Any:
        """Resolves allow-listed globals; refuses the rest by name."""
        if (module, name) in ALLOWED:
            return super().find_class(module, name)
        raise UnsafePickleError(
            f"refusing to unpickle {module}.{name}: dataset files may only hold numpy arrays "
            "and plain containers"
        )


def load_pickle_stream(stream: BinaryIO) -> Any:
    """Unpickles numpy data and plain containers from an open binary stream."""
    return RestrictedUnpickler(stream, encoding="latin1").load()


def load_pickle(path: str | os.PathLike[str]) -> Any:
    """Reads a pickle file with the restricted unpickler.

    Raises:
        FileNotFoundError: the file does not exist.
        UnsafePickleError: the file holds other Python objects.
        ValueError: the file is not a readable pickle (the message names it).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    with path.open("rb") as stream:
        try:
            return load_pickle_stream(stream)
        except UnsafePickleError as error:
            raise UnsafePickleError(f"{path}: {error}") from None
        except (
            pickle.UnpicklingError,
            EOFError,
            AttributeError,
            ImportError,
            IndexError,
            TypeError,
            ValueError,
        ) as error:
            raise ValueError(f"{path} is not a readable pickle ({error})") from None


def load_npy(path: str | os.PathLike[str]) -> Any:
    """Reads a ``.npy`` file; object arrays go through the restricted unpickler.

    ``np.save`` of a dict writes a 0-d object array holding a pickle of the dict.

    Returns:
        The array, or the pickled object itself when the file holds a 0-d object array
        (how ``np.save`` stores a dict).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    with path.open("rb") as stream:
        try:
            version = npy_format.read_magic(stream)
            if version == (1, 0):
                shape, _, dtype = npy_format.read_array_header_1_0(stream)
            else:
                shape, _, dtype = npy_format.read_array_header_2_0(stream)
        except ValueError as error:
            raise ValueError(f"{path} is not a .npy file ({error})") from None
        if not dtype.hasobject:
            stream.seek(0)
            return np.load(io.BytesIO(stream.read()), allow_pickle=False)
        try:
            array = load_pickle_stream(stream)
        except UnsafePickleError as error:
            raise UnsafePickleError(f"{path}: {error}") from None
        except (pickle.UnpicklingError, EOFError, AttributeError, TypeError, ValueError) as error:
            raise ValueError(f"{path} holds an unreadable pickled object ({error})") from None
    if isinstance(array, np.ndarray) and array.shape == () and shape == ():
        return array.item()
    return array
