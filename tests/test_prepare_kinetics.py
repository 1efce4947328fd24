"""taptr prepare-kinetics: a fabricated CSV and clips give the known TAP-Vid-Kinetics shards."""

from __future__ import annotations

import io
import pickle

import numpy as np
import pytest
from PIL import Image

from taptr.cli.main import main as cli_main
from taptr.data.prepare_kinetics import (
    extract_frames,
    prepare_kinetics,
    read_kinetics_csv,
    shard_name,
)
from taptr.data.tapvid import iter_tapvid
from taptr.io.video import write_video

HEIGHT, WIDTH = 48, 64


def _row(
    youtube_id: str, start: int, end: int, rng: np.random.Generator
) -> tuple[list, np.ndarray]:
    """One CSV row and its (250, 3) (x, y, occluded) triples."""
    triples = np.column_stack(
        [rng.uniform(0, 1, 250).round(6), rng.uniform(0, 1, 250).round(6), rng.random(250) < 0.3]
    )
    cells = [f"{x:.6f},{y:.6f},{int(o)}" for x, y, o in triples]
    return [youtube_id, str(start), str(end), ",".join(cells)], triples


def _clip(path, num_frames: int, fps: float) -> None:
    """Solid grey frames, frame i at level 10 * i, so frames can be told apart after coding."""
    levels = (10 * np.arange(num_frames)).astype(np.uint8)
    frames = np.broadcast_to(levels[:, None, None, None], (num_frames, HEIGHT, WIDTH, 3))
    path.parent.mkdir(parents=True, exist_ok=True)
    write_video(path, np.ascontiguousarray(frames), fps)


@pytest.fixture
def fabricated(tmp_path):
    """A CSV of three clips (two tracks each, the middle clip not downloaded) and the clips."""
    rng = np.random.default_rng(0)
    labels = {}
    lines = []
    for youtube_id, start in (("aaaaaaaaaaa", 10), ("missingclip", 0), ("ccccccccccc", 3)):
        for _ in range(2):
            row, triples = _row(youtube_id, start, start + 10, rng)
            lines.append(",".join(row))
            labels.setdefault(youtube_id, []).append(triples)
    csv_path = tmp_path / "tapvid_kinetics.csv"
    csv_path.write_text("\n".join(lines) + "\n")
    clips = tmp_path / "clips"
    _clip(clips / "label_a" / "aaaaaaaaaaa_000010_000020.mp4", 12, 25.0)  # 25 fps: kept as is
    _clip(clips / "label_c" / "deeper" / "ccccccccccc_000003_000013.mp4", 20, 50.0)  # halved
    return csv_path, clips, {k: np.stack(v) for k, v in labels.items()}


def _expected_item(triples: np.ndarray, num_frames: int) -> dict[str, np.ndarray]:
    """The item generate_tapvid.py writes: half-pixel-shifted points cut to the clip's frames."""
    size = np.array([WIDTH, HEIGHT], dtype=np.float64)
    points = (triples[:, :num_frames, :2] * size - 0.5) / size
    return {"points": points, "occluded": triples[:, :num_frames, 2].astype(bool)}


def _levels(frames: np.ndarray) -> list[int]:
    decoded = [np.asarray(Image.open(io.BytesIO(bytes(f)))) for f in frames]
    assert all(d.shape == (HEIGHT, WIDTH, 3) for d in decoded)
    return [round(float(d.mean()) / 10) for d in decoded]


def test_fabricated_set_gives_the_known_shards(fabricated, tmp_path):
    csv_path, clips, labels = fabricated
    out = tmp_path / "tapvid_kinetics"
    report = prepare_kinetics(csv_path, clips, out)

    assert report.missing == ["missingclip_000000_000010"]
    assert report.videos == ["aaaaaaaaaaa_000010_000020", "ccccccccccc_000003_000013"]
    assert report.num_points == 4
    assert [p.name for p in report.shards] == [shard_name(k) for k in range(10)]
    assert shard_name(0) == "0000_of_0010.pkl"
    shards = [pickle.loads(p.read_bytes()) for p in report.shards]
    # ceil(2 videos / 10 shards) = 1 video per shard, in CSV order; the rest are empty lists
    assert [len(s) for s in shards] == [1, 1] + [0] * 8
    for shard, youtube_id, num_frames in ((0, "aaaaaaaaaaa", 12), (1, "ccccccccccc", 10)):
        item = shards[shard][0]
        assert set(item) == {"video", "points", "occluded"}
        expected = _expected_item(labels[youtube_id], num_frames)
        assert item["points"].dtype == np.float64 and item["occluded"].dtype == bool
        np.testing.assert_allclose(item["points"], expected["points"], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(item["occluded"], expected["occluded"])
        assert item["video"].shape == (num_frames,)
        assert all(bytes(f)[:2] == b"\xff\xd8" for f in item["video"])  # JPEG frames
    # frames at 25 fps: every frame of the 25 fps clip, every other one of the 50 fps clip
    assert _levels(shards[0][0]["video"]) == list(range(12))
    assert _levels(shards[1][0]["video"]) == list(range(0, 20, 2))


def test_shards_load_with_the_tapvid_reader(fabricated, tmp_path):
    csv_path, clips, labels = fabricated
    prepare_kinetics(csv_path, clips, tmp_path / "data" / "tapvid_kinetics")
    videos = list(iter_tapvid("kinetics", tmp_path / "data"))
    assert [v.name for v in videos] == ["0", "1"]
    sample = videos[1].load()
    assert sample.video.shape == (10, HEIGHT, WIDTH, 3)
    assert sample.tracks.shape == (10, 2, 2)
    np.testing.assert_array_equal(sample.visible, ~labels["ccccccccccc"][:, :10, 2].T.astype(bool))


def test_frames_are_capped(fabricated):
    _, clips, _ = fabricated
    path = clips / "label_a" / "aaaaaaaaaaa_000010_000020.mp4"
    assert len(extract_frames(path, max_frames=5)) == 5


def test_malformed_csv_names_the_line(tmp_path):
    path = tmp_path / "bad.csv"
    row, _ = _row("x", 0, 10, np.random.default_rng(1))
    path.write_text(",".join(row) + "\n" + ",".join(row[:3]) + ",0.5,0.5\n")
    with pytest.raises(ValueError, match=r"bad.csv:2: 5 columns"):
        read_kinetics_csv(path)
    path.write_text(",".join(row)[:-1] + "2\n")  # the last occluded flag
    with pytest.raises(ValueError, match="occluded flags must be 0 or 1"):
        read_kinetics_csv(path)


def test_cli_reports_missing_clips_and_errors(fabricated, tmp_path, capsys):
    csv_path, clips, _ = fabricated
    out = tmp_path / "out"
    assert cli_main(["prepare-kinetics", str(csv_path), str(clips), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "skipped 1 clips" in printed and "missingclip_000000_000010" in printed
    assert "wrote 2 videos (4 tracks) to 10 shards" in printed
    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli_main(["prepare-kinetics", str(csv_path), str(empty), "--out", str(out)]) == 2
    assert "none of the 3 clips" in capsys.readouterr().err
