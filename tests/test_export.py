"""Round trips of the track files, their layout, and their errors."""

from __future__ import annotations

import numpy as np
import pytest

from taptr.io.tracks import (
    CSV_HEADER,
    load_tracks_csv,
    load_tracks_npz,
    save_tracks_csv,
    save_tracks_npz,
)


@pytest.fixture
def tracks_and_visibility():
    rng = np.random.default_rng(0)
    tracks = rng.uniform(-5, 300, (4, 3, 2)).astype(np.float32)
    tracks[2, 1] = [np.float32(1 / 3), np.float32(2**-20)]  # digits that need 9 places
    return tracks, rng.random((4, 3)) > 0.5


def test_npz_round_trip(tmp_path, tracks_and_visibility):
    tracks, visibility = tracks_and_visibility
    queries = np.array([[0, 1.5, 2.5], [1, 10, 20], [3, 0, 0]], np.float32)
    metadata = {"video": "clip.mp4", "fps": 24.0, "model": "taptrv2"}
    path = save_tracks_npz(tmp_path / "out" / "tracks.npz", tracks, visibility, queries, metadata)
    assert [p.name for p in path.parent.iterdir()] == ["tracks.npz"]
    saved = load_tracks_npz(path)
    np.testing.assert_array_equal(saved.tracks, tracks)
    np.testing.assert_array_equal(saved.visibility, visibility)
    np.testing.assert_array_equal(saved.queries, queries)
    assert saved.metadata == metadata
    assert saved.tracks.dtype == np.float32 and saved.visibility.dtype == bool
    with np.load(path, allow_pickle=False) as data:  # plain arrays, readable without us
        assert sorted(data.files) == ["metadata", "queries", "tracks", "visibility"]
        assert data["tracks"].dtype == np.float32 and data["visibility"].dtype == bool


def test_csv_round_trip_and_layout(tmp_path, tracks_and_visibility):
    tracks, visibility = tracks_and_visibility
    path = save_tracks_csv(tmp_path / "tracks.csv", tracks, visibility)
    lines = path.read_text().splitlines()
    assert lines[0] == CSV_HEADER == "frame,point,x,y,visible"
    assert len(lines) == 1 + 4 * 3
    frame, point, x, y, visible = lines[1 + 1 * 3 + 2].split(",")  # frame-major order
    assert (frame, point, visible) == ("1", "2", str(int(visibility[1, 2])))
    assert np.float32(x) == tracks[1, 2, 0] and np.float32(y) == tracks[1, 2, 1]
    loaded_tracks, loaded_visibility = load_tracks_csv(path)
    np.testing.assert_array_equal(loaded_tracks, tracks)  # exact: 9 significant digits
    np.testing.assert_array_equal(loaded_visibility, visibility)


def test_csv_rows_in_any_order(tmp_path, tracks_and_visibility):
    tracks, visibility = tracks_and_visibility
    path = save_tracks_csv(tmp_path / "tracks.csv", tracks, visibility)
    header, *rows = path.read_text().splitlines()
    path.write_text("\n".join([header, *rows[::-1]]) + "\n")
    np.testing.assert_array_equal(load_tracks_csv(path)[0], tracks)


def test_csv_errors(tmp_path, tracks_and_visibility):
    tracks, visibility = tracks_and_visibility
    with pytest.raises(FileNotFoundError):
        load_tracks_csv(tmp_path / "missing.csv")
    (tmp_path / "bad.csv").write_text("t,n,x,y\n0,0,1,2\n")
    with pytest.raises(ValueError, match="expected header"):
        load_tracks_csv(tmp_path / "bad.csv")
    path = save_tracks_csv(tmp_path / "tracks.csv", tracks, visibility)
    path.write_text("\n".join(path.read_text().splitlines()[:-1]) + "\n")  # one row short
    with pytest.raises(ValueError, match="every frame and point"):
        load_tracks_csv(path)


def test_shape_errors(tmp_path, tracks_and_visibility):
    tracks, visibility = tracks_and_visibility
    with pytest.raises(ValueError, match="visibility must be"):
        save_tracks_csv(tmp_path / "t.csv", tracks, visibility[:, :2])
    with pytest.raises(ValueError, match="queries must be"):
        save_tracks_npz(tmp_path / "t.npz", tracks, visibility, np.zeros((2, 3)))
    with pytest.raises(ValueError, match="tracks must be"):
        save_tracks_npz(tmp_path / "t.npz", tracks[..., 0], visibility, np.zeros((3, 3)))
    assert list(tmp_path.iterdir()) == []
