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
import zlib
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


def png_bomb(width: int = 100_000, height: int = 100_000, depth: int = 8, colour: int = 0) -> bytes:
    """A PNG header declaring ``width`` × ``height`` with a tiny (broken) body.

    ``depth`` bits per sample and ``colour`` type (0 grey, 2 RGB, 6 RGBA): 16-bit RGBA
    decodes to 8 bytes a pixel.
    """
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    header = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
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


# -- issue 29: decoders by content, lying sizes, logical views, special files -------------


def gif_canvas(width: int = 16_000, height: int = 16_000) -> bytes:
    """A 35-byte GIF whose screen and only image declare ``width`` × ``height``.

    FFmpeg's GIF decoder allocates the whole canvas (1 GB at 16,000²) for the first frame.
    """
    screen = struct.pack("<HHBBB", width, height, 0, 0, 0)
    image = b"\x2c" + struct.pack("<HHHHB", 0, 0, width, height, 0x80)
    palette = b"\x00\x00\x00\xff\xff\xff"
    pixels = b"\x02" + b"\x02\x4c\x01" + b"\x00"  # LZW code size 2, one sub-block, end
    return b"GIF89a" + screen + image + palette + pixels + b"\x3b"


def hdr_image(height: int = 16, width: int = 16) -> bytes:
    """A Radiance HDR image (flat RGBE): OpenCV decodes it by content, Pillow cannot read it.

    Named ``.png``, it is "an image format that is not PNG": with run-length scanlines such
    a file expands a hundredfold, to 12 bytes a pixel in OpenCV.
    """
    header = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n" + f"-Y {height} +X {width}\n".encode()
    return header + bytes([128, 64, 32, 129]) * (height * width)


def deflated_checkpoint(path: Path, inflated: int) -> Path:
    """A zip checkpoint whose one storage record deflates ``inflated`` zero bytes to ~0.1%.

    The storage declares exactly what the record inflates to, so every size the file
    states is honest; only the file is a thousand times smaller than what it holds. The
    deflate stream is one compressed MiB of zeros, flushed so that it stands alone, written
    ``inflated`` / 1 MiB times (so a 768 MiB bomb takes no time to make).
    """
    mib = 1 << 20
    numel = inflated // 4
    plain = torch_zip(path, {"w": tensor_ref("0", numel)}, {"0": (torch.FloatStorage, numel, b"")})
    with zipfile.ZipFile(plain) as archive:
        records = {info.filename: archive.read(info) for info in archive.infolist()}
    piece = zlib.compressobj(9, zlib.DEFLATED, -15)
    segment = piece.compress(bytes(mib)) + piece.flush(zlib.Z_FULL_FLUSH)
    crc = 0
    for _ in range(inflated // mib):
        crc = zlib.crc32(bytes(mib), crc)
    entries = []
    for name, data in records.items():
        if name.endswith("data/0"):
            stream = segment * (inflated // mib) + zlib.compressobj(9, zlib.DEFLATED, -15).flush()
            entries.append((name, 8, stream, crc, inflated // mib * mib))
        else:
            entries.append((name, 0, data, zlib.crc32(data), len(data)))
    path.write_bytes(_zip(entries))
    return path


def _zip(entries: list[tuple[str, int, bytes, int, int]]) -> bytes:
    """A zip archive of (name, method, stored bytes, crc, uncompressed size) entries."""
    body, directory = b"", b""
    for name, method, data, crc, size in entries:
        encoded = name.encode()
        fields = (20, 0, method, 0, 33, crc, len(data), size, len(encoded))
        directory += (
            struct.pack("<4s6H3L5H2L", b"PK\x01\x02", 20, *fields, 0, 0, 0, 0, 0, len(body))
            + encoded
        )
        body += struct.pack("<4s5H3L2H", b"PK\x03\x04", *fields, 0) + encoded + data
    count = len(entries)
    end = struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, count, count, len(directory), len(body), 0)
    return body + directory + end


def view_checkpoint(path: Path, numel: int) -> Path:
    """The tiny model's checkpoint with one weight a ``numel``-element view of ONE float.

    ``torch.save`` keeps the zero stride: the file holds 4 bytes for the view, and anything
    that computes on the whole view (a finiteness check) allocates ``numel`` elements.
    """
    from taptr import build_model
    from taptr.weights.checkpoint import checkpoint_dict

    torch.manual_seed(0)
    data = checkpoint_dict(build_model("tiny"))
    key = next(k for k, v in data["model"].items() if v.is_floating_point())
    data["model"][key] = torch.zeros(1).expand(numel)
    torch.save(data, path)
    return path


DEEP = "__deep__"


def deep_config_checkpoint(path: Path, depth: int = 100_000, key: str = "d_model") -> Path:
    """The tiny model's checkpoint whose config value ``key`` is a list nested ``depth`` deep.

    ``pickle`` cannot write such a value (it recurses); the opcodes are spliced in: EMPTY_LIST
    ``depth`` times, then APPEND ``depth - 1`` times.
    """
    from taptr import build_model
    from taptr.weights.checkpoint import checkpoint_dict

    data = checkpoint_dict(build_model("tiny"))
    data["config"][key] = DEEP
    torch.save(data, path)
    nested = b"]" * depth + b"a" * (depth - 1)
    marker = b"X" + struct.pack("<I", len(DEEP)) + DEEP.encode()  # BINUNICODE (protocol 2)
    with zipfile.ZipFile(path) as archive:
        records = {info.filename: archive.read(info) for info in archive.infolist()}
    name = next(n for n in records if n.endswith("data.pkl"))
    assert records[name].count(marker) == 1
    records[name] = records[name].replace(marker, nested)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as archive:
        for record, content in records.items():
            archive.writestr(record, content)
    return path


def spliced_video(path: Path, sizes: tuple[tuple[int, int], ...] = ((32, 32), (48, 64))) -> Path:
    """MPEG-TS segments of different frame sizes, one after the other (``cat a.ts b.ts``).

    A transport stream may change resolution mid-stream; FFmpeg then decodes frames of the
    new size. The suffix is the caller's (FFmpeg finds the format by content).
    """
    import av

    parts = []
    for index, (height, width) in enumerate(sizes):
        stream = io.BytesIO()
        with av.open(stream, "w", format="mpegts") as container:
            video = container.add_stream("mpeg2video", rate=10)
            video.width, video.height, video.pix_fmt = width, height, "yuv420p"
            for t in range(4):
                frame = np.full((height, width, 3), 40 * index + 10 * t, np.uint8)
                container.mux(video.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))
            container.mux(video.encode())
        parts.append(stream.getvalue())
    path.write_bytes(b"".join(parts))
    return path
