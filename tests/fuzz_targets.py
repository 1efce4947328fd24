"""Input categories of the fuzz suite: a hypothesis strategy and a target for each.

A target takes one generated input, writes it to a temporary folder, reads it through the
public reader and returns a description of a *valid* result, or raises. `classify` sorts
outcomes: a `ValueError` (every reader's documented error; `CheckpointError` and the
limit errors are ValueErrors) or `FileNotFoundError` is clean, any other exception is a
traceback, and a result that fails its validity check (NaN tracks, wrong shape or dtype) is
silent wrong output. `tests/test_fuzz.py` asserts that nothing is a traceback or silent;
`scripts/fuzz_report.py` counts the outcomes. The categories of issue 29 (decoders by content,
lying sizes, logical views, special files, resource estimates) are in `tests.fuzz_hostile`;
its `memory_bound` oracle (peak RSS growth per input) applies to every category. Issue 45's
(kept capture timings, downloads from a misbehaving Drive) are in `tests.fuzz_downloads`;
issue 51's (a corpus's output folder tampered with) in `tests.fuzz_corpus`, and
(tampered export folders: manifests and graphs) in `tests.fuzz_export`.
"""

from __future__ import annotations

import contextlib
import io
import os
import pickle
import struct
import tempfile
import traceback
import warnings
from collections.abc import Callable, Iterator
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hypothesis import strategies as st

from taptr.io.safe_pickle import ALLOWED
from tests import bombs, fuzz_corpus, fuzz_downloads, fuzz_export, fuzz_hostile, fuzz_options
from tests.fuzz_hostile import SilentError, memory_bound

CLEAN = (ValueError, FileNotFoundError)


def classify(target: Callable[[Any], Any], value: Any, problems: list[str] | None = None) -> str:
    """``"valid"``, ``"clean"``, ``"traceback"`` or ``"silent"`` for one input.

    Args:
        target: the reader of a category.
        value: one generated input.
        problems: collects the formatted traceback of each traceback or silent outcome.
    """
    try:
        with memory_bound(), warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore")
            target(value)
    except CLEAN:
        return "clean"
    except Exception as error:
        if problems is not None:
            problems.append("".join(traceback.format_exception(error)))
        return "silent" if isinstance(error, SilentError) else "traceback"
    return "valid"


def _check_sample(sample: Any) -> None:
    video, tracks, visible = sample.video, sample.tracks, sample.visible
    ok = (
        video.dtype == np.uint8
        and video.ndim == 4
        and video.shape[3] == 3
        and video.shape[0] >= 1
        and tracks.shape == (video.shape[0], tracks.shape[1], 2)
        and visible.shape == tracks.shape[:2]
        and visible.dtype == bool
        and np.isfinite(tracks).all()
    )
    if not ok:
        raise SilentError(f"bad sample {video.shape} {video.dtype} {tracks.shape} {visible.shape}")


def _mutate(data: bytes, edits: list[tuple[int, int, int]]) -> bytes:
    """Applies (kind, position, value) edits: 0 flip a byte, 1 truncate, 2 insert a byte."""
    buffer = bytearray(data)
    for kind, position, value in edits:
        if not buffer:
            break
        at = position % len(buffer)
        if kind == 0:
            buffer[at] ^= value or 1
        elif kind == 1:
            del buffer[at:]
        else:
            buffer.insert(at, value)
    return bytes(buffer)


EDITS = st.lists(
    st.tuples(st.integers(0, 2), st.integers(0, 2**31), st.integers(0, 255)), min_size=1, max_size=4
)


# -- TAP-Vid pickles -----------------------------------------------------------------------


def read_tapvid(data: bytes) -> None:
    """Loads every video of a DAVIS-layout pickle holding ``data``."""
    from taptr.data.tapvid import iter_tapvid

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "tapvid_davis.pkl"
        path.write_bytes(data)
        for pending in iter_tapvid("davis", path):
            _check_sample(pending.load())


@cache
def _valid_pickles() -> tuple[bytes, ...]:
    item = bombs.davis_item(frames=3, size=6)
    encoded = dict(item, video=[bombs.png_bytes(6, 6, v) for v in (0, 80, 160)])
    return tuple(
        pickle.dumps({"a": chosen}, protocol=protocol)
        for chosen in (item, encoded)
        for protocol in (2, 4, 5)
    )


mutated_pickles = st.builds(
    lambda index, edits: _mutate(_valid_pickles()[index], edits),
    st.integers(0, 5),
    EDITS,
)
"""Valid TAP-Vid pickles with a few bytes flipped, cut or inserted."""

_GADGETS = [
    *(bombs.global_op(module, name) for module, name in sorted(ALLOWED)),
    bombs.global_op("os", "system"),
    bombs.global_op("builtins", "eval"),
    bombs.global_op("numpy._core.multiarray", "_reconstruct") + bombs.global_op("numpy", "ndarray"),
    *(bombs.int_op(v) for v in (0, 1, -1, 3, 2**31, 2**40, 12 * bombs.GIB)),
    *(b"K" + bytes([v]) for v in (0, 1, 2, 8)),
    *(b"\x8e" + struct.pack("<Q", n) for n in (0, 3, 2**40)),
    *(b"\x8d" + struct.pack("<Q", n) for n in (1, 2**40)),
    *(b"\x96" + struct.pack("<Q", n) for n in (2, 2**40)),
    b"C\x04abcd", b"\x8c\x01b", b"\x8c\x02O8", b"\x8c\x02u1", b"\x8c\x06latin1", b"\x8c\x03hex",
    b"G" + struct.pack(">d", float("nan")), b"N", b"\x88", b"\x89",
    b"(", b"t", b")", b"\x85", b"\x86", b"\x87", b"R", b"b", b"]", b"}", b"l", b"e", b"a",
    b"s", b"u", b"0", b"2", b"\x94", b"h\x00", b"h\x01", b"\x81", b"\x8f", b"\x90", b"\x91",
]  # fmt: skip

opcode_pickles = st.lists(st.sampled_from(_GADGETS), max_size=24).map(
    lambda parts: b"\x80\x04" + b"".join(parts) + b"."
)
"""Pickles assembled from allowed and refused globals, huge numbers and opcodes: the
restricted unpickler's attack surface."""

_VIDEOS = st.one_of(
    st.integers(0, 3)
    .flatmap(lambda t: st.sampled_from([(t, 4, 4, 3), (t, 4, 4), (t, 0, 4, 3), (t, 4, 4, 1)]))
    .map(lambda shape: np.zeros(shape, np.uint8)),
    st.integers(0, 3).map(lambda t: [bombs.png_bytes(4, 4, 9)] * t),
    st.integers(1, 3).map(lambda t: [bombs.png_bomb(60_000, 60_000)] * t),
    st.lists(st.one_of(st.binary(max_size=16), st.integers(-3, 2**40), st.none()), max_size=3),
    st.sampled_from([None, "video", 3, np.zeros((2, 4, 4, 3), np.float32)]),
)
_NUMBERS = st.sampled_from([np.float64, np.float32, np.int32, np.complex64, np.bool_, object])


@st.composite
def tapvid_items(draw: st.DrawFn) -> bytes:
    """Pickles of one item with generated video, points and occlusion entries."""
    video = draw(_VIDEOS)
    frames = draw(st.integers(0, 3))
    points = draw(st.integers(0, 2))
    values = draw(st.sampled_from([0.5, np.nan, np.inf, -1e300, 1e300]))
    shape = draw(st.sampled_from([(points, frames, 2), (points, frames), (frames, points, 2)]))
    item: dict[str, Any] = {
        "video": video,
        "points": _cast(np.full(shape, values), draw(_NUMBERS)),
        "occluded": np.zeros(shape[:2], draw(_NUMBERS)),
    }
    for key in draw(st.sets(st.sampled_from(sorted(item)), max_size=1)):
        del item[key]
    return pickle.dumps({"v": item}, protocol=4)


def _cast(array: np.ndarray, dtype: Any) -> np.ndarray:
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return array.astype(dtype)


# -- Kubric folders ------------------------------------------------------------------------


def read_kubric(files: dict[str, bytes]) -> None:
    """Reads sequence ``0000`` made of ``files`` (relative path → content)."""
    from taptr.data.kubric import read_sequence

    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder) / "0000"
        for name, content in files.items():
            (root / name).parent.mkdir(parents=True, exist_ok=True)
            (root / name).write_bytes(content)
        _check_sample(read_sequence(root))


def _npy(array: Any, header: dict[str, Any] | None = None) -> bytes:
    stream = io.BytesIO()
    if header is None:
        np.save(stream, array, allow_pickle=True)
        return stream.getvalue()
    np.lib.format.write_array_header_1_0(stream, header)
    return stream.getvalue() + np.ascontiguousarray(array).tobytes()


@st.composite
def kubric_folders(draw: st.DrawFn) -> dict[str, bytes]:
    """A sequence with 2 frames whose annotation file is generated or mutated."""
    frames = {f"frames/{t:03d}.png": bombs.png_bytes(8, 8, 40 * t) for t in range(2)}
    coords = np.full((3, 2, 2), draw(st.sampled_from([2.0, np.nan, -np.inf])), np.float32)
    annotations = {"coords": coords, "visibility": np.zeros((3, 2), bool)}
    kind = draw(st.integers(0, 3))
    if kind == 0:  # a mutated valid file
        content = _mutate(_npy(np.array(annotations, dtype=object)), draw(EDITS))
    elif kind == 1:  # a plain array with a mutated header
        shape = tuple(draw(st.lists(st.integers(-1, 2**40), max_size=4)))
        descr = draw(st.sampled_from(["<f4", "<f8", "|u1", "|O", "<c8", "|V16", "<U4", ">i8"]))
        header = {"descr": descr, "fortran_order": draw(st.booleans()), "shape": shape}
        try:
            content = _npy(np.zeros(draw(st.integers(0, 16)), np.uint8), header)
        except (ValueError, TypeError, OverflowError):
            content = b""
    elif kind == 2:  # generated annotation contents
        value = draw(
            st.sampled_from(
                [
                    np.zeros((3, 2, 2), np.complex64),
                    np.zeros((3, 2), np.float32),
                    np.array(["a", "b"]),
                    "text",
                    None,
                ]
            )
        )
        key = draw(st.sampled_from(["coords", "visibility"]))
        content = _npy(np.array(dict(annotations, **{key: value}), dtype=object))
    else:  # an attack pickle after a valid object-array header
        header = {"descr": "|O", "fortran_order": False, "shape": ()}
        stream = io.BytesIO()
        np.lib.format.write_array_header_1_0(stream, header)
        content = stream.getvalue() + draw(opcode_pickles)
    return {**frames, "0000.npy": content}


# -- checkpoints ---------------------------------------------------------------------------


def read_checkpoint(data: bytes) -> None:
    """Loads a checkpoint file holding ``data`` and checks the model's weights are finite."""
    from taptr.weights.checkpoint import load_checkpoint, read_visibility_threshold

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "model.pth"
        path.write_bytes(data)
        model = load_checkpoint(path)
        threshold = read_visibility_threshold(path)
    if not all(
        torch.isfinite(p).all() for p in model.state_dict().values() if p.is_floating_point()
    ):
        raise SilentError("a loaded model has non-finite weights")
    if threshold is not None and not 0 < threshold < 1:
        raise SilentError(f"visibility threshold {threshold}")


@cache
def _tiny_checkpoint() -> dict[str, Any]:
    from taptr import build_model
    from taptr.weights.checkpoint import checkpoint_dict

    torch.manual_seed(0)
    return checkpoint_dict(build_model("tiny"))


@cache
def _tiny_file(legacy: bool) -> bytes:
    stream = io.BytesIO()
    torch.save(_tiny_checkpoint(), stream, _use_new_zipfile_serialization=not legacy)
    return stream.getvalue()


_CONFIG_VALUES = st.one_of(
    st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=4),
    st.lists(st.integers(-5, 5000), max_size=4),
    st.none(),
    st.booleans(),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
)
_DTYPES = st.sampled_from(
    [torch.float16, torch.float64, torch.int64, torch.int8, torch.bool, torch.complex64]
)


@st.composite
def checkpoint_mutations(draw: st.DrawFn) -> bytes:
    """The tiny model's checkpoint with a mutated config, weight or entry, saved."""
    data = dict(_tiny_checkpoint())
    config = dict(data["config"])
    weights = dict(data["model"])
    names = sorted(weights)
    kind = draw(st.integers(0, 4))
    if kind == 0:
        key = draw(st.sampled_from([*sorted(config), "bogus", "backbone"]))
        config[key] = draw(_CONFIG_VALUES)
    elif kind == 1:
        name = draw(st.sampled_from(names))
        action = draw(st.integers(0, 4))
        if action == 0:
            del weights[name]
        elif action == 1:
            shape = draw(st.lists(st.integers(0, 5), max_size=3))
            weights[name] = torch.zeros(shape)
        elif action == 2:
            weights[name] = weights[name].to(draw(_DTYPES))
        elif action == 3:
            value = draw(st.sampled_from([float("nan"), float("inf"), -float("inf")]))
            weights[name] = torch.full_like(weights[name], value)
        else:
            weights[name] = draw(st.sampled_from([3, "w", [1.0], None]))
    elif kind == 2:
        weights[draw(st.text(min_size=1, max_size=8))] = torch.zeros(2)
    elif kind == 3:
        key = draw(st.sampled_from(["format", "version", "config", "model"]))
        data[key] = draw(st.one_of(_CONFIG_VALUES, st.just(torch.zeros(3))))
        if key == "model":
            weights = data[key]
    else:
        data["visibility_threshold"] = draw(_CONFIG_VALUES)
    if kind not in (3,) or data.get("config") is config:
        data["config"] = config
    if not (kind == 3 and data.get("model") is not weights):
        data["model"] = weights
    stream = io.BytesIO()
    torch.save(data, stream, _use_new_zipfile_serialization=draw(st.booleans()))
    return stream.getvalue()


checkpoint_bytes = st.builds(
    lambda legacy, edits: _mutate(_tiny_file(legacy), edits), st.booleans(), EDITS
)
"""The tiny model's checkpoint file (zip or legacy) with a few bytes flipped, cut or inserted."""


# -- weights under a wrong name ------------------------------------------------------------

_NAMED_PRESETS = ("tiny", "tiny-v3", "small")
"""Small architectures the fuzzed names promise and the fuzzed files hold."""


def read_named_weights(case: tuple[str, str, bool, float | None]) -> None:
    """Saves a ``found`` model under the file name of weights that promise ``expected``.

    The file is loaded by name (`taptr.weights.registry.load_model`, offline, from the
    weights folder);
    a load that returns a model of another architecture than the name's is silent wrong
    output, a refusal of the name's own architecture is a traceback.
    """
    from taptr.config import get_config
    from taptr.weights import registry
    from taptr.weights.checkpoint import CheckpointError
    from taptr.weights.drive import ManualWeights
    from taptr.weights.identity import same_architecture

    found, expected, half, threshold = case
    entry = ManualWeights("https://drive.google.com/file/d/fuzz", "fuzz.pth", expected, "x", "")
    with tempfile.TemporaryDirectory() as folder, _named_in(folder, entry):
        Path(folder, "fuzz.pth").write_bytes(_named_file(found, half, threshold))
        try:
            model = registry.load_model("fuzz-official").model
        except CheckpointError:
            if same_architecture(get_config(found), get_config(expected)):
                raise AssertionError(f"{found} refused under a name of {expected}") from None
            raise
    if not same_architecture(model.config, get_config(expected)):
        raise SilentError(f"{found} weights loaded under a name that promises {expected}")


@contextlib.contextmanager
def _named_in(folder: str, entry: Any) -> Iterator[None]:
    """``fuzz-official`` registered as Drive weights read (offline) from ``folder``."""
    from taptr.weights import registry

    saved = {key: os.environ.get(key) for key in ("TAPTR_WEIGHTS_DIR", "TAPTR_OFFLINE")}
    os.environ.update(TAPTR_WEIGHTS_DIR=folder, TAPTR_OFFLINE="1")
    registry.MANUAL["fuzz-official"] = entry
    try:
        yield
    finally:
        del registry.MANUAL["fuzz-official"]
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


@cache
def _named_file(preset: str, half: bool, threshold: float | None) -> bytes:
    from taptr import build_model
    from taptr.weights.checkpoint import save_checkpoint

    torch.manual_seed(0)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "model.pth"
        save_checkpoint(build_model(preset), path, half=half, visibility_threshold=threshold)
        return path.read_bytes()


named_weights = st.tuples(
    st.sampled_from(_NAMED_PRESETS),
    st.sampled_from(_NAMED_PRESETS),
    st.booleans(),
    st.sampled_from([None, 0.3]),
)
"""(architecture of the file, architecture its name promises, float16, a stored threshold)."""


# -- videos and frame folders --------------------------------------------------------------


def read_video_files(files: dict[str, bytes]) -> None:
    """Reads a video file (one entry) or a frame folder (several) through `read_video`."""
    from taptr.io.video import read_video, video_info

    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        for name, content in files.items():
            (root / name).write_bytes(content)
        source = root / next(iter(files)) if len(files) == 1 else root
        video = read_video(source)
        info = video_info(source)
    if video.dtype != np.uint8 or video.ndim != 4 or video.shape[3] != 3 or not len(video):
        raise SilentError(f"bad video {video.shape} {video.dtype}")
    if (info.height, info.width) != video.shape[1:3]:
        raise SilentError(f"video_info says {info.height}x{info.width}, frames {video.shape}")


@st.composite
def video_inputs(draw: st.DrawFn) -> dict[str, bytes]:
    """A generated mp4/gif/avi file or png/jpg frame folder, possibly mutated."""
    import cv2

    frames = draw(st.integers(0, 3))
    height, width = draw(st.integers(1, 24)), draw(st.integers(1, 24))
    channels = draw(st.sampled_from([1, 3, 4]))
    dtype = draw(st.sampled_from([np.uint8, np.uint16]))
    rng = np.random.default_rng(draw(st.integers(0, 9)))
    stack = rng.integers(0, 256, (frames, height, width, channels)).astype(dtype)
    suffix = draw(st.sampled_from([".png", ".jpg", ".mp4", ".avi", ".gif"]))
    files: dict[str, bytes] = {}
    if suffix in (".png", ".jpg"):
        for index, frame in enumerate(stack):
            ok, encoded = cv2.imencode(
                suffix, frame if suffix == ".png" else frame.astype(np.uint8)
            )
            files[f"{index}{suffix}"] = encoded.tobytes() if ok else b""
        if not files:
            files["0.png"] = b""
    else:
        files[f"clip{suffix}"] = _encode(stack, suffix)
    if draw(st.booleans()):
        name = draw(st.sampled_from(sorted(files)))
        files[name] = _mutate(files[name], draw(EDITS))
    if draw(st.integers(0, 9)) == 0:
        files[draw(st.sampled_from(["bomb.png", "clip.mp4"]))] = bombs.png_bomb(60_000, 60_000)
    return files


def _encode(stack: np.ndarray, suffix: str) -> bytes:
    import av

    stream = io.BytesIO()
    codec = {".mp4": "libx264", ".avi": "mpeg4", ".gif": "gif"}[suffix]
    with av.open(stream, "w", format=suffix[1:]) as container:
        video = container.add_stream(codec, rate=10)
        height, width = stack.shape[1:3]
        video.width, video.height = width + width % 2, height + height % 2
        video.pix_fmt = "rgb8" if suffix == ".gif" else "yuv420p"
        for frame in stack:
            rgb = np.zeros((video.height, video.width, 3), np.uint8)
            rgb[:height, :width] = frame[..., :1].astype(np.uint8)
            container.mux(video.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")))
        container.mux(video.encode())
    return stream.getvalue()


CATEGORIES: dict[str, tuple[Any, Callable[[Any], Any]]] = {
    "TAP-Vid pickle, mutated bytes": (mutated_pickles, read_tapvid),
    "TAP-Vid pickle, unpickler attacks": (opcode_pickles, read_tapvid),
    "TAP-Vid pickle, generated items": (tapvid_items(), read_tapvid),
    "Kubric folder (.npy headers, contents)": (kubric_folders(), read_kubric),
    "checkpoint, key/shape/dtype/config mutations": (checkpoint_mutations(), read_checkpoint),
    "checkpoint, mutated bytes": (checkpoint_bytes, read_checkpoint),
    "video file / frame folder": (video_inputs(), read_video_files),
    "named weights, another architecture": (named_weights, read_named_weights),
    **fuzz_hostile.CATEGORIES,
    **fuzz_options.CATEGORIES,
    **fuzz_downloads.CATEGORIES,
    **fuzz_corpus.CATEGORIES,
    **fuzz_export.CATEGORIES,
}
"""Every fuzzed input category: (strategy, target)."""
