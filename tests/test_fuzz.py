"""Fuzz tests: generated and mutated files through every reader (issue 15).

Each input category of `tests.fuzz_targets` must give a valid result or a clean error
(`ValueError`, `FileNotFoundError`), never another exception and never NaN or a malformed
array. The default profile (tests/conftest.py) runs a few examples per category;
``--hypothesis-profile=long`` runs 2,000, and ``scripts/fuzz_report.py`` tabulates them.
Every input also runs under `tests.fuzz_hostile.memory_bound` (peak RSS growth per input).
"""

from __future__ import annotations

import contextlib
import os
import warnings

import pytest
from hypothesis import given, settings

from tests import fuzz_corpus as corpus
from tests import fuzz_downloads as downloads
from tests import fuzz_export as export
from tests import fuzz_hostile as hostile
from tests import fuzz_options as options
from tests import fuzz_targets as targets

# each corpus example writes a folder of parts and reruns over it: a quarter of the
# profile's examples, at least 15 (``--hypothesis-profile=long`` runs 500 of each)
CORPUS_EXAMPLES = max(15, settings.default.max_examples // 4)


def _run(target, value) -> None:
    with warnings.catch_warnings(), targets.memory_bound():
        warnings.simplefilter("ignore")  # a truncated video's frame-count warning is fine
        with contextlib.suppress(targets.CLEAN):
            target(value)


@given(targets.mutated_pickles)
def test_fuzz_tapvid_mutated_pickles(data):
    _run(targets.read_tapvid, data)


@given(targets.opcode_pickles)
def test_fuzz_tapvid_unpickler_attacks(data):
    _run(targets.read_tapvid, data)


@given(targets.tapvid_items())
def test_fuzz_tapvid_generated_items(data):
    _run(targets.read_tapvid, data)


@given(targets.kubric_folders())
def test_fuzz_kubric_folders(files):
    _run(targets.read_kubric, files)


@given(targets.checkpoint_mutations())
def test_fuzz_checkpoint_mutations(data):
    _run(targets.read_checkpoint, data)


@given(targets.checkpoint_bytes)
def test_fuzz_checkpoint_bytes(data):
    _run(targets.read_checkpoint, data)


@given(targets.video_inputs())
def test_fuzz_videos_and_frame_folders(files):
    _run(targets.read_video_files, files)


@given(targets.named_weights)
def test_fuzz_named_weights_of_another_architecture(case):
    _run(targets.read_named_weights, case)


@given(hostile.decoder_inputs())
def test_fuzz_decoders_by_content(value):
    _run(hostile.read_by_role, value)


@given(hostile.lying_checkpoints())
def test_fuzz_checkpoint_lying_record_sizes(data):
    _run(hostile.read_watched_checkpoint, data)


@given(hostile.view_checkpoints())
def test_fuzz_checkpoint_logical_views(data):
    _run(hostile.read_watched_checkpoint, data)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs POSIX special files")
@given(hostile.special_paths)
def test_fuzz_special_files(value):
    _run(hostile.read_special, value)


@given(hostile.resource_requests())
def test_fuzz_resource_estimates(request):
    _run(hostile.check_estimate, request)


@given(options.measured_files())
def test_fuzz_measured_choices_file(data):
    _run(options.read_measured, data)


@given(options.settings_entries())
def test_fuzz_result_folder_settings(entry):
    _run(options.rerun_over_settings, entry)


@given(options.bench_options())
def test_fuzz_bench_options(argv):
    _run(options.check_bench, argv)


@given(downloads.kept_timings())
def test_fuzz_kept_capture_timings(value):
    _run(downloads.run_over_kept_timing, value)


@settings(max_examples=CORPUS_EXAMPLES)
@given(corpus.index_tamperings())
def test_fuzz_corpus_tampered_index(case):
    pytest.importorskip("pyarrow")
    _run(corpus.tamper_index, case)


@settings(max_examples=CORPUS_EXAMPLES)
@given(corpus.part_tamperings())
def test_fuzz_corpus_tampered_parts(case):
    pytest.importorskip("pyarrow")
    _run(corpus.tamper_part, case)


@settings(max_examples=CORPUS_EXAMPLES)
@given(corpus.folder_tamperings())
def test_fuzz_corpus_tampered_marker_and_links(case):
    pytest.importorskip("pyarrow")
    _run(corpus.tamper_folder, case)


# each example serves a download: a quarter of the profile's examples, at least 15
@settings(max_examples=max(15, settings.default.max_examples // 4))
@given(downloads.downloads)
def test_fuzz_downloads_from_a_misbehaving_drive(case):
    pytest.importorskip("gdown")
    _run(downloads.download_from_misbehaving_drive, case)


@given(export.manifest_edits())
def test_fuzz_export_manifest(data):
    _run(export.read_manifest_folder, data)


@given(export.huge_manifests)
def test_fuzz_export_manifest_far_too_large(size):
    _run(export.read_huge_manifest, size)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs POSIX special files")
@given(export.tampered_graphs)
def test_fuzz_export_graph_files(value):
    pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    _run(export.open_tampered, value)


def test_every_category_is_fuzzed():
    tested = {name for name in globals() if name.startswith("test_fuzz_")}
    assert len(tested) == len(targets.CATEGORIES)


@pytest.mark.parametrize("name", sorted(targets.CATEGORIES))
def test_classify_sorts_outcomes(name):
    strategy, target = targets.CATEGORIES[name]
    assert targets.classify(lambda _: None, None) == "valid"
    assert targets.classify(lambda _: int("x"), None) == "clean"
    assert targets.classify(lambda _: [][1], None) == "traceback"
    assert callable(target) and strategy is not None
