"""Kubric MOVi-F reader (CoTracker's layout) on fabricated sequences."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from taptr.data.kubric import list_sequences, read_sequence, write_sequence
from taptr.io.safe_pickle import UnsafePickleError
from taptr.types import TrackingSample


def _fabricate(folder, num_frames=3, height=6, width=8, name=None):
    """Frames with known colours and a .npy whose 'visibility' means occluded."""
    name = name or folder.name
    (folder / "frames").mkdir(parents=True)
    for t in range(num_frames):
        rgb = np.zeros((height, width, 3), np.uint8)
        rgb[..., 0], rgb[..., 1], rgb[..., 2] = 10 * t, 100, 200  # R encodes the frame
        cv2.imwrite(str(folder / "frames" / f"{t:03d}.png"), rgb[..., ::-1])
    coords = np.array(
        [
            [[1.0, 2.0], [2.0, 2.0], [3.5, 2.5]],
            [[0.0, 0.0], [-1.0, 0.0], [7.0, 5.0]],  # leaves the image at frame 1
        ],
        np.float64,
    )
    occluded = np.array([[False, True, False], [False, False, False]])
    np.save(folder / f"{name}.npy", {"coords": coords, "visibility": occluded}, allow_pickle=True)
    return coords, occluded


def test_reads_rgb_and_inverts_the_occlusion_key(tmp_path):
    coords, occluded = _fabricate(tmp_path / "7")
    sample = read_sequence(tmp_path / "7")
    assert isinstance(sample, TrackingSample) and sample.name == "7"
    assert sample.video.shape == (3, 6, 8, 3) and sample.video.dtype == np.uint8
    assert sample.video[2, 0, 0].tolist() == [20, 100, 200]  # RGB, frames in order
    assert sample.tracks.dtype == np.float32
    np.testing.assert_array_equal(sample.tracks, coords.transpose(1, 0, 2))
    # 'visibility' in the file means occluded; outside the image is not visible either
    expected = np.array([[True, True], [False, False], [True, True]])
    np.testing.assert_array_equal(sample.visible, expected)
    np.testing.assert_array_equal(~occluded.T[:, 0], expected[:, 0])


def test_bgr_flag_keeps_opencv_order(tmp_path):
    _fabricate(tmp_path / "3")
    sample = read_sequence(tmp_path / "3", bgr=True)
    assert sample.video[2, 0, 0].tolist() == [200, 100, 20]


def test_sequences_and_frames_sort_numerically(tmp_path):
    for name in ("10", "9", "100"):
        _fabricate(tmp_path / name)
    (tmp_path / "annotations").mkdir()  # TAPTR's preprocessing folder is not a sequence
    assert [p.name for p in list_sequences(tmp_path)] == ["9", "10", "100"]
    frames = tmp_path / "9" / "frames"
    for t in range(3):
        (frames / f"{t:03d}.png").rename(frames / f"{t}.png")  # 0.png, 1.png, 2.png
    cv2.imwrite(str(frames / "10.png"), np.zeros((6, 8, 3), np.uint8))
    with pytest.raises(ValueError, match=r"9\.npy.*\(N, 4, 2\)"):
        read_sequence(tmp_path / "9")  # 4 frames now, annotations for 3


def test_split_root_is_named_in_the_error(tmp_path):
    _fabricate(tmp_path / "r512" / "train" / "0")
    _fabricate(tmp_path / "r512" / "val" / "0")
    assert len(list_sequences(tmp_path / "r512" / "train")) == 1
    with pytest.raises(ValueError, match="splits train, val"):
        list_sequences(tmp_path / "r512")
    with pytest.raises(FileNotFoundError, match="not found"):
        list_sequences(tmp_path / "missing")


def test_malformed_sequences_name_the_file(tmp_path):
    _fabricate(tmp_path / "a")
    (tmp_path / "a" / "a.npy").rename(tmp_path / "a" / "other.npy")
    with pytest.raises(FileNotFoundError, match=r"a\.npy.*found: other\.npy"):
        read_sequence(tmp_path / "a")

    _fabricate(tmp_path / "b")
    np.save(tmp_path / "b" / "b.npy", {"coords": np.zeros((2, 3, 2))}, allow_pickle=True)
    with pytest.raises(ValueError, match=r"b\.npy.*'coords' and 'visibility'"):
        read_sequence(tmp_path / "b")

    _fabricate(tmp_path / "c")
    bad = {"coords": np.zeros((2, 3, 2)), "visibility": np.zeros((3, 2), bool)}
    np.save(tmp_path / "c" / "c.npy", bad, allow_pickle=True)
    with pytest.raises(ValueError, match=r"c\.npy.*'visibility' must be"):
        read_sequence(tmp_path / "c")

    _fabricate(tmp_path / "d")
    cv2.imwrite(str(tmp_path / "d" / "frames" / "001.png"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(ValueError, match=r"001\.png.*differs"):
        read_sequence(tmp_path / "d")

    _fabricate(tmp_path / "e")
    (tmp_path / "e" / "frames" / "002.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match=r"002\.png: not a readable image"):
        read_sequence(tmp_path / "e")


class _Exploit:
    def __reduce__(self):
        return (print, ("pwned",))


def test_annotations_are_never_unpickled_unsafely(tmp_path):
    _fabricate(tmp_path / "s")
    payload = np.empty((), dtype=object)
    payload[()] = {"coords": _Exploit(), "visibility": np.zeros((2, 3), bool)}
    with (tmp_path / "s" / "s.npy").open("wb") as stream:
        np.lib.format.write_array(stream, payload, allow_pickle=True, pickle_kwargs={})
    with pytest.raises(UnsafePickleError, match=r"builtins\.print"):
        read_sequence(tmp_path / "s")


def test_write_then_read_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    video = rng.integers(0, 256, (4, 5, 7, 3), dtype=np.uint8)
    tracks = rng.uniform(0, 4, (4, 3, 2)).astype(np.float32)
    visible = rng.random((4, 3)) < 0.5
    write_sequence(tmp_path / "0042", TrackingSample(video, tracks, visible))
    assert sorted(p.name for p in (tmp_path / "0042" / "frames").iterdir())[0] == "000.png"
    back = read_sequence(tmp_path / "0042")
    np.testing.assert_array_equal(back.video, video)
    np.testing.assert_array_equal(back.tracks, tracks)
    np.testing.assert_array_equal(back.visible, visible)
