"""Readers of the TAP-Vid pickles: formats, folder layouts, lazy decoding, hostile files."""

from __future__ import annotations

import os
import pickle

import cv2
import numpy as np
import pytest

import taptr.data.tapvid as tapvid
from taptr.data.tapvid import (
    iter_tapvid,
    pixels_to_raster,
    raster_to_pixels,
)
from taptr.eval.datasets import open_dataset
from taptr.io.safe_pickle import UnsafePickleError
from tests.test_tapvid_fabricated import make_clip, tapvid_item, write_davis, write_kinetics_shard


def _decode_with_opencv(item):
    """The JPEG frames of an item decoded by another decoder than the reader's (PIL)."""
    return np.stack(
        [
            cv2.cvtColor(
                cv2.imdecode(np.frombuffer(f, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB
            )
            for f in item["video"]
        ]
    )


def _assert_same_sample(loaded, expected):
    np.testing.assert_array_equal(loaded.video, expected.video)
    np.testing.assert_allclose(loaded.tracks, expected.tracks, atol=1e-4)
    np.testing.assert_array_equal(loaded.visible, expected.visible)


def test_raster_conversion():
    # the centre of pixel 0 of a 64-wide image is raster 0.5 / 64; the outer edge is −0.5
    np.testing.assert_allclose(raster_to_pixels(np.array([0.5 / 64, 0.0]), 32, 64), [0, -0.5])
    points = np.random.default_rng(0).uniform(-0.5, 63.5, (5, 2))
    np.testing.assert_allclose(raster_to_pixels(pixels_to_raster(points, 48, 64), 48, 64), points)


def test_davis_dict_pickle_in_every_root_form(tmp_path):
    clips = [make_clip(12, seed=0, name="bear"), make_clip(8, seed=1, name="car")]
    path = write_davis(tmp_path / "tapvid_davis" / "tapvid_davis.pkl", clips)
    for root in (path, path.parent, tmp_path):
        pending = list(iter_tapvid("davis", root))
        assert [p.name for p in pending] == ["bear", "car"]
        for entry, clip in zip(pending, clips, strict=True):
            _assert_same_sample(entry.load(), clip)


def test_rgb_stacking_list_is_named_by_index(tmp_path):
    clips = [make_clip(8, seed=s) for s in range(3)]
    path = tmp_path / "tapvid_rgb_stacking" / "tapvid_rgb_stacking.pkl"
    path.parent.mkdir()
    path.write_bytes(pickle.dumps([tapvid_item(c) for c in clips]))
    pending = list(open_dataset("rgb_stacking", tmp_path))
    assert [p.name for p in pending] == ["0", "1", "2"]
    _assert_same_sample(pending[2].load(), clips[2])


def test_robotap_split_pickles(tmp_path):
    folder = tmp_path / "tapvid_robotap"
    write_davis(folder / "robotap_split0.pkl", [make_clip(8, seed=0, name="r0")])
    write_davis(folder / "robotap_split1.pkl", [make_clip(8, seed=1, name="r1")])
    assert [p.name for p in open_dataset("robotap", tmp_path)] == ["r0", "r1"]


def test_kinetics_shards_decode_jpeg_one_video_at_a_time(tmp_path, monkeypatch):
    clips = [make_clip(8, seed=s) for s in range(3)]
    folder = tmp_path / "tapvid_kinetics"
    write_kinetics_shard(folder / "0000_of_0010.pkl", clips[:2])
    write_kinetics_shard(folder / "0001_of_0010.pkl", clips[2:])
    opened = []
    real_open = tapvid.Image.open
    monkeypatch.setattr(
        tapvid.Image, "open", lambda *a, **k: opened.append(1) or real_open(*a, **k)
    )
    pending = list(open_dataset("kinetics", tmp_path))
    assert [p.name for p in pending] == ["0", "1", "2"]  # numbered across shards
    assert not opened  # listing decodes nothing
    sample = pending[2].load()
    assert len(opened) == 8  # one video's frames
    # JPEG is lossy: compare with the same bytes decoded by OpenCV, and the ground truth
    decoded = _decode_with_opencv(tapvid_item(clips[2], jpeg=True))
    assert np.abs(sample.video.astype(int) - decoded).max() <= 2
    np.testing.assert_allclose(sample.tracks, clips[2].tracks, atol=1e-4)
    np.testing.assert_array_equal(sample.visible, clips[2].visible)


def test_missing_files_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"tapvid_davis\.pkl"):
        open_dataset("davis", tmp_path)
    with pytest.raises(ValueError, match="unknown dataset"):
        open_dataset("sintel", tmp_path)


def test_malformed_items_are_named(tmp_path):
    path = tmp_path / "tapvid_davis.pkl"
    item = tapvid_item(make_clip(8))
    path.write_bytes(pickle.dumps({"ok": item, "broken": {"video": item["video"]}}))
    pending = list(iter_tapvid("davis", path))
    with pytest.raises(ValueError, match="'broken'"):
        pending[1].load()
    path.write_bytes(pickle.dumps({"short": dict(item, occluded=item["occluded"][:, :5])}))
    with pytest.raises(ValueError, match="8 frames"):
        next(iter_tapvid("davis", path)).load()
    path.write_bytes(pickle.dumps("not a dataset"))
    with pytest.raises(ValueError, match="expected a dict or a list"):
        list(iter_tapvid("davis", path))


class _Payload:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_hostile_pickle_is_refused_without_running_it(tmp_path):
    marker = tmp_path / "pwned"
    path = tmp_path / "tapvid_davis.pkl"
    path.write_bytes(pickle.dumps({"video": _Payload(marker)}))
    with pytest.raises(UnsafePickleError, match=r"(posix|os)\.system"):
        list(iter_tapvid("davis", path))
    assert not marker.exists()
    # the same file given to the CLI: a one-line error, exit status 2, nothing run
    from taptr.cli.main import main

    status = main(
        ["eval", "--dataset", "davis", "--root", str(path), "--tracker", "static"]
        + ["--out", str(tmp_path / "out")]
    )
    assert status == 2
    assert not marker.exists()
    assert not (tmp_path / "out" / "results.json").exists()
