"""Shared fixtures: tiny models, seeded generators, the fabricated official checkpoint."""

from __future__ import annotations

import importlib.util
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import torch
from hypothesis import HealthCheck, settings

from tests.fake_drive import FakeDrive
from tests.helpers import (
    V3_FINGERPRINT,
    V3_SEED,
    generated_official_weights,
    seed1_official_weights,
)

if os.environ.get("PYTEST_XDIST_WORKER"):
    # two workers on two cores: one thread each, in the commands they run too
    torch.set_num_threads(1)
    os.environ["OMP_NUM_THREADS"] = "1"

# Fuzz tests (tests/test_fuzz.py): few examples by default so the suite stays in the CI
# budget; ``--hypothesis-profile=long`` runs >= 2,000 per test by hand.
_SLOW_OK = [HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much]
settings.register_profile(
    "taptr-ci", max_examples=50, deadline=None, database=None, suppress_health_check=_SLOW_OK
)
settings.register_profile("long", max_examples=2000, deadline=None, suppress_health_check=_SLOW_OK)
settings.load_profile("taptr-ci")

# The default model is the paper's weights from the Hugging Face cache or the network:
# tests never touch the network and never see a developer's cache, so the default falls
# back to the bundled model (tests of the download path set up a local fake Hub).
os.environ["HF_HUB_OFFLINE"] = "1"
os.environ["HF_HUB_CACHE"] = os.path.join(
    os.environ.get("TMPDIR", "/tmp"), f"taptr-tests-hub-cache-{os.getpid()}"
)
# measured speed choices (`taptr.runtime.measured`) go to a file of this run, not the user's
os.environ["TAPTR_MEASURED"] = os.path.join(
    os.environ.get("TMPDIR", "/tmp"), f"taptr-tests-measured-{os.getpid()}.json"
)
if importlib.util.find_spec("huggingface_hub"):
    # it reads these once, at import: import it now, not inside a test that patches them
    importlib.import_module("huggingface_hub.constants")


def pytest_configure(config: pytest.Config) -> None:
    """Registers ``cpu``: tests whose branch depends on the CPU's instructions."""
    config.addinivalue_line(
        "markers",
        "cpu: the branch taken depends on the CPU's instructions (bfloat16, oneDNN); .ci/run "
        "runs these again under each simulated CPU (TAPTR_CPU, taptr.model.ops.cpu_features)",
    )


@pytest.fixture
def simulated_cpu() -> Iterator[Callable[[str | None], None]]:
    """Call with a ``TAPTR_CPU`` level to run the test as on that CPU (None: as the run is).

    The package's own override (`taptr.model.ops.cpu_features`): taptr then takes the
    branches of a CPU without the instructions above the level. Restored afterwards.
    """
    from taptr.model.ops import cpu_features

    before = os.environ.get(cpu_features.VARIABLE)

    def simulate(level: str | None) -> None:
        value = before if level is None else level
        if value is None:
            os.environ.pop(cpu_features.VARIABLE, None)
        else:
            os.environ[cpu_features.VARIABLE] = value
        cpu_features.refresh()

    try:
        yield simulate
    finally:
        simulate(None)


@pytest.fixture
def generator() -> torch.Generator:
    """A seeded CPU generator."""
    return torch.Generator().manual_seed(0)


@pytest.fixture
def tiny_model():
    """A freshly built tiny model in eval mode, seeded."""
    from taptr import build_model

    torch.manual_seed(0)
    return build_model("tiny").eval()


@pytest.fixture(scope="session")
def tiny_checkpoint(tmp_path_factory) -> Path:
    """The tiny model (seed 0, 6 context points) saved as a checkpoint file."""
    from taptr import build_model
    from taptr.config import get_config
    from taptr.weights.checkpoint import save_checkpoint

    torch.manual_seed(0)
    built = build_model(get_config("tiny").replace(context_points=6))
    return save_checkpoint(built, tmp_path_factory.mktemp("tiny_model") / "tiny.pth")


@pytest.fixture(scope="session")
def official_state_dict() -> dict[str, torch.Tensor]:
    """The seed-1 official TAPTRv2 weights of the golden fixtures (``module.`` keys)."""
    return seed1_official_weights("official-state-dict.txt")


@pytest.fixture(scope="session")
def official_v1_checkpoint(tmp_path_factory) -> Path:
    """The seed-1 official TAPTR v1 weights, laid out as the authors' release."""
    weights = seed1_official_weights("official-v1-state-dict.txt")
    path = tmp_path_factory.mktemp("official_v1") / "taptrv1_seed1.pth"
    torch.save({"ema_model": weights, "epoch": 0}, path)
    return path


@pytest.fixture(scope="session")
def official_checkpoint(tmp_path_factory, official_state_dict) -> Path:
    """The seed-1 weights written as the authors' release is laid out."""
    path = tmp_path_factory.mktemp("official") / "taptrv2_seed1.pth"
    torch.save({"ema_model": official_state_dict}, path)
    return path


@pytest.fixture(scope="session")
def official_v3_checkpoint(tmp_path_factory) -> Path:
    """The v3 golden fixtures' TAPTRv3 ResNet-18 weights, laid out as the authors' release."""
    weights = generated_official_weights("official-v3-r18-state-dict.txt", V3_SEED, V3_FINGERPRINT)
    path = tmp_path_factory.mktemp("official_v3") / "TAPTRv3_resnet18_384x512.pth"
    torch.save({"ema_model": weights}, path)
    return path


@pytest.fixture
def weights_folder(monkeypatch, tmp_path) -> Path:
    """Downloads allowed (the suite runs offline) into an empty weights folder of our own."""
    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    monkeypatch.delenv("TAPTR_OFFLINE", raising=False)
    folder = tmp_path / "weights"
    monkeypatch.setenv("TAPTR_WEIGHTS_DIR", str(folder))
    return folder


@pytest.fixture
def fake_drive(monkeypatch) -> Iterator[Callable[..., FakeDrive]]:
    """Starts fake Drives (`tests.fake_drive.FakeDrive`) that taptr downloads from, on 127.0.0.1.

    Call it with the file's content and the fake's options; the last one started is the one
    taptr asks (``TAPTR_DRIVE_URL``). All are closed after the test.
    """
    servers: list[FakeDrive] = []

    def start(content: bytes, **options: Any) -> FakeDrive:
        fake = FakeDrive(content, **options)
        servers.append(fake)
        monkeypatch.setenv("TAPTR_DRIVE_URL", fake.url)
        return fake

    yield start
    for fake in servers:
        fake.close()


@pytest.fixture(scope="module")
def one_thread() -> Iterator[None]:
    """One torch thread for a module: on a shared 2-core machine two threads spin against
    each other."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
