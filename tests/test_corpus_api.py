"""The corpus from Python (issue 50): a `ModelSpec` in, no command-line code, no predictor.

The driver's settings digests and memory per actor come from the spec and its
checkpoint's config, without building the tracker; they must equal what the predictor
itself gave (the digests of existing corpora, the actors' reservations). The Python API
runs a corpus in tests/test_corpus.py (``test_results_go_to_an_object_store``), on the
Ray instance that test starts anyway.
"""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest

from taptr.api.spec import ModelSpec
from taptr.corpus.inputs import CorpusVideo, QuerySpec

SRC = Path(__file__).resolve().parents[1] / "src" / "taptr"


def _predictor_digests(spec: ModelSpec, queries: list[QuerySpec], max_frames, backward):
    """The digests as the driver made them before: from a predictor on the CPU."""
    from taptr.api.predictor import Predictor
    from taptr.runtime.precision import autocast_type
    from taptr.settings_record import query_record, record_digest, settings_record

    predictor = Predictor.from_pretrained(
        spec.checkpoint, device="cpu", input_size=spec.input_size,
        context_points=spec.context_points, support_points=spec.support,
        history_frames=spec.history_frames, autocast=autocast_type(spec.dtype),
        kernel="gather", frames_per_call=1, capture="off",
    )  # fmt: skip
    base = settings_record(
        predictor, {}, dtype=spec.dtype, max_frames=max_frames, backward=backward
    )
    digests = []
    for query in queries:
        points = None if query.points is None else __import__("numpy").float32(query.points)
        record = query_record(points, query.grid, query.mask, query.query_frame, query.mask_stride)
        digests.append(record_digest({**base, "queries": record}))
    weights = sum(p.numel() * p.element_size() for p in predictor.model.parameters())
    return digests, predictor, weights


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """The tiny model saved with a calibrated visibility threshold."""
    import torch

    from taptr import build_model
    from taptr.config import get_config
    from taptr.weights.checkpoint import save_checkpoint

    torch.manual_seed(1)
    model = build_model(get_config("tiny").replace(context_points=4))
    path = tmp_path_factory.mktemp("calibrated") / "calibrated.pth"
    return save_checkpoint(model, path, visibility_threshold=0.3)


def test_digests_and_memory_equal_the_predictor_s_without_building_it(
    tiny_checkpoint, calibrated, monkeypatch
):
    from taptr.corpus import cluster
    from taptr.corpus.model_facts import model_facts
    from taptr.corpus.settings import TrackSettings, with_digests
    from taptr.memory_estimate import estimate_tracking

    queries = [QuerySpec(grid=3), QuerySpec(points=((0.0, 4.0, 5.0), (2.0, 1.5, 3.0)))]
    videos = [CorpusVideo(f"v{i}", "x.mp4", spec) for i, spec in enumerate(queries)]
    specs = [
        ModelSpec(str(tiny_checkpoint)),
        ModelSpec("tiny", device="cuda", kernel="grid_sample", capture="on"),  # speed only
        ModelSpec(str(calibrated), input_size=(48, 64), context_points=3, support="grid"),
        ModelSpec("tiny-v3", dtype="bfloat16", history_frames=5),
    ]
    for spec, (max_frames, backward) in zip(specs, [(None, False), (7, True)] * 2, strict=True):
        facts = model_facts(spec)
        digested = with_digests(videos, spec, facts, TrackSettings(max_frames, backward))
        expected, predictor, weights = _predictor_digests(spec, queries, max_frames, backward)
        assert [video.digest for video in digested] == expected, spec
        run = estimate_tracking(
            predictor.model.config, input_size=predictor.input_size,
            num_frames=cluster.TYPICAL_FRAMES,
            num_points=cluster.TYPICAL_POINTS + predictor.context_points,
            frame_size=cluster.TYPICAL_SIZE, whole_video=False,
        )  # fmt: skip
        if spec.dtype == "float32":  # in bfloat16 a CPU predictor keeps copies in half
            assert cluster.actor_memory(facts) == cluster.PROCESS_BYTES + weights + run.total
        assert facts.weight_bytes == 4 * sum(p.numel() for p in predictor.model.parameters())
    assert model_facts(specs[2]).visibility_threshold == 0.3


def test_the_driver_builds_no_predictor(tiny_checkpoint, monkeypatch):
    from taptr.api import predictor as module
    from taptr.corpus.model_facts import model_facts

    def refused(*args, **kwargs):
        raise AssertionError("the driver built a predictor")

    monkeypatch.setattr(module.Predictor, "__init__", refused)
    monkeypatch.setattr(module.Predictor, "from_pretrained", refused)
    assert model_facts(ModelSpec(str(tiny_checkpoint))).config.input_size == (64, 64)


def test_a_field_a_spec_gains_later_flows_into_the_digest(tiny_checkpoint):
    from taptr.corpus.model_facts import model_facts
    from taptr.corpus.settings import TrackSettings, with_digests

    @dataclasses.dataclass(frozen=True)
    class LaterSpec(ModelSpec):
        refine: str = "off"  # a made-up option; engine, once the example, is speed only

    videos = [CorpusVideo("v", "x.mp4", QuerySpec(grid=2))]
    facts = model_facts(ModelSpec(str(tiny_checkpoint)))

    def digest(spec: ModelSpec) -> str:
        return with_digests(videos, spec, facts, TrackSettings())[0].digest

    plain = digest(ModelSpec(str(tiny_checkpoint)))
    assert digest(LaterSpec(str(tiny_checkpoint))) == plain  # at its default: same results
    assert digest(LaterSpec(str(tiny_checkpoint), refine="twice")) != plain


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        (ModelSpec(dtype="float8"), "dtype must be one of float32, bfloat16, float16"),
        (ModelSpec(support="everywhere"), "support must be one of"),
        (ModelSpec(context_points=-1), "context_points must be a whole number >= 0"),
        (ModelSpec(input_size=(0, 64)), r"input_size must be \(height, width\)"),
        (ModelSpec("tiny", history_frames=4), "history_frames applies to TAPTRv3 models only"),
    ],
)
def test_a_spec_no_predictor_takes_is_refused_before_anything_is_read(spec, message):
    from taptr.corpus.model_facts import model_facts

    with pytest.raises(ValueError, match=message):
        model_facts(spec)


def test_the_corpus_imports_nothing_from_the_command_line():
    for path in sorted((SRC / "corpus").glob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            names = (
                [node.module or ""]
                if isinstance(node, ast.ImportFrom)
                else [alias.name for alias in node.names]
                if isinstance(node, ast.Import)
                else []
            )
            assert not any(name.startswith("taptr.cli") for name in names), path.name
