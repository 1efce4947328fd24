"""Careless and hostile arguments: one-line errors naming the flag, before any work starts.

Regression tests for issue 15 (items 2, 3, 5 and 7): every case fails with exit status 2
and a single ``taptr COMMAND: error: ...`` line, or is accepted and gives correct output.
"""

from __future__ import annotations

import argparse
import os
import re

import cv2
import numpy as np
import pytest
import torch

from taptr.api.inputs import MAX_POINTS_ENV, grid_queries, max_points, query_tensor
from taptr.api.regions import read_mask
from taptr.cli.main import build_parser, main
from taptr.io.tracks import load_tracks_npz
from taptr.io.video import write_video


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """A 10-frame 48×64 video with a bright square moving right."""
    frames = np.full((10, 48, 64, 3), 40, np.uint8)
    for t in range(10):
        frames[t, 16:28, 10 + 2 * t : 22 + 2 * t] = (230, 200, 40)
    return write_video(tmp_path_factory.mktemp("clip") / "clip.mp4", frames, fps=10)


def _one_line_error(capsys, command: str) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith(f"taptr {command}: error:") and "Traceback" not in err
    return lines[0]


def _files(tmp_path, clip):
    """Small bad inputs, by name."""
    (tmp_path / "afile").write_text("not a folder")
    (tmp_path / "afolder").mkdir()
    (tmp_path / "spaces.txt").write_text("0 10 10\n1 20 20\n")
    (tmp_path / "nan.txt").write_text("t,x,y\nnan,10,10\n")
    (tmp_path / "inf.txt").write_text("0,10,10\n1,inf,10\n")
    (tmp_path / "words.txt").write_text("t,x,y\n0,10,10\nhello,1,2\n")
    (tmp_path / "binary.txt").write_bytes(b"0,1,1\n\xff\xfe\x00garbage")
    (tmp_path / "long.txt").write_text("0," * 5000 + "\n")
    cv2.imwrite(str(tmp_path / "empty.png"), np.zeros((48, 64), np.uint8))
    torch.save([1, 2, 3], tmp_path / "list.pt")
    return {"clip": clip, "tmp": tmp_path}


CLIP_ERRORS = [
    pytest.param(["--grid", "1000"], r"--grid 1000: 1,000,000 points.*TAPTR_MAX_POINTS", id="grid"),
    pytest.param(["--grid", "0"], r"--grid must be at least 1", id="grid-zero"),
    pytest.param(["--grid", "2", "--out", "{tmp}/afile"], r"--out .*afile is a file", id="out"),
    pytest.param(["--grid", "2", "--input-size", "0", "0"], r"--input-size 0 0", id="size0"),
    pytest.param(
        ["--grid", "2", "--input-size", "60000", "60000"], r"--input-size 60000", id="size-huge"
    ),
    pytest.param(["--grid", "2", "--device", "bogus"], r"--device bogus: not a device", id="dev"),
    pytest.param(["--grid", "2", "--max-frames", "0"], r"--max-frames must be", id="frames"),
    pytest.param(["--mask", "{tmp}/empty.png", "--mask-stride", "0"], "--mask-stride", id="ms"),
    pytest.param(["--mask", "{tmp}/empty.png"], r"--mask .*empty.png: no pixel", id="empty"),
    pytest.param(["--points", "0 10 10"], r"--points: point 1 .*separated by spaces", id="sp"),
    pytest.param(["--points", "0,1"], r"--points: point 1 .*triples", id="pair"),
    pytest.param(["--points", "-1,10,10"], r"--points: query frame t outside", id="dash"),
    pytest.param(["--points-file", "{tmp}/nan.txt"], r"nan.txt line 2 .*NaN", id="nan"),
    pytest.param(["--points-file", "{tmp}/inf.txt"], r"inf.txt line 2 .*infinite", id="inf"),
    pytest.param(["--points-file", "{tmp}/words.txt"], r"words.txt line 3 .*triples", id="word"),
    pytest.param(["--points-file", "{tmp}/binary.txt"], r"binary.txt: not UTF-8", id="utf8"),
    pytest.param(["--points-file", "{tmp}/long.txt"], r"long.txt line 1: longer", id="long"),
    pytest.param(["--points-file", "{tmp}/none.txt"], r"--points-file .*none.txt", id="missing"),
]


@pytest.mark.parametrize(("args", "message"), CLIP_ERRORS)
def test_track_argument_errors_are_one_line_and_write_nothing(
    clip, tmp_path, capsys, args, message
):
    paths = _files(tmp_path, clip)
    args = [a.format(**paths) for a in args]
    out = [] if "--out" in args else ["--out", str(tmp_path / "out")]
    assert main(["track", str(clip), *args, "--checkpoint", "tiny", *out]) == 2
    assert re.search(message, _one_line_error(capsys, "track"))
    assert not (tmp_path / "out").exists()


def test_track_device_cuda_without_gpu_is_one_line(clip, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    argv = ["track", str(clip), "--grid", "2", "--device", "cuda", "--out", str(tmp_path)]
    assert main(argv) == 2
    assert "--device cuda: this machine has no usable CUDA GPU" in _one_line_error(capsys, "track")


def test_argument_errors_come_before_the_video_is_read(tmp_path, capsys):
    # the video does not exist: the argument error must win, the run must not start
    missing = str(tmp_path / "missing.mp4")
    (tmp_path / "afile").write_text("")
    assert main(["track", missing, "--grid", "2", "--out", str(tmp_path / "afile")]) == 2
    assert "--out" in _one_line_error(capsys, "track")
    assert main(["edit", missing, "--mask", "m.png", "--overlay", "o.png", "--out", "."]) == 2
    assert "is a folder" in _one_line_error(capsys, "edit")


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux /proc")
def test_unwritable_out_fails_before_the_run(clip, capsys):
    # /proc refuses new files even to root, for whom permission bits say nothing
    assert main(["track", str(clip), "--grid", "2", "--out", "/proc/taptr-out"]) == 2
    assert "--out /proc/taptr-out: cannot write in /proc" in _one_line_error(capsys, "track")


def test_points_file_over_the_limit_fails_before_building_queries(clip, tmp_path, capsys):
    big = tmp_path / "big.txt"
    big.write_text("0,1,1\n" * (max_points() + 1))
    assert main(["track", str(clip), "--points-file", str(big), "--out", str(tmp_path / "o")]) == 2
    line = _one_line_error(capsys, "track")
    assert "100,001 points, more than the limit of 100,000" in line and MAX_POINTS_ENV in line


def test_max_points_is_raisable_by_environment(clip, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv(MAX_POINTS_ENV, "3")
    assert main(["track", str(clip), "--grid", "2", "--out", str(tmp_path / "o")]) == 2
    assert "--grid 2: 4 points, more than the limit of 3" in _one_line_error(capsys, "track")
    monkeypatch.setenv(MAX_POINTS_ENV, "4")
    assert (
        main(
            [
                "track",
                str(clip),
                "--grid",
                "2",
                "--checkpoint",
                "tiny",
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 0
    )


def test_points_starting_with_a_dash_are_accepted(clip, tmp_path):
    out = tmp_path / "o"
    argv = ["track", str(clip), "--points", "-0,10,10", "--checkpoint", "tiny", "--out", str(out)]
    assert main(argv) == 0
    np.testing.assert_array_equal(load_tracks_npz(out / "tracks.npz").queries, [[0, 10, 10]])


def test_points_file_with_spaces_header_and_comments(clip, tmp_path):
    points = tmp_path / "p.txt"
    np.savetxt(points, [[0, 10, 10], [2, 20.5, 30]], header="t x y")
    out = tmp_path / "o"
    assert (
        main(
            [
                "track",
                str(clip),
                "--points-file",
                str(points),
                "--checkpoint",
                "tiny",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    np.testing.assert_array_equal(
        load_tracks_npz(out / "tracks.npz").queries, [[0, 10, 10], [2, 20.5, 30]]
    )


def test_parser_errors_are_one_line_with_a_hint(clip, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["track", str(clip), "--grid", "2.5"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--grid: invalid int value: '2.5'" in err
    assert "(see 'taptr track --help')" in err
    with pytest.raises(SystemExit):
        main(["track", str(clip), "--points-file", "-x.txt"])
    assert "written --points-file=VALUE" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["track", "clip.mp4", "--gird", "8"], "unknown option --gird; did you mean --grid?"),
        (["track", "c.mp4", "--grid", "8", "--chekpoint=x"], "did you mean --checkpoint?"),
        (["eval", "--dataset", "davis", "--gird", "3"], "unknown option --gird (see"),
    ],
)
def test_a_misspelled_option_is_unknown_with_the_closest_name(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    line = _one_line_error(capsys, argv[0])
    assert message in line and "required" not in line


def test_abbreviations_and_values_after_a_double_dash_are_still_accepted():
    from taptr.cli.main import unknown_option

    track = build_parser()._subparsers._group_actions[0].choices["track"]
    assert unknown_option(track, ["clip.mp4", "--gr", "8", "--check", "x"]) is None
    assert unknown_option(track, ["--grid", "8", "--", "--not-an-option"]) is None
    assert unknown_option(track, ["--grid=8", "--outt", "o"]) == (
        "unknown option --outt; did you mean --out?"
    )


def test_train_resume_on_a_list_is_one_line(tmp_path, capsys):
    torch.save([1, 2, 3], tmp_path / "list.pt")
    assert main(["train", "--resume", str(tmp_path / "list.pt"), "--out", str(tmp_path)]) == 2
    assert "is not a taptr training checkpoint" in _one_line_error(capsys, "train")


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["bench", "--device", "bogus"], "--device bogus"),
        (["bench", "--points", "0"], "--points must be at least 1"),
        (["bench", "--points", "200000"], "200,000 points"),
        (["export", "--format", "onnx", "--out", "x", "--input-size", "0", "0"], "--input-size"),
        (
            ["eval", "--dataset", "davis", "--root", "x", "--out", "o", "--device", "nope"],
            "--device",
        ),
        (["convert", "in.pth", "."], "DST . is a folder"),
    ],
)
def test_other_commands_check_arguments_first(argv, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    assert message in _one_line_error(capsys, argv[0])


def test_edit_rejects_bad_opacity_and_empty_mask(clip, tmp_path, capsys):
    cv2.imwrite(str(tmp_path / "empty.png"), np.zeros((48, 64), np.uint8))
    cv2.imwrite(str(tmp_path / "logo.png"), np.zeros((4, 4, 3), np.uint8))
    base = [
        "edit",
        str(clip),
        "--overlay",
        str(tmp_path / "logo.png"),
        "--out",
        str(tmp_path / "e.mp4"),
    ]
    assert main([*base, "--mask", str(tmp_path / "logo.png"), "--opacity", "2"]) == 2
    assert "--opacity must lie in [0, 1]" in _one_line_error(capsys, "edit")
    assert main([*base, "--mask", str(tmp_path / "empty.png")]) == 2
    assert "--mask" in _one_line_error(capsys, "edit")


def test_bugs_are_one_line_unless_verbose(monkeypatch, capsys):
    def broken(_args: argparse.Namespace) -> int:
        raise RuntimeError("boom\nsecond line")

    import taptr.cli.sample_video as command

    monkeypatch.setattr(command, "run", broken)
    assert main(["sample-video", "x.mp4"]) == 1
    line = _one_line_error(capsys, "sample-video")
    assert "RuntimeError: boom second line" in line and "bug" in line
    assert main(["-v", "sample-video", "x.mp4"]) == 1
    assert "Traceback" in capsys.readouterr().err


def test_multi_line_messages_are_joined_into_one(tmp_path, clip, capsys):
    from taptr import build_model
    from taptr.weights.checkpoint import checkpoint_dict

    bad = checkpoint_dict(build_model("tiny"))
    bad["model"].pop("encoder.level_embed")
    bad["model"]["extra.weight"] = torch.zeros(1)
    torch.save(bad, tmp_path / "wrong.pth")
    argv = ["track", str(clip), "--grid", "2", "--checkpoint", str(tmp_path / "wrong.pth")]
    assert main([*argv, "--out", str(tmp_path / "o")]) == 2
    line = _one_line_error(capsys, "track")
    assert re.search(r"does not match the model: missing \(1\): .*; unexpected \(1\)", line)


def test_out_of_memory_is_one_line(monkeypatch, capsys):
    def hungry(_args: argparse.Namespace) -> int:
        raise MemoryError("Unable to allocate 12.0 GiB")

    import taptr.cli.sample_video as command

    monkeypatch.setattr(command, "run", hungry)
    assert main(["sample-video", "x.mp4"]) == 1
    line = _one_line_error(capsys, "sample-video")
    assert "out of memory" in line and "12.0 GiB" in line


@pytest.mark.parametrize("where", ["before", "after"])
def test_verbose_shows_the_traceback_of_user_errors(tmp_path, capsys, where):
    argv = ["track", str(tmp_path / "missing.mp4"), "--grid", "2", "--out", str(tmp_path)]
    assert main(["-v", *argv] if where == "before" else [*argv, "-v"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and "taptr track: error:" in err


# --- help text ---------------------------------------------------------------------------


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def _option_help(command: str, flag: str) -> str:
    parser = _subparsers()[command]
    return next(a.help for a in parser._actions if flag in a.option_strings)


@pytest.mark.parametrize(
    ("command", "flag", "default"),
    [
        ("track", "--mask-stride", "8"),
        ("edit", "--stride", "6"),
        ("edit", "--opacity", "1"),
        ("edit", "--query-frame", "0"),
        ("demo", "--max-frames", None),
    ],
)
def test_help_shows_defaults(command, flag, default):
    text = _option_help(command, flag)
    parser = _subparsers()[command]
    value = default or str(parser.get_default(flag.lstrip("-").replace("-", "_")))
    assert f"default {value}" in text or f"default: {value}" in text, text


def test_every_bench_option_has_help():
    parser = _subparsers()["bench"]
    missing = [a.option_strings for a in parser._actions if a.option_strings and not a.help]
    assert not missing


def test_device_help_is_the_same_everywhere():
    helps = {
        name: next(a.help for a in parser._actions if "--device" in a.option_strings)
        for name, parser in _subparsers().items()
        if any("--device" in a.option_strings for a in parser._actions)
    }
    assert {"track", "edit", "eval", "bench", "calibrate", "demo"} <= set(helps)
    prefixes = {text.split(" (default")[0] for text in helps.values()}
    assert prefixes == {"where to run: cpu, cuda, cuda:N or mps"}, helps


# --- Python API --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "queries",
    [
        "0,1,1",
        [["0", "1", "1"]],
        [[0, 1, 1j]],
        np.array([[0, 1, 1]], dtype=object),
        [[0, 1], [1]],
        torch.tensor([[0, 1, 1j]]),
        [[True, True, False]],
        object(),
    ],
    ids=["str", "strings", "complex", "objects", "ragged", "complex-tensor", "bool", "object"],
)
def test_queries_must_be_real_numbers(queries):
    with pytest.raises(ValueError, match="real numbers"):
        query_tensor(queries, 1, 5, 10, 10)


@pytest.mark.parametrize("grid_size", [2.5, True, "3", None])
def test_grid_size_must_be_a_whole_number(grid_size):
    with pytest.raises(ValueError, match="whole number"):
        grid_queries(grid_size, 0, 10, 10)


def test_grid_size_accepts_numpy_integers():
    assert grid_queries(np.int64(2), 0, 10, 10).shape == (4, 3)


def test_predictor_refuses_too_many_points_before_tracking(monkeypatch):
    import taptr

    predictor = taptr.Predictor(taptr.build_model("tiny"), device="cpu")
    video = np.zeros((2, 16, 16, 3), np.uint8)
    with pytest.raises(ValueError, match="grid_size must be a whole number"):
        predictor.track(video, grid_size=2.5)
    monkeypatch.setenv(MAX_POINTS_ENV, "5")
    with pytest.raises(ValueError, match=f"6 points, more than the limit of 5.*{MAX_POINTS_ENV}"):
        predictor.track(video, np.zeros((6, 3)))


def test_results_larger_than_memory_are_refused_before_the_run(monkeypatch):
    import taptr.api.inputs as inputs

    monkeypatch.setattr(inputs, "_available_memory", lambda: 1000)
    with pytest.raises(ValueError, match="for the results alone"):
        query_tensor(np.zeros((100, 3)), 1, 5, 10, 10)


# --- masks -------------------------------------------------------------------------------


def test_a_zero_one_mask_is_not_empty(tmp_path):
    mask = np.zeros((8, 8), np.uint8)
    mask[2:4, 2:5] = 1
    cv2.imwrite(str(tmp_path / "m.png"), mask)
    np.testing.assert_array_equal(read_mask(tmp_path / "m.png"), mask == 1)


def test_mask_alpha_is_honoured(tmp_path):
    image = np.full((8, 8, 4), 255, np.uint8)  # white everywhere ...
    image[..., 3] = 0  # ... but transparent
    image[1:3, 1:3, 3] = 255
    cv2.imwrite(str(tmp_path / "m.png"), image)
    assert read_mask(tmp_path / "m.png").sum() == 4


def test_mask_16_bit_and_grey_alpha(tmp_path):
    deep = np.zeros((8, 8), np.uint16)
    deep[0, 0] = 1
    cv2.imwrite(str(tmp_path / "d.png"), deep)
    assert read_mask(tmp_path / "d.png").sum() == 1


def test_mask_errors_name_the_file_and_flag(tmp_path):
    cv2.imwrite(str(tmp_path / "m.png"), np.zeros((8, 8), np.uint8))
    with pytest.raises(ValueError, match=r"--mask .*m.png: no pixel is inside"):
        read_mask(tmp_path / "m.png", name="--mask")
    with pytest.raises(ValueError, match=r"--mask .*m.png is 8x8, the video is 64x48"):
        read_mask(tmp_path / "m.png", name="--mask", size=(48, 64))
    (tmp_path / "bad.png").write_bytes(b"not an image")
    with pytest.raises(ValueError, match=r"bad.png: not an image"):
        read_mask(tmp_path / "bad.png")


def test_track_with_a_zero_one_rgba_mask(clip, tmp_path):
    image = np.zeros((48, 64, 4), np.uint8)
    image[16:28, 16:28] = (1, 1, 1, 1)
    cv2.imwrite(str(tmp_path / "m.png"), image)
    out = tmp_path / "o"
    argv = ["track", str(clip), "--mask", str(tmp_path / "m.png"), "--mask-stride", "4"]
    assert main([*argv, "--checkpoint", "tiny", "--out", str(out)]) == 0
    assert load_tracks_npz(out / "tracks.npz").queries.shape == (9, 3)
