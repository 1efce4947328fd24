"""Regression tests for hostile and careless input files (issue 15, items 1, 3, 5 and 6).

Every reproducer of the review is rebuilt here in a few kilobytes: each must give a one-line
`ValueError` naming the file (or a warning), fast and without allocating what the file
declares. `tests.bombs` builds the files.
"""

from __future__ import annotations

import io
import pickle
import time
import warnings
import zipfile

import numpy as np
import pytest
import torch

import taptr
from taptr.cli.main import main
from taptr.data.check import check_kubric_folder
from taptr.data.kubric import read_sequence, write_sequence
from taptr.data.tapvid import iter_tapvid
from taptr.io import limits
from taptr.io.safe_npy import load_npy
from taptr.io.safe_pickle import PickleBombError, UnsafePickleError, load_pickle
from taptr.io.video import read_video, write_video
from taptr.types import TrackingSample
from taptr.weights.checkpoint import (
    CheckpointError,
    UnsafeCheckpointError,
    load_checkpoint,
    read_file,
    read_visibility_threshold,
    save_checkpoint,
)
from tests import bombs


def _one_line(error: pytest.ExceptionInfo[BaseException], *names: str) -> str:
    message = str(error.value)
    assert "\n" not in message, message
    for name in names:
        assert name in message, message
    return message


# -- item 1: tiny files that asked for gigabytes ------------------------------------------


@pytest.mark.parametrize("name", sorted(bombs.pickle_bombs()))
def test_tapvid_pickle_bombs_give_one_line_errors(tmp_path, name):
    path = tmp_path / "tapvid_davis.pkl"
    path.write_bytes(bombs.pickle_bombs()[name])
    with pytest.raises(ValueError) as error:
        list(iter_tapvid("davis", path))
    _one_line(error, str(path))


def test_55_byte_bytearray_pickle_does_not_ask_for_12_gib(tmp_path):
    path = tmp_path / "tapvid_davis.pkl"
    path.write_bytes(bombs.pickle_bombs()["bytearray_call"])
    assert path.stat().st_size <= 55
    with pytest.raises(UnsafePickleError, match="bytearray"):
        load_pickle(path)


def test_pickle_length_prefix_past_the_end_is_refused_before_reading(tmp_path):
    path = tmp_path / "x.pkl"
    path.write_bytes(bombs.pickle_bombs()["binbytes8_length"])
    with pytest.raises(PickleBombError, match="12,884,901,888 bytes"):
        load_pickle(path)


def test_pickle_memo_index_bomb_is_refused(tmp_path):
    path = tmp_path / "tapvid_davis.pkl"
    path.write_bytes(bombs.MEMO_BOMB)
    with pytest.raises(PickleBombError, match="memo index of 2,147,483,647"):
        load_pickle(path)


def test_unknown_codec_in_a_pickle_is_a_one_line_error(tmp_path):
    path = tmp_path / "tapvid_davis.pkl"
    path.write_bytes(bombs.pickle_bombs()["codec_unknown"])
    with pytest.raises(ValueError) as error:
        load_pickle(path)
    _one_line(error, str(path), "bogus")


def test_valid_pickles_of_every_protocol_still_load(tmp_path):
    item = bombs.davis_item()
    item["points"] = np.ascontiguousarray(item["points"].transpose(1, 0, 2)).transpose(1, 0, 2)
    for protocol in range(2, pickle.HIGHEST_PROTOCOL + 1):
        path = tmp_path / f"p{protocol}.pkl"
        path.write_bytes(pickle.dumps({"v": item}, protocol=protocol))
        sample = next(iter_tapvid("davis", path)).load()
        np.testing.assert_array_equal(sample.video, item["video"])
        np.testing.assert_allclose(sample.tracks[:, :, 0], item["points"][..., 0].T * 8 - 0.5)


def _frames_pickle(path, frame: bytes, count: int):
    """A DAVIS pickle of ``count`` references to one encoded frame, with matching points."""
    item = {
        "video": [frame] * count,  # pickled once, referenced count times
        "points": np.full((1, count, 2), 0.5),
        "occluded": np.zeros((1, count), bool),
    }
    path.write_bytes(pickle.dumps({"bomb": item}, protocol=4))
    return path


def test_davis_pickle_declaring_20000_frames_fails_fast(tmp_path):
    path = _frames_pickle(tmp_path / "tapvid_davis.pkl", bombs.png_bytes(256, 256), 20_000)
    assert path.stat().st_size < 400_000
    pending = next(iter_tapvid("davis", path))
    start = time.perf_counter()
    with pytest.raises(limits.LimitError) as error:
        pending.load()
    assert time.perf_counter() - start < 2
    _one_line(error, str(path), "20,000 frames", "TAPTR_MAX_VIDEO_FRAMES")


def test_png_frames_decoding_to_gigabytes_fail_before_decoding(tmp_path):
    path = _frames_pickle(tmp_path / "tapvid_davis.pkl", bombs.png_bytes(4096, 4096), 92)
    assert path.stat().st_size < 100_000
    start = time.perf_counter()
    with pytest.raises(limits.LimitError) as error:
        next(iter_tapvid("davis", path)).load()
    assert time.perf_counter() - start < 2
    _one_line(error, str(path), "TAPTR_MAX_VIDEO_BYTES")


def test_png_decompression_bomb_in_a_pickle_is_a_one_line_error(tmp_path):
    path = _frames_pickle(tmp_path / "tapvid_davis.pkl", bombs.png_bomb(), 2)
    with pytest.raises(ValueError) as error:
        next(iter_tapvid("davis", path)).load()
    _one_line(error, str(path), "frame 0", "10,000,000,000 pixels", "TAPTR_MAX_IMAGE_PIXELS")


def test_a_raised_limit_lets_a_large_video_through(tmp_path, monkeypatch):
    path = _frames_pickle(tmp_path / "tapvid_davis.pkl", bombs.png_bytes(64, 64), 30)
    monkeypatch.setenv("TAPTR_MAX_VIDEO_FRAMES", "20")
    with pytest.raises(limits.LimitError):
        next(iter_tapvid("davis", path)).load()
    monkeypatch.setenv("TAPTR_MAX_VIDEO_FRAMES", "30")
    assert next(iter_tapvid("davis", path)).load().video.shape == (30, 64, 64, 3)


def test_frame_bomb_through_the_eval_cli_exits_2(tmp_path, capsys):
    path = _frames_pickle(tmp_path / "tapvid_davis.pkl", bombs.png_bytes(256, 256), 20_000)
    status = main(
        ["eval", "--dataset", "davis", "--root", str(path), "--tracker", "static"]
        + ["--out", str(tmp_path / "out")]
    )
    assert status == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert "TAPTR_MAX_VIDEO_FRAMES" in err.strip().splitlines()[-1]


def _kubric_folder(root):
    sample = TrackingSample(
        np.zeros((8, 32, 32, 3), np.uint8),
        np.full((8, 4, 2), 5.0, np.float32),
        np.ones((8, 4), bool),
    )
    for name in ("0000", "0001"):
        write_sequence(root / name, sample)
    return root


def test_128_byte_npy_declaring_7_tib_gives_one_line_errors(tmp_path, capsys):
    root = _kubric_folder(tmp_path / "kubric")
    bomb = bombs.npy_header_bomb(root / "0000" / "0000.npy")
    assert bomb.stat().st_size == 128
    with pytest.raises(ValueError) as error:
        read_sequence(root / "0000")
    _one_line(error, str(bomb), "8,000,000,000,000 bytes")
    report = check_kubric_folder(root)
    assert [f.where for f in report.errors] == [str(root / "0000")]
    assert main(["check-data", str(root)]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and "8,000,000,000,000 bytes" in err


def test_npy_with_an_unterminated_header_is_a_one_line_error(tmp_path):
    root = _kubric_folder(tmp_path / "kubric")
    header = b"{'descr': '<f4', 'fortran_order': False, 'shape': (3,".ljust(117) + b"\n"
    bomb = root / "0000" / "0000.npy"
    bomb.write_bytes(b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header)
    with pytest.raises(ValueError) as error:
        read_sequence(root / "0000")
    _one_line(error, str(bomb), "not a .npy file")


def test_npy_with_a_negative_shape_is_a_one_line_error(tmp_path):
    # a negative product, which numpy's int64 product wraps to 6.9e18 elements (55 EB)
    bomb = bombs.npy_header_bomb(tmp_path / "negative.npy", shape=(-5, 2**61))
    with pytest.raises(ValueError) as error:
        load_npy(bomb)
    _one_line(error, str(bomb), "negative shape")


def test_128_byte_npy_stops_training_with_one_line(tmp_path, capsys):
    root = _kubric_folder(tmp_path / "kubric")
    bombs.npy_header_bomb(root / "0000" / "0000.npy")
    status = main(
        ["train", "preset=small", "steps=1", f"data.root={root}", f"data.val_root={root}"]
        + ["model.d_model=32", "data.num_points=2", "data.num_workers=0"]
        + ["--out", str(tmp_path / "run")]
    )
    assert status == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "0000.npy: the header declares" in err


def test_kubric_frame_decompression_bomb(tmp_path):
    root = _kubric_folder(tmp_path / "kubric")
    (root / "0000" / "frames" / "003.png").write_bytes(bombs.png_bomb())
    with pytest.raises(ValueError) as error:
        read_sequence(root / "0000")
    _one_line(error, "003.png", "10,000,000,000 pixels")


def test_frame_folder_decompression_bomb(tmp_path):
    for index in range(2):
        (tmp_path / f"{index}.png").write_bytes(bombs.png_bytes(8, 8))
    (tmp_path / "2.png").write_bytes(bombs.png_bomb())
    with pytest.raises(ValueError) as error:
        read_video(tmp_path)
    _one_line(error, "2.png", "TAPTR_MAX_IMAGE_PIXELS")


def test_video_over_the_memory_budget_fails_before_decoding(tmp_path, monkeypatch):
    frames = np.zeros((12, 64, 64, 3), np.uint8)
    path = write_video(tmp_path / "v.mp4", frames, fps=10)
    monkeypatch.setenv("TAPTR_MAX_VIDEO_BYTES", str(64 * 64 * 3 * 11))
    import taptr.io.video as video_io

    monkeypatch.setattr(video_io, "_decode", lambda *a: pytest.fail("decoded"))
    with pytest.raises(limits.LimitError) as error:
        read_video(path)
    _one_line(error, str(path), "12 frames of 64x64", "TAPTR_MAX_VIDEO_BYTES")


def test_video_budget_counts_frames_the_header_does_not_declare(tmp_path, monkeypatch):
    for index in range(5):
        (tmp_path / f"{index}.png").write_bytes(bombs.png_bytes(8, 8))
    monkeypatch.setenv("TAPTR_MAX_VIDEO_BYTES", str(8 * 8 * 3 * 4))
    with pytest.raises(limits.LimitError, match="TAPTR_MAX_VIDEO_BYTES"):
        read_video(tmp_path)
    assert read_video(tmp_path, max_frames=4).shape == (4, 8, 8, 3)


def _write(path, data: bytes):
    path.write_bytes(data)
    return path


def _tiny_checkpoint(tmp_path, name="tiny.pth", **changes):
    torch.manual_seed(0)
    model = taptr.build_model("tiny")
    data = taptr.weights.checkpoint.checkpoint_dict(model)
    data.update(changes)
    path = tmp_path / name
    torch.save(data, path)
    return path, data


@pytest.mark.parametrize(
    ("builder", "message"),
    [
        (lambda d: bombs.call_checkpoint(d / "c.pth", bytearray, 12 * bombs.GIB), "bytearray"),
        (lambda d: bombs.call_checkpoint(d / "c.pth", torch.FloatTensor, bombs.GIB), "FloatTensor"),
        (lambda d: bombs.call_checkpoint(d / "c.pth", torch._utils._rebuild_qtensor, 1), "quantiz"),
        (
            lambda d: bombs.torch_zip(
                d / "c.pth",
                {"w": bombs.tensor_ref("0", 3 * bombs.GIB)},
                {"0": (torch.FloatStorage, 3 * bombs.GIB, bytes(12))},
            ),
            "declares 12,884,901,888 bytes",
        ),
        (lambda d: bombs.legacy_checkpoint(d / "c.pth", 3 * bombs.GIB), "tensor data"),
        (lambda d: _write(d / "c.pth", bombs.MEMO_BOMB), "memo index"),
    ],
    ids=["bytearray", "legacy_constructor", "qtensor", "zip_storage", "legacy_storage", "memo"],
)
def test_pth_bombs_are_refused_before_torch_load(tmp_path, builder, message):
    path = builder(tmp_path)
    assert path.stat().st_size < 2_000
    with pytest.raises(CheckpointError) as error:
        load_checkpoint(path)
    _one_line(error, str(path), message)


def test_checkpoint_file_and_tensor_bytes_are_bounded(tmp_path, monkeypatch):
    path, _ = _tiny_checkpoint(tmp_path)
    monkeypatch.setenv("TAPTR_MAX_CHECKPOINT_BYTES", "1K")
    with pytest.raises(CheckpointError) as error:
        read_file(path)
    _one_line(error, str(path), "TAPTR_MAX_CHECKPOINT_BYTES")
    monkeypatch.setenv("TAPTR_MAX_CHECKPOINT_BYTES", str(path.stat().st_size))
    with zipfile.ZipFile(path) as archive:  # the file passes, its records' total does not
        records = sum(r.file_size for r in archive.infolist())
    assert records > path.stat().st_size or read_file(path)


def test_config_is_validated_and_weights_checked_before_building(tmp_path, monkeypatch):
    _, data = _tiny_checkpoint(tmp_path)
    huge = dict(data["config"], d_model=4096, ffn_dim=16384, decoder_layers=32, num_heads=64)
    path = tmp_path / "huge.pth"
    torch.save(dict(data, config=huge), path)
    devices = []
    real_build = taptr.weights.checkpoint.build_model
    monkeypatch.setattr(
        taptr.weights.checkpoint,
        "build_model",
        lambda config: devices.append(str(torch.get_default_device())) or real_build(config),
    )
    with pytest.raises(CheckpointError, match="does not match the model"):
        load_checkpoint(path)
    assert "meta" in devices and "cpu" not in devices  # only the skeleton, which costs nothing


def test_checkpoint_version_of_the_wrong_type_is_refused(tmp_path):
    _, data = _tiny_checkpoint(tmp_path)
    path = tmp_path / "version.pth"
    torch.save(dict(data, version=torch.zeros(3)), path)
    with pytest.raises(CheckpointError) as error:
        load_checkpoint(path)
    _one_line(error, str(path), "version")


@pytest.mark.parametrize(
    ("change", "key"),
    [
        ({"d_model": "256"}, "d_model"),
        ({"num_heads": 10_000}, "num_heads"),
        ({"input_size": [60000, 60000]}, "input_size"),
        ({"input_size": [0, 0]}, "input_size"),
        ({"backbone": "resnet"}, "backbone"),
        ({"window_size": 1.5}, "window_size"),
        ({"position_update": "no"}, "position_update"),
    ],
)
def test_checkpoint_config_with_wrong_types_names_the_key(tmp_path, change, key):
    _, data = _tiny_checkpoint(tmp_path)
    path = tmp_path / "bad_config.pth"
    torch.save(dict(data, config=dict(data["config"], **change)), path)
    with pytest.raises(CheckpointError) as error:
        load_checkpoint(path)
    _one_line(error, str(path), key)


# -- item 3: silently wrong output ---------------------------------------------------------


def test_nan_weights_are_refused_naming_the_checkpoint(tmp_path):
    _, data = _tiny_checkpoint(tmp_path)
    key = next(k for k, v in data["model"].items() if v.is_floating_point())
    data["model"][key] = torch.full_like(data["model"][key], float("nan"))
    path = tmp_path / "nan.pth"
    torch.save(data, path)
    with pytest.raises(CheckpointError, match="non-finite") as error:
        load_checkpoint(path)
    assert str(path) in str(error.value) and key in str(error.value)


@pytest.mark.parametrize("dtype", [torch.int64, torch.complex64, torch.bool])
def test_integer_or_complex_weights_are_refused(tmp_path, dtype):
    _, data = _tiny_checkpoint(tmp_path)
    key = next(k for k, v in data["model"].items() if v.is_floating_point())
    data["model"][key] = data["model"][key].to(dtype)
    path = tmp_path / "typed.pth"
    torch.save(data, path)
    with pytest.raises(CheckpointError, match="wrong dtype") as error:
        load_checkpoint(path)
    assert key in str(error.value)


def test_non_finite_ground_truth_in_a_davis_pickle_names_the_video(tmp_path):
    item = bombs.davis_item()
    item["points"][0, 1, 0] = np.nan
    path = tmp_path / "tapvid_davis.pkl"
    path.write_bytes(pickle.dumps({"bear": item}))
    with pytest.raises(ValueError) as error:
        next(iter_tapvid("davis", path)).load()
    _one_line(error, str(path), "'bear'", "non-finite")


def test_ground_truth_beyond_float32_is_refused(tmp_path):
    item = bombs.davis_item()
    item["points"][0, 1, 0] = 1e300  # finite, but inf as float32 pixels
    path = tmp_path / "tapvid_davis.pkl"
    path.write_bytes(pickle.dumps({"bear": item}))
    with pytest.raises(ValueError, match="too large"):
        next(iter_tapvid("davis", path)).load()


def test_complex_ground_truth_is_refused(tmp_path):
    item = bombs.davis_item()
    item["points"] = item["points"] + 1j
    path = tmp_path / "tapvid_davis.pkl"
    path.write_bytes(pickle.dumps({"bear": item}))
    with pytest.raises(ValueError, match="real numbers"):
        next(iter_tapvid("davis", path)).load()


def test_truncated_video_warns_with_both_frame_counts(tmp_path):
    rng = np.random.default_rng(0)
    path = write_video(tmp_path / "v.mp4", rng.integers(0, 256, (12, 64, 64, 3), np.uint8), 10)
    import av

    with av.open(str(path)) as container:
        second = [p.pos for p in container.demux(container.streams.video[0]) if p.size][1]
    truncated = tmp_path / "truncated.mp4"
    truncated.write_bytes(path.read_bytes()[:second])
    with pytest.warns(UserWarning, match=r"decoded 1 frames where the container declares 12"):
        assert len(read_video(truncated)) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(read_video(path)) == 12  # a whole file: no warning


def test_bad_visibility_threshold_names_the_file(tmp_path):
    path, _ = _tiny_checkpoint(tmp_path, visibility_threshold="high")
    with pytest.raises(CheckpointError) as error:
        read_visibility_threshold(path)
    _one_line(error, str(path), "visibility_threshold")


# -- item 6: misleading messages -----------------------------------------------------------


class _Payload:
    def __reduce__(self):
        import os

        return (os.system, ("echo should-never-run",))


def test_legacy_malicious_checkpoint_gets_our_message(tmp_path):
    path = tmp_path / "legacy.pth"
    torch.save({"x": _Payload()}, path, _use_new_zipfile_serialization=False)
    with pytest.raises(UnsafeCheckpointError) as error:
        load_checkpoint(path)
    message = _one_line(error, str(path), "system")
    assert "weights_only" not in message


def test_unsupported_operand_names_the_file(tmp_path):
    path = tmp_path / "protocol0.pth"
    path.write_bytes(pickle.dumps({"a": "x"}, protocol=0))
    with pytest.raises(CheckpointError) as error:
        load_checkpoint(path)
    message = _one_line(error, str(path))
    assert "weights_only" not in message


def test_load_checkpoint_never_raises_a_raw_unpickling_error(tmp_path):
    good, _ = _tiny_checkpoint(tmp_path)
    with zipfile.ZipFile(good) as archive:
        records = {info.filename: archive.read(info) for info in archive.infolist()}
    name = next(n for n in records if n.endswith("data.pkl"))
    records[name] = records[name][:20] + b"\xff" + records[name][21:]  # an unknown opcode
    path = tmp_path / "corrupt.pth"
    with zipfile.ZipFile(path, "w") as archive:
        for record, content in records.items():
            archive.writestr(record, content)
    with pytest.raises(CheckpointError) as error:
        load_checkpoint(path)
    assert not isinstance(error.value, pickle.UnpicklingError) or isinstance(
        error.value, ValueError
    )
    _one_line(error, str(path))


def test_valid_checkpoints_still_load(tmp_path):
    torch.manual_seed(0)
    model = taptr.build_model("tiny")
    path = save_checkpoint(model, tmp_path / "ok.pth", half=True, visibility_threshold=0.4)
    assert load_checkpoint(path).config == model.config
    assert read_visibility_threshold(path) == pytest.approx(0.4)
    legacy = tmp_path / "legacy_ok.pth"
    torch.save(torch.load(path, weights_only=True), legacy, _use_new_zipfile_serialization=False)
    assert load_checkpoint(legacy).config == model.config
    stream = io.BytesIO()
    torch.save({"x": 1}, stream)
    assert stream.tell() > 0
