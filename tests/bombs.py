"""Builders of hostile and careless input files, shared by the regression and fuzz tests.

Every builder writes a small file under a given folder and returns its path; none of them
needs more than a few kilobytes of memory or disk. `scripts/fuzz_report.py` uses them too.
"""

from __future__ import annotations

import collections
import io
import pickle
import struct
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

GIB = 1024**3


def global_op(module: str, name: str) -> bytes:
    """Protocol-4 opcodes pushing the global ``module.name``."""
    return (
        b"\x8c"
        + bytes([len(module)])
        + module.encode()
        + b"\x8c"
        + bytes([len(name)])
        + name.encode()
        + b"\x93"
    )


def int_op(value: int) -> bytes:
    """LONG1 opcode pushing ``value``."""
    data = value.to_bytes((value.bit_length() + 8) // 8, "little", signed=True)
    return b"\x8a" + bytes([len(data)]) + data


def pickle_bombs() -> dict[str, bytes]:
    """Tiny pickles that ask for gigabytes, by name."""
    size = 12 * GIB
    reconstruct = global_op("numpy._core.multiarray", "_reconstruct") + global_op(
        "numpy", "ndarray"
    )
    return {
        "bytearray_call": b"\x80\x04"
        + global_op("builtins", "bytearray")
        + int_op(size)
        + b"\x85R.",
        "bytes_call": b"\x80\x04" + global_op("builtins", "bytes") + int_op(size) + b"\x85R.",
        "binbytes8_length": b"\x80\x04\x8e" + struct.pack("<Q", size) + b"abc.",
        "bytearray8_length": b"\x80\x05\x96" + struct.pack("<Q", size) + b"abc.",
        "binunicode8_length": b"\x80\x04\x8d" + struct.pack("<Q", size) + b"abc.",
        "reconstruct_shape": b"\x80\x04" + reconstruct + int_op(size) + b"\x85C\x01b\x87R.",
        "object_array_state": b"\x80\x04"
        + reconstruct
        + b"K\x00\x85C\x01b\x87R(K\x01"
        + int_op(size // 8)
        + b"\x85"
        + global_op("numpy", "dtype")
        + b"\x8c\x02O8\x85R"
        + b"\x89]tb.",
        "ndarray_call": b"\x80\x04" + global_op("numpy", "ndarray") + int_op(size) + b"\x85R.",
        "codec_hex": b"\x80\x04" + global_op("_codecs", "encode") + b"\x8c\x03abc\x8c\x03hex\x86R.",
        "codec_unknown": b"\x80\x04"
        + global_op("_codecs", "encode")
        + b"\x8c\x03abc\x8c\x05bogus\x86R.",
        "set_copies": _set_copies(),
        "os_system": b"\x80\x04" + global_op("os", "system") + b"\x8c\x04true\x85R.",
        "memo_index": MEMO_BOMB,
    }


MEMO_BOMB = b"\x80\x02Nr" + struct.pack("<I", 2**31 - 1) + b"."
"""LONG_BINPUT at index 2**31 - 1: CPython's unpickler grows its memo table to 32 GiB."""


def _set_copies() -> bytes:
    """One list of 10,000 items turned into a set 2,000 times (copies, not references)."""
    items = b"(" + b"K\x01" + b"2" * 9_999 + b"l\x94"  # MARK, 1, DUP x 9999, LIST, MEMOIZE
    call = global_op("builtins", "set") + b"h\x00\x85R"  # set(memo[0])
    return b"\x80\x04" + items + b"0(" + call * 2000 + b"l."


def davis_item(frames: int = 4, size: int = 8, points: int = 2, seed: int = 0) -> dict[str, Any]:
    """One valid TAP-Vid item (uint8 video, normalised raster points, occlusion flags)."""
    rng = np.random.default_rng(seed)
    return {
        "video": rng.integers(0, 256, (frames, size, size, 3), dtype=np.uint8),
        "points": rng.uniform(0.1, 0.9, (points, frames, 2)),
        "occluded": rng.random((points, frames)) < 0.2,
    }


def png_bytes(height: int, width: int, value: int = 0) -> bytes:
    """A constant grey PNG (compresses to almost nothing however large)."""
    from PIL import Image

    stream = io.BytesIO()
    Image.new("L", (width, height), value).save(stream, format="PNG", optimize=True)
    return stream.getvalue()


def png_bomb(width: int = 100_000, height: int = 100_000) -> bytes:
    """A PNG header declaring ``width`` × ``height`` with a tiny (broken) body."""
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    data = zlib.compress(b"\x00" * 1024)
    return (
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", data) + chunk(b"IEND", b"")
    )


def npy_header_bomb(path: Path, shape: tuple[int, ...] = (1_000_000, 1_000_000, 2)) -> Path:
    """A 128-byte ``.npy`` whose header declares a float32 array of ``shape`` (7.28 TiB)."""
    stream = io.BytesIO()
    header = {"descr": "<f4", "fortran_order": False, "shape": shape}
    np.lib.format.write_array_header_1_0(stream, header)
    path.write_bytes(stream.getvalue())
    return path


class _Call:
    """Pickles as ``func(*args)``."""

    def __init__(self, func: Any, *args: Any) -> None:
        self.func, self.args = func, args

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return self.func, self.args


def torch_zip(path: Path, obj: Any, storages: dict[str, tuple[Any, int, bytes]]) -> Path:
    """A zip-format checkpoint whose pickle is ``obj``, with hand-made storage records.

    ``storages`` maps a key to (storage type, declared element count, record bytes); a
    `StorageRef` in ``obj`` pickles as the persistent id of its key.
    """
    data = io.BytesIO()
    pickler = pickle.Pickler(data, protocol=2)
    pickler.persistent_id = lambda o: (  # type: ignore[method-assign]
        ("storage", storages[o.key][0], o.key, "cpu", storages[o.key][1])
        if isinstance(o, StorageRef)
        else None
    )
    pickler.dump(obj)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as archive:
        archive.writestr("archive/data.pkl", data.getvalue())
        archive.writestr("archive/byteorder", "little")
        for key, (_, _, record) in storages.items():
            archive.writestr(f"archive/data/{key}", record)
        archive.writestr("archive/version", "3\n")
    return path


class StorageRef:
    """A storage by key, for `torch_zip`."""

    def __init__(self, key: str) -> None:
        self.key = key


def tensor_ref(key: str, numel: int) -> _Call:
    """``_rebuild_tensor_v2`` of storage ``key`` as a 1-d tensor of ``numel`` elements."""
    return _Call(
        torch._utils._rebuild_tensor_v2,
        StorageRef(key),
        0,
        (numel,),
        (1,),
        False,
        collections.OrderedDict(),
    )


def legacy_checkpoint(path: Path, numel: int, held: int = 16) -> Path:
    """A legacy-format file declaring one float storage of ``numel`` elements, ``held`` bytes."""
    from torch.serialization import MAGIC_NUMBER, PROTOCOL_VERSION

    stream = io.BytesIO()
    for header in (MAGIC_NUMBER, PROTOCOL_VERSION, {"little_endian": True}):
        pickle.dump(header, stream, protocol=2)
    pickler = pickle.Pickler(stream, protocol=2)
    pickler.persistent_id = lambda o: (  # type: ignore[method-assign]
        ("storage", torch.FloatStorage, "0", "cpu", numel, None)
        if isinstance(o, StorageRef)
        else None
    )
    pickler.dump({"w": tensor_ref("0", numel)})
    pickle.dump(["0"], stream, protocol=2)
    stream.write(struct.pack("<q", numel) + bytes(held))
    path.write_bytes(stream.getvalue())
    return path


def call_checkpoint(path: Path, func: Any, *args: Any) -> Path:
    """A zip-format checkpoint whose pickle is ``{"x": func(*args)}``."""
    return torch_zip(path, {"x": _Call(func, *args)}, {})
