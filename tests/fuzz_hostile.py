"""Fuzz categories of issue 29: decoders by content, lying sizes, logical views, special
files and resource estimates. `tests.fuzz_targets` adds them to its `CATEGORIES`.

Each target has an oracle beyond "a clean error or a valid result":

- decoder by content: every image is read with ``TAPTR_MAX_IMAGE_PIXELS`` at
  `PIXEL_LIMIT`; a returned image above it, or a video frame decoded from a file whose
  header is not PNG or JPEG, is silent wrong output.
- lying sizes and logical views: ``torch.isfinite`` is watched; a call on more elements
  than the tensor's storage holds (a view materialised beyond its storage) is silent
  wrong output.
- special files: a reader that blocks on a FIFO (more than `HANG_SECONDS`) is a failure.
- resource estimates: the estimate must be positive, grow with every knob, and refuse
  exactly the runs above the budget with a one-line message naming the knobs.

`memory_bound` (used by `tests.fuzz_targets.classify` and tests/test_fuzz.py) adds one
oracle to every category: the process's peak resident memory may grow by at most
`RSS_BUDGET` while one input is read (Linux; elsewhere it checks nothing).
"""

from __future__ import annotations

import contextlib
import functools
import io
import os
import socket
import tempfile
import threading
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hypothesis import strategies as st

from tests import bombs

PIXEL_LIMIT = 2500
"""``TAPTR_MAX_IMAGE_PIXELS`` while images are fuzzed: 50 × 50."""

RSS_BUDGET = 512 * 1024**2
"""Most the peak resident memory may grow while one fuzzed input is read."""

HANG_SECONDS = 10.0


class SilentError(AssertionError):
    """A reader returned a result that is wrong (NaN, bad shape) instead of an error."""


# -- the memory oracle ---------------------------------------------------------------------


def _status(key: str) -> int | None:
    try:
        with open("/proc/self/status", encoding="ascii") as stream:
            for line in stream:
                if line.startswith(key):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


@contextlib.contextmanager
def memory_bound() -> Iterator[None]:
    """Raises `SilentError` when the block grew the peak RSS by more than `RSS_BUDGET`."""
    try:
        with open("/proc/self/clear_refs", "w", encoding="ascii") as stream:
            stream.write("5")  # resets VmHWM, the peak, to the current RSS
    except OSError:
        yield
        return
    start = _status("VmRSS")
    try:
        yield
    finally:  # an error after a huge allocation is no clean error
        peak = _status("VmHWM")
        if start is not None and peak is not None and peak - start > RSS_BUDGET:
            grown = (peak - start) / 2**20
            raise SilentError(f"peak RSS grew by {grown:.0f} MiB reading one input")


@contextlib.contextmanager
def _env(**values: str) -> Iterator[None]:
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for key, value in old.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


# -- decoder by content --------------------------------------------------------------------

_PIL_FORMATS = ["PNG", "JPEG", "BMP", "TIFF", "WEBP", "GIF", "PPM"]
_MODES = ["L", "RGB", "RGBA", "I;16", "P", "1"]


def _encode_image(kind: str, height: int, width: int, mode: str, seed: int) -> bytes:
    from PIL import Image

    if kind == "HDR":
        return bombs.hdr_image(height, width)
    if kind == "PNG header bomb":
        return bombs.png_bomb(width * 40, height * 40, depth=16, colour=6)
    if kind == "GIF canvas":
        return bombs.gif_canvas(width * 40, height * 40)
    if kind == "garbage":
        return np.random.default_rng(seed).integers(0, 256, 64, dtype=np.uint8).tobytes()
    rng = np.random.default_rng(seed)
    image = Image.fromarray(rng.integers(0, 256, (height, width, 3), dtype=np.uint8))
    if mode == "I;16":
        image = Image.fromarray(rng.integers(0, 65535, (height, width), dtype=np.uint16))
    elif mode != "RGB":
        image = image.convert(mode)
    stream = io.BytesIO()
    try:
        image.save(stream, format=kind)
    except (OSError, ValueError, KeyError):  # a mode the format cannot store
        image.convert("RGB").save(stream, format=kind)
    return stream.getvalue()


ROLES = ("frame folder", "video file", "kubric frame", "mask", "overlay", "tapvid frame")


@st.composite
def decoder_inputs(draw: st.DrawFn) -> tuple[str, str, bytes]:
    """(role, file name, content): an image of any format under a name taptr reads."""
    kind = draw(st.sampled_from([*_PIL_FORMATS, "HDR", "PNG header bomb", "GIF canvas", "garbage"]))
    height, width = draw(st.integers(1, 80)), draw(st.integers(1, 80))
    content = _encode_image(
        kind, height, width, draw(st.sampled_from(_MODES)), draw(st.integers(0, 9))
    )
    if draw(st.integers(0, 3)) == 0:
        from tests.fuzz_targets import EDITS, _mutate

        content = _mutate(content, draw(EDITS))
    role = draw(st.sampled_from(ROLES))
    suffix = draw(
        st.sampled_from(
            [".png", ".jpg", ".jpeg"] if role != "video file" else [".gif", ".mp4", ".avi"]
        )
    )
    return role, f"0{suffix}", content


def _true_format(path: Path) -> str | None:
    from PIL import Image

    try:
        with Image.open(path) as image:
            return image.format
    except Exception:
        return None


def read_by_role(value: tuple[str, str, bytes]) -> None:
    """Reads one image through the reader of its role, with the pixel limit lowered."""
    role, name, content = value
    with tempfile.TemporaryDirectory() as folder, _env(TAPTR_MAX_IMAGE_PIXELS=str(PIXEL_LIMIT)):
        root = Path(folder)
        path = _layout(role, root, name)
        path.write_bytes(content)
        images = _read_role(role, root, path, content)
        for image in images:
            if image.shape[0] * image.shape[1] > PIXEL_LIMIT:
                raise SilentError(f"{role}: {image.shape} passed a {PIXEL_LIMIT}-pixel limit")
        frame = role in ("frame folder", "kubric frame", "tapvid frame")
        if images and frame and _true_format(path) not in ("PNG", "JPEG"):
            raise SilentError(f"{role}: a {_true_format(path)} file was decoded as a frame")


def _layout(role: str, root: Path, name: str) -> Path:
    """Where the fuzzed file goes for ``role`` (a Kubric sequence gets its annotations)."""
    if role != "kubric frame":
        return root / name
    sequence = root / "0000"
    (sequence / "frames").mkdir(parents=True)
    annotations = {"coords": np.zeros((1, 1, 2), np.float32), "visibility": np.zeros((1, 1), bool)}
    np.save(sequence / "0000.npy", np.array(annotations, dtype=object), allow_pickle=True)
    return sequence / "frames" / "000.png"


def _read_role(role: str, root: Path, path: Path, content: bytes) -> list[np.ndarray]:
    from taptr.io.video import read_video

    if role == "frame folder":
        return list(read_video(root))
    if role == "video file":
        return list(read_video(path))
    if role == "mask":
        from taptr.api.regions import read_mask

        return [read_mask(path)]
    if role == "overlay":
        from taptr.cli.edit import _read_overlay

        return [_read_overlay(str(path))]
    if role == "tapvid frame":
        from taptr.data.tapvid import decode_frames

        return list(decode_frames([content], "fuzz"))
    from taptr.data.kubric import read_sequence

    return list(read_sequence(root / "0000").video)


# -- lying sizes ---------------------------------------------------------------------------


@st.composite
def lying_checkpoints(draw: st.DrawFn) -> bytes:
    """A small checkpoint re-zipped with one kind of lie about its records' sizes.

    Lies: records padded beyond their storage, directory sizes that differ from the
    records', compressed records, and honest-looking deflated bombs; one file in nine
    only compresses its records (it must load).
    """
    lie = draw(st.sampled_from(["padded", "file size", "compressed size", "bomb"] * 2 + ["none"]))
    if lie == "bomb":
        return _deflated(draw(st.sampled_from([1 << 20, BOMB_BYTES])))
    with zipfile.ZipFile(io.BytesIO(_small_file())) as archive:
        records = {info.filename: archive.read(info) for info in archive.infolist()}
    names = sorted(records)
    chosen = draw(st.sampled_from(names))
    compression = draw(st.sampled_from(["none", "chosen", "all"]))
    stream = io.BytesIO()
    with zipfile.ZipFile(stream, "w") as archive:
        for name in names:
            data = records[name]
            if lie == "padded" and name == chosen:  # more bytes than its storage
                data += bytes(draw(st.one_of(st.integers(1, 4096), st.just(4 << 20))))
            deflated = name == chosen if compression == "chosen" else compression == "all"
            method = zipfile.ZIP_DEFLATED if deflated else zipfile.ZIP_STORED
            archive.writestr(name, data, compress_type=method)
        info = next(i for i in archive.filelist if i.filename == chosen)
        if lie == "file size":  # the central directory, written at close, lies
            info.file_size = draw(
                st.integers(0, 2**32 - 1).filter(lambda n, real=info.file_size: n != real)
            )
        elif lie == "compressed size":
            info.compress_size = draw(
                st.integers(0, 2**32 - 1).filter(lambda n, real=info.compress_size: n != real)
            )
    return stream.getvalue()


@functools.cache
def _small_file() -> bytes:
    """A zip checkpoint of three tensors (the zip layer is what is fuzzed, not the model)."""
    stream = io.BytesIO()
    weights = {"a": torch.arange(1000.0), "b": torch.ones(3, 5), "c": torch.zeros(0)}
    torch.save({"format": "taptr", "version": 1, "model": weights}, stream)
    return stream.getvalue()


BOMB_BYTES = 768 * 1024**2
"""What the deflated bomb inflates to: above `RSS_BUDGET`, so reading it all is caught."""


@functools.cache
def _deflated(inflated: int) -> bytes:
    """`tests.bombs.deflated_checkpoint` of ``inflated`` bytes (made once, in about 1 s)."""
    with tempfile.TemporaryDirectory() as folder:
        return bombs.deflated_checkpoint(Path(folder) / "d.pth", inflated).read_bytes()


def read_watched_checkpoint(data: bytes) -> None:
    """`tests.fuzz_targets.read_checkpoint`, with ``torch.isfinite`` watched."""
    from tests.fuzz_targets import read_checkpoint

    with _watched_isfinite():
        read_checkpoint(data)


@contextlib.contextmanager
def _watched_isfinite() -> Iterator[None]:
    real = torch.isfinite

    def watched(tensor: torch.Tensor) -> torch.Tensor:
        held = tensor.untyped_storage().nbytes() // max(1, tensor.element_size())
        if tensor.numel() > held:
            raise SilentError(
                f"isfinite on {tensor.numel():,} elements of a {held:,}-element storage"
            )
        return real(tensor)

    torch.isfinite = watched  # type: ignore[assignment]
    try:
        yield
    finally:
        torch.isfinite = real  # type: ignore[assignment]


# -- logical views -------------------------------------------------------------------------


@st.composite
def view_checkpoints(draw: st.DrawFn) -> bytes:
    """Checkpoints whose tensors are views of any offset, size and stride over a storage."""
    kind = draw(st.integers(0, 1))
    if kind == 0:  # hand-made views in a bare zip
        numel = draw(st.integers(0, 64))
        dims = draw(st.integers(0, 4))
        size = tuple(
            draw(
                st.lists(st.sampled_from([0, 1, 2, 7, 10**6, 2**40]), min_size=dims, max_size=dims)
            )
        )
        stride = tuple(
            draw(st.lists(st.sampled_from([0, 1, 3, -1, 2**40]), min_size=dims, max_size=dims))
        )
        offset = draw(st.sampled_from([0, 1, 63, 2**40, -1]))
        ref = bombs._Call(
            torch._utils._rebuild_tensor_v2, bombs.StorageRef("0"), offset, size, stride, False, {}
        )
        with tempfile.TemporaryDirectory() as folder:
            path = bombs.torch_zip(
                Path(folder) / "v.pth",
                {"format": "taptr", "w": ref},
                {"0": (torch.FloatStorage, numel, bytes(4 * numel))},
            )
            return path.read_bytes()
    from tests.fuzz_targets import _tiny_checkpoint

    data = dict(_tiny_checkpoint())
    data["model"] = dict(data["model"])
    name = draw(st.sampled_from(sorted(data["model"])))
    shape = data["model"][name].shape
    value = draw(st.sampled_from([1.0, float("nan"), float("inf")]))
    if draw(st.booleans()):
        data["model"][name] = torch.full((1,), value).expand(shape)  # the model's shape
    else:
        data["model"][name] = torch.full((1,), value).expand(draw(st.sampled_from([10**6, 10**8])))
    stream = io.BytesIO()
    torch.save(data, stream)
    return stream.getvalue()


# -- special files -------------------------------------------------------------------------

SPECIAL_KINDS = (
    "fifo",
    "folder",
    "socket",
    "/dev/null",
    "link to fifo",
    "dangling link",
    "link loop",
)
SPECIAL_ROLES = (
    "video",
    "frame in a folder",
    "checkpoint",
    "points file",
    "mask",
    "overlay",
    "tapvid file",
    "kubric annotations",
    "kubric frame",
)

special_paths = st.tuples(
    st.sampled_from(SPECIAL_ROLES),
    st.sampled_from(SPECIAL_KINDS),
    st.text("abcxyz019_-. ", min_size=1, max_size=40).filter(lambda t: t.strip(". ")),
)
"""(role, kind of path, name stem): a path that is not a regular file where a file belongs."""


def _make_special(path: Path, kind: str, sockets: list[socket.socket]) -> list[Path]:
    """Creates ``path`` as ``kind``; returns the FIFOs a blocked reader would wait on."""
    if kind == "fifo":
        os.mkfifo(path)
        return [path]
    if kind == "folder":
        path.mkdir()
    elif kind == "socket":
        server = socket.socket(socket.AF_UNIX)
        server.bind(str(path))
        sockets.append(server)
    elif kind == "/dev/null":
        path.symlink_to("/dev/null")
    elif kind == "link to fifo":
        os.mkfifo(path.with_name("target"))
        path.symlink_to(path.with_name("target"))
        return [path.with_name("target")]
    elif kind == "dangling link":
        path.symlink_to(path.with_name("nowhere"))
    else:
        path.symlink_to(path)
    return []


def read_special(value: tuple[str, str, str]) -> None:
    """Reads a special path in its role; a reader that blocks is a failure."""
    role, kind, stem = value
    with tempfile.TemporaryDirectory(dir="/tmp") as folder:
        root = Path(folder)
        path, run = _special_role(root, role, stem)
        sockets: list[socket.socket] = []
        fifos = _make_special(path, kind, sockets)
        try:
            _within(run, fifos)
        finally:
            for server in sockets:
                server.close()


def _within(run: Callable[[], Any], fifos: list[Path]) -> None:
    outcome: dict[str, BaseException] = {}

    def target() -> None:
        try:
            run()
        except BaseException as error:
            outcome["error"] = error

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(HANG_SECONDS)
    if thread.is_alive():
        for fifo in fifos:
            os.close(os.open(fifo, os.O_RDWR | os.O_NONBLOCK))
        thread.join(HANG_SECONDS)
        raise SilentError("a reader blocked on a special file")
    if "error" in outcome:
        raise outcome["error"]


def _special_role(root: Path, role: str, stem: str) -> tuple[Path, Callable[[], Any]]:
    """(the path to make special, a call that reads it in ``role``)."""
    from taptr.api.regions import read_mask
    from taptr.cli.common.points import read_points_file
    from taptr.cli.edit import _read_overlay
    from taptr.data.kubric import read_sequence
    from taptr.data.tapvid import iter_tapvid
    from taptr.io.video import read_video, video_info
    from taptr.weights.checkpoint import load_checkpoint

    if role == "video":
        path = root / f"{stem}.mp4"
        return path, lambda: (video_info(path), read_video(path))
    if role == "frame in a folder":
        (root / "0.png").write_bytes(bombs.png_bytes(4, 4))
        return root / f"f{stem}.png", lambda: read_video(root)
    if role == "checkpoint":
        path = root / f"{stem}.pth"
        return path, lambda: load_checkpoint(path)
    if role == "points file":
        path = root / f"{stem}.txt"
        return path, lambda: read_points_file(str(path))
    if role == "mask":
        path = root / f"{stem}.png"
        return path, lambda: read_mask(path)
    if role == "overlay":
        path = root / f"{stem}.png"
        return path, lambda: _read_overlay(str(path))
    if role == "tapvid file":
        (root / "tapvid_davis").mkdir()
        path = root / "tapvid_davis" / "tapvid_davis.pkl"
        return path, lambda: [pending.load() for pending in iter_tapvid("davis", root)]
    sequence = root / "0000"
    (sequence / "frames").mkdir(parents=True)
    (sequence / "frames" / "000.png").write_bytes(bombs.png_bytes(4, 4))
    if role == "kubric annotations":
        return sequence / "0000.npy", lambda: read_sequence(sequence)
    np.save(
        sequence / "0000.npy",
        np.array(
            {"coords": np.zeros((1, 2, 2), np.float32), "visibility": np.zeros((1, 2), bool)},
            dtype=object,
        ),
        allow_pickle=True,
    )
    return sequence / "frames" / "001.png", lambda: read_sequence(sequence)


# -- resource estimates --------------------------------------------------------------------


@st.composite
def resource_requests(draw: st.DrawFn) -> dict[str, Any]:
    """A tracking run: model preset, input size, frames, points, video size, budget."""
    return {
        "preset": draw(st.sampled_from(["tiny", "small", "taptrv2", "taptrv1"])),
        "input_size": (draw(st.integers(16, 4096)), draw(st.integers(16, 4096))),
        "num_frames": draw(st.integers(1, 100_000)),
        "num_points": draw(st.integers(1, 100_000)),
        "frame_size": (draw(st.integers(1, 8192)), draw(st.integers(1, 8192))),
        "whole_video": draw(st.booleans()),
        "backward": draw(st.booleans()),
        "budget": draw(st.integers(1, 2**45)),
    }


def check_estimate(request: dict[str, Any]) -> None:
    """Estimates a run; checks positivity, monotony and the refusal against the budget."""
    from taptr.config import get_config
    from taptr.memory_estimate import MemoryEstimateError, check_memory, estimate_tracking

    request = dict(request)
    budget = request.pop("budget")
    config = get_config(request.pop("preset"))
    base = estimate_tracking(config, **request)
    if not all(isinstance(v, int) and v > 0 for v in base.parts.values() if v):
        raise SilentError(f"parts {base.parts}")
    for knob in ("num_frames", "num_points"):
        larger = estimate_tracking(config, **dict(request, **{knob: request[knob] + 1}))
        if larger.total < base.total:
            raise SilentError(f"more {knob} gave a smaller estimate")
    height, width = request["input_size"]
    larger = estimate_tracking(config, **dict(request, input_size=(height + 8, width + 8)))
    if larger.total < base.total:
        raise SilentError("a larger input size gave a smaller estimate")
    with _env(TAPTR_MAX_MEMORY=str(budget)):
        try:
            check_memory(base, "tracking", "lower --input-size, fewer points or --max-frames")
        except MemoryEstimateError as error:
            if base.total <= budget or "\n" in str(error) or "--input-size" not in str(error):
                raise SilentError(f"refused within the budget, or badly: {error}") from None
            raise
        if base.total > budget:
            raise SilentError(f"{base.total:,} bytes accepted with a budget of {budget:,}")


CATEGORIES: dict[str, tuple[Any, Callable[[Any], Any]]] = {
    "images and videos, decoder by content": (decoder_inputs(), read_by_role),
    "checkpoint, lying record sizes": (lying_checkpoints(), read_watched_checkpoint),
    "checkpoint, logical tensor views": (view_checkpoints(), read_watched_checkpoint),
    "special files where a file belongs": (special_paths, read_special),
    "resource estimates before tracking": (resource_requests(), check_estimate),
}
"""The categories of this module, added to `tests.fuzz_targets.CATEGORIES`."""
