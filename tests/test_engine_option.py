"""``--engine``: TAPTRv3's exported graphs run by name from the commands, exported once.

A tiny seeded TAPTRv3 checkpoint at 48 × 64, a 4-frame clip; the export cache is the test's
own folder (``TAPTR_EXPORT_DIR``), exported once per module.
"""

from __future__ import annotations

import json
import pickle
from importlib.util import find_spec

import numpy as np
import pytest

from taptr.api.spec import ModelSpec
from taptr.cli.main import main
from taptr.export.cache import CACHE_VARIABLE, KEY_FILE
from taptr.io.video import write_video
from taptr.weights.checkpoint import save_checkpoint
from tests.export_v3_cases import randomised_v3

pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript", reason="exporting needs onnxscript")

ENGINES = [
    "onnxruntime",
    pytest.param(
        "openvino",
        marks=pytest.mark.skipif(find_spec("openvino") is None, reason="openvino is missing"),
    ),
]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A tiny TAPTRv3 checkpoint, a clip, and the torch engine's result folder."""
    folder = tmp_path_factory.mktemp("engine")
    weights = save_checkpoint(randomised_v3(input_size=(48, 64)), folder / "tiny_v3.pth")
    frames = np.random.default_rng(3).integers(0, 256, (4, 48, 64, 3), dtype=np.uint8)
    clip = write_video(folder / "clip.mp4", frames, fps=10)
    return folder, weights, clip


@pytest.fixture(scope="module")
def cache(files, tmp_path_factory):
    """The module's export cache, set for every test."""
    folder = tmp_path_factory.mktemp("exports")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(CACHE_VARIABLE, str(folder))
        yield folder


def track(files, out, *extra):
    folder, weights, clip = files
    argv = ["track", str(clip), "--grid", "3", "--checkpoint", str(weights), "--threads", "1"]
    return main([*argv, "--out", str(folder / out), *extra])


@pytest.fixture(scope="module")
def torch_run(files, cache):
    assert track(files, "torch", "--engine", "torch") == 0
    return files[0] / "torch"


@pytest.mark.parametrize("engine", ENGINES)
def test_an_engine_writes_torchs_tracks_and_settings(files, cache, torch_run, engine, capfd):
    assert track(files, engine, "--engine", engine) == 0
    out = files[0] / engine
    expected, found = np.load(torch_run / "tracks.npz"), np.load(out / "tracks.npz")
    np.testing.assert_allclose(found["tracks"], expected["tracks"], atol=2e-3)
    assert (found["visibility"] == expected["visibility"]).mean() > 0.95  # ties at 0.45 aside
    # the engine changes no setting that changes the tracks (corpus.settings.SPEED_ONLY)
    settings = json.loads((out / "settings.json").read_text())
    assert settings == json.loads((torch_run / "settings.json").read_text())


def test_the_streamed_backward_pass_matches_torch(files, cache):
    assert track(files, "torch_backward", "--backward") == 0
    assert track(files, "onnx_backward", "--backward", "--engine", "onnxruntime") == 0
    expected = np.load(files[0] / "torch_backward" / "tracks.npz")["tracks"]
    found = np.load(files[0] / "onnx_backward" / "tracks.npz")["tracks"]
    np.testing.assert_allclose(found, expected, atol=2e-3)


@pytest.mark.parametrize("backward", [False, True])
def test_in_memory_and_backward_tracks_match_torch(files, cache, backward):
    from taptr.api.predictor import Predictor
    from taptr.api.spec import ModelSpec

    _, weights, _ = files
    video = np.random.default_rng(1).integers(0, 256, (4, 48, 64, 3), dtype=np.uint8)
    queries = np.array([[1, 10.0, 20.0], [2, 40.0, 30.0], [0, 5.0, 5.0]], np.float32)
    graphs = ModelSpec(str(weights), engine="onnxruntime", threads=1).load()
    torch_result = Predictor.from_pretrained(str(weights), device="cpu").track(
        video, queries, backward=backward
    )
    result = graphs.track(video, queries, backward=backward)
    assert result.tracks.shape == (1, 4, 3, 2) and result.visibility.shape == (1, 4, 3)
    np.testing.assert_allclose(result.tracks.numpy(), torch_result.tracks.numpy(), atol=2e-3)


def test_the_export_is_made_once_and_reused(files, cache, capfd):
    track(files, "first", "--engine", "onnxruntime")  # exported here or by an earlier test
    capfd.readouterr()
    entries = sorted(path.name for path in cache.iterdir())
    assert track(files, "again", "--engine", "onnxruntime") == 0
    assert "exported" not in capfd.readouterr().err
    assert sorted(path.name for path in cache.iterdir()) == entries


def test_a_damaged_entry_is_exported_again_in_one_line(files, cache, capfd):
    track(files, "before", "--engine", "onnxruntime")
    (entry,) = [path for path in cache.iterdir() if not path.name.startswith(".")]
    (entry / KEY_FILE).write_text("{not json")
    capfd.readouterr()
    assert track(files, "after", "--engine", "onnxruntime") == 0
    lines = [line for line in capfd.readouterr().err.splitlines() if "damaged" in line]
    assert len(lines) == 1 and str(entry) in lines[0]
    assert json.loads((entry / KEY_FILE).read_text())["format"] == 1


def test_int8_runs_from_the_command_line_near_float32(files, cache, torch_run, capfd):
    """``--dtype int8``: the encoder quantised once (said in one line), tracks near float32."""
    assert track(files, "int8", "--engine", "onnxruntime", "--dtype", "int8") == 0
    assert track(files, "int8_again", "--engine", "onnxruntime", "--dtype", "int8") == 0
    made = [line for line in capfd.readouterr().err.splitlines() if "int8" in line]
    assert len(made) == 1, made  # made by the first run only
    expected = np.load(torch_run / "tracks.npz")["tracks"]
    found = np.load(files[0] / "int8" / "tracks.npz")["tracks"]
    assert np.abs(found - expected).mean() < 1.5  # pixels, on a 48 x 64 clip
    settings = json.loads((files[0] / "int8" / "settings.json").read_text())
    assert settings["dtype"] == "int8"


@pytest.mark.parametrize(
    ("extra", "named"),
    [
        (["--dtype", "int8"], "--engine onnxruntime"),
        (["--engine", "onnxruntime", "--dtype", "float16"], "not float16"),
        (["--engine", "onnxruntime", "--dtype", "bfloat16"], "engine='openvino'"),
    ],
)
def test_a_precision_the_engine_does_not_run_is_one_line(files, cache, extra, named, capfd):
    """Refused in one line, exit 2, and never taken for a damaged export."""
    track(files, "warm", "--engine", "onnxruntime")  # the export exists
    capfd.readouterr()
    assert track(files, "refused", *extra) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and named in err[0], err
    assert "damaged" not in err[0]


def test_a_v2_checkpoint_is_refused_in_one_line(files, cache, tmp_path, capfd):
    import taptr

    weights = save_checkpoint(taptr.build_model("tiny").eval(), tmp_path / "tiny_v2.pth")
    clip = files[2]
    argv = ["track", str(clip), "--grid", "2", "--checkpoint", str(weights), "--engine"]
    assert main([*argv, "onnxruntime", "--out", str(tmp_path / "out")]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "runs TAPTRv3 checkpoints" in err[0] and "--engine torch" in err[0]


def test_an_unknown_engine_is_refused(files, tmp_path, capfd):
    with pytest.raises(SystemExit) as exit:
        main(["track", str(files[2]), "--grid", "2", "--engine", "tensorflow"])
    assert exit.value.code == 2
    assert "--engine" in capfd.readouterr().err


def test_a_gpu_is_refused_for_a_graph_engine(files, tmp_path, capfd):
    argv = ["track", str(files[2]), "--grid", "2", "--engine", "openvino", "--device", "cuda"]
    assert main([*argv, "--out", str(tmp_path / "out")]) == 2
    assert "runs on the CPU" in capfd.readouterr().err


def test_the_spec_with_an_engine_pickles_and_keeps_the_corpus_digest():
    from taptr.corpus.settings import SPEED_ONLY

    spec = ModelSpec("tiny-v3", engine="openvino", threads=2)
    assert pickle.loads(pickle.dumps(spec)) == spec
    assert "engine" in SPEED_ONLY  # the same tracks up to rounding: a corpus may switch


def test_bench_times_the_engines_side_by_side(capsys):
    argv = ["bench", "--preset", "tiny-v3", "--size", "48", "64", "--frames", "3"]
    assert main([*argv, "--points", "4", "--threads", "1", "--engine", "torch", "onnxruntime"]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if "s/frame" in line]
    assert [line.split()[1] for line in lines] == ["torch", "onnxruntime"]
    assert "torch's time" in lines[1]


def test_bench_refuses_engines_for_a_v2_preset(capsys):
    assert main(["bench", "--preset", "tiny", "--engine", "onnxruntime"]) == 2
    assert "TAPTRv3 presets" in capsys.readouterr().err
