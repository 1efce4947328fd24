"""``TAPTR_CPU``: taptr takes the branches of a lesser CPU on any host (issue 45).

The suite must pass on CPUs with and without AVX512-BF16, AMX and AVX-512, but a host has
one set of instructions: `taptr.model.ops.cpu_features` takes away what is above the
level named, so each branch runs here. `simulated_cpu` (tests/conftest.py) sets it for one
test; .ci/run runs the ``cpu``-marked tests again under each level.
"""

from __future__ import annotations

import pytest
import torch

from taptr.model.ops import cpu_features, dense

pytestmark = pytest.mark.cpu

HOST = torch.backends.cpu.get_cpu_capability()


def test_without_bfloat16_the_cpu_has_none(simulated_cpu):
    simulated_cpu("avx512")
    assert cpu_features.bfloat16_hardware() == {"avx512_bf16": False, "amx": False}
    assert not dense.native_bfloat16()
    with pytest.raises(RuntimeError, match="no native bfloat16"), dense.bfloat16_products():
        pass
    assert cpu_features.simulated() == "avx512"


def test_without_avx512_the_capability_is_avx2(simulated_cpu):
    simulated_cpu("avx2")
    expected = "AVX2" if HOST in ("AVX2", "AVX512") else HOST
    assert cpu_features.cpu_capability() == expected
    assert not dense.native_bfloat16()
    assert dense.onednn_available() == (
        expected == "AVX2"
        and torch.backends.mkldnn.is_available()
        and hasattr(torch.ops.mkldnn, "_linear_pointwise")
    )


def test_without_vector_instructions_products_are_plain(simulated_cpu):
    simulated_cpu("default")
    assert not dense.onednn_available()
    x, weight = torch.randn(3, 8), torch.randn(4, 8)
    assert not dense.onednn_applies(x, weight)
    torch.testing.assert_close(
        dense.linear(x, weight, None, onednn=True), torch.nn.functional.linear(x, weight)
    )


def test_naming_the_highest_level_takes_nothing_away(simulated_cpu):
    simulated_cpu("amx")
    assert cpu_features.cpu_capability() == HOST
    assert cpu_features.bfloat16_hardware() == {
        "avx512_bf16": torch.cpu._is_avx512_bf16_supported(),
        "amx": torch.cpu._is_amx_tile_supported(),
    }
    assert cpu_features.simulated() is None


def test_an_unknown_level_is_refused_with_the_levels(simulated_cpu):
    simulated_cpu("avx1024")
    with pytest.raises(ValueError, match="TAPTR_CPU='avx1024' is no CPU level; choose from"):
        cpu_features.ceiling()


def test_a_simulated_cpu_keeps_its_own_measured_choices(simulated_cpu):
    from taptr.runtime.measured import device_name

    simulated_cpu("avx2")
    lesser = device_name(torch.device("cpu"))
    assert "(AVX2," in lesser or HOST not in ("AVX2", "AVX512")
    simulated_cpu("default")
    assert "(DEFAULT," in device_name(torch.device("cpu"))


def test_the_machine_record_says_the_cpu_is_simulated(simulated_cpu):
    from taptr.apps.benchmark import machine

    simulated_cpu("avx512")
    record = machine()
    assert record["cpu_simulated"] == "avx512"
    assert record["cpu_bfloat16"] == {"avx512_bf16": False, "amx": False}


def test_the_predictor_runs_float32_without_bfloat16(simulated_cpu):
    from taptr.api.predictor import Predictor
    from taptr.model.build import build_model

    simulated_cpu("avx512")
    with pytest.warns(UserWarning, match="this CPU has no native bfloat16"):
        predictor = Predictor(
            build_model("tiny"), device="cpu", autocast=torch.bfloat16, frames_per_call=1
        )
    assert predictor.autocast is None
    video = torch.zeros(1, 4, 3, 32, 32, dtype=torch.uint8)
    result = predictor.track(video, torch.tensor([[0.0, 5.0, 5.0]]))
    assert result.tracks.dtype == torch.float32 and torch.isfinite(result.tracks).all()
