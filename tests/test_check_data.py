"""taptr check-data: readable sequences pass, broken ones are errors, suspicious ones warnings."""

from __future__ import annotations

import numpy as np

from taptr.cli.main import main as cli_main
from taptr.data.check import check_kubric_folder
from taptr.data.kubric import write_sequence
from taptr.types import TrackingSample

T, N, H, W = 8, 6, 32, 48


def _sample(visible_fraction: float = 0.9, normalised: bool = False) -> TrackingSample:
    rng = np.random.default_rng(0)
    video = rng.integers(0, 255, (T, H, W, 3), dtype=np.uint8)
    tracks = rng.uniform([2, 2], [W - 3, H - 3], (T, N, 2)).astype(np.float32)
    if normalised:
        tracks /= np.array([W, H], np.float32)
    visible = rng.random((T, N)) < visible_fraction
    visible[0] = True  # every track visible at least once
    return TrackingSample(video, tracks, visible)


def _write_good(root, count: int = 2) -> None:
    for index in range(count):
        write_sequence(root / f"{index:05d}", _sample())


def test_clean_folder_passes(tmp_path, capsys):
    _write_good(tmp_path)
    report = check_kubric_folder(tmp_path)
    assert report.num_sequences == 2 and not report.findings
    assert report.stats["00000"].num_frames == T and report.stats["00000"].size == (H, W)
    assert report.stats["00001"].num_points == N
    assert cli_main(["check-data", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "2 sequences, 2 readable" in out and "0 errors, 0 warnings: ok" in out


def test_broken_and_suspicious_sequences_are_reported(tmp_path, capsys):
    _write_good(tmp_path, 1)
    write_sequence(tmp_path / "00001", _sample())
    (tmp_path / "00001" / "00001.npy").unlink()  # unreadable: no annotations
    write_sequence(tmp_path / "00002", _sample(normalised=True))
    write_sequence(tmp_path / "00003", _sample(visible_fraction=0.1))  # flags look inverted
    (tmp_path / "notes").mkdir()  # no frames/: skipped by the reader
    report = check_kubric_folder(tmp_path)

    assert [(f.level, f.where.rsplit("/", 1)[-1]) for f in report.errors] == [("error", "00001")]
    assert "missing annotation file" in report.errors[0].message
    messages = {f.where.rsplit("/", 1)[-1]: f.message for f in report.warnings}
    assert "coords must be pixels" in messages["00002"]
    assert "OCCLUSION flags" in messages["00003"]
    assert "1 folders without frames/ are ignored: notes" in messages[tmp_path.name]
    assert set(report.stats) == {"00000", "00002", "00003"}

    assert cli_main(["check-data", str(tmp_path)]) == 1
    captured = capsys.readouterr()
    assert "error: " in captured.err and "FAILED" in captured.out


def test_short_sequences_warn_and_strict_fails(tmp_path):
    _write_good(tmp_path, 1)
    assert cli_main(["check-data", str(tmp_path), "--min-frames", str(T + 1)]) == 0
    assert cli_main(["check-data", str(tmp_path), "--min-frames", str(T + 1), "--strict"]) == 1
    assert check_kubric_folder(tmp_path, min_frames=T + 1).warnings[0].message == (
        f"{T} frames, fewer than {T + 1}"
    )


def test_max_sequences_limits_the_check(tmp_path):
    _write_good(tmp_path, 3)
    report = check_kubric_folder(tmp_path, max_sequences=1)
    assert report.num_sequences == 3 and list(report.stats) == ["00000"]


def test_missing_or_empty_root_is_one_line_error(tmp_path, capsys):
    assert cli_main(["check-data", str(tmp_path / "nowhere")]) == 2
    assert "dataset root not found" in capsys.readouterr().err
    split = tmp_path / "train"
    _write_good(split, 1)
    assert cli_main(["check-data", str(tmp_path)]) == 2
    assert "pass one of them" in capsys.readouterr().err
