"""Paths, loaders and inputs shared by the tests."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from taptr.config import ModelConfig, tiny

FIXTURES = Path(__file__).parent / "fixtures"
SHARED_MEDIA = Path(__file__).resolve().parents[2] / "shared" / "media"


def load_golden(case: str) -> dict[str, np.ndarray]:
    """A compact golden fixture (see scripts/compact_golden.py)."""
    with np.load(FIXTURES / f"{case}.npz") as data:
        return {k: data[k] for k in data.files}


SEED1_FINGERPRINTS = {
    "official-state-dict.txt": "3e475c2cad6f199fecbb3458d98eb67acc110c1b53ae1c02c6f3a2e88fe67d72",
    "official-v1-state-dict.txt": (
        "002c0715433fe8d9274a2a13fbae9617698ab8b9b8401b38211ca3dbe3f05c3c"
    ),
}
"""Fingerprints of the seed-1 weights the golden fixtures were made with, by key list."""

V3_SEED = 240716
V3_FINGERPRINT = "1107a079306d2ae4953c3c052d834f3daa40f10f4387ff6aabb2820233e8245c"
"""The seed and fingerprint of the TAPTRv3 ResNet-18 weights of the v3 golden fixtures."""


def generated_official_weights(
    key_list_name: str, seed: int, fingerprint: str | None = None
) -> dict[str, torch.Tensor]:
    """Official-layout weights (``module.`` keys) of the fixtures' generator for a key list."""
    spec = importlib.util.spec_from_file_location("make_weights", FIXTURES / "make_weights.py")
    make_weights = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(make_weights)
    key_list = make_weights.read_key_list(FIXTURES / key_list_name)
    state_dict, _ = make_weights.make_state_dict(key_list, seed=seed)
    if fingerprint is not None:
        assert make_weights.fingerprint(state_dict) == fingerprint
    return {"module." + k: torch.from_numpy(v) for k, v in state_dict.items()}


def seed1_official_weights(key_list_name: str) -> dict[str, torch.Tensor]:
    """The golden fixtures' seed-1 official weights (``module.`` keys) for a key list."""
    return generated_official_weights(key_list_name, 1, SEED1_FINGERPRINTS[key_list_name])


def golden_inputs(golden: dict[str, np.ndarray], dtype: torch.dtype = torch.float32):
    """`taptr.official_forward`'s inputs of a golden case: video, start frames, xy, labels."""
    from taptr.model.taptr import normalize_frames

    video = normalize_frames(torch.from_numpy(golden["in_video_u8"]).float() / 255)
    return (
        video.to(dtype),
        torch.from_numpy(golden["in_query_t"]),
        torch.from_numpy(golden["in_query_xy_norm"]).to(dtype),
        torch.from_numpy(golden["in_query_label"]),
    )


def float64_tiny_predictor():
    """A seeded tiny model's predictor in float64 (32 × 48 input): in float64 the different
    ways of running a video (per frame or per window, forwards or reversed) agree to rounding,
    so their results can be compared exactly."""
    import taptr

    torch.manual_seed(0)
    model = taptr.build_model("tiny")
    return taptr.Predictor(model, input_size=(32, 48), device="cpu", dtype=torch.float64)


def noise_video(frames: int, seed: int = 0) -> np.ndarray:
    """(frames, 40, 56, 3) uint8 uniform noise."""
    return (np.random.default_rng(seed).random((frames, 40, 56, 3)) * 255).astype(np.uint8)


def tiny_v1(**changes) -> ModelConfig:
    """The `tiny` preset as TAPTR v1 (standard attention, no APU, cost volume), then changes."""
    config = tiny().replace(
        version=1,
        cross_attention="standard",
        position_update=False,
        disentangler=False,
        cost_volume=True,
    )
    return config.replace(**changes)


def decode_window_inputs(
    memory: torch.Tensor, points: int, starts: torch.Tensor, generator: torch.Generator
) -> tuple[torch.Tensor, ...]:
    """Random inputs of the exported ``decode_window`` graph around ``memory`` (W_t, S, C).

    Returns memory, content (W_t, N, C), position logits (W_t, N, 4), initial content
    (N, C), and the tracking and update masks (W_t, N) of points starting at ``starts``
    (N,) frames into the window.
    """
    window, _, channels = memory.shape
    offsets = torch.arange(window)[:, None]
    return (
        memory,
        torch.randn(window, points, channels, generator=generator),
        torch.randn(window, points, 4, generator=generator),
        torch.randn(points, channels, generator=generator),
        offsets >= starts,
        offsets > starts,
    )


def run_torchrun(
    args: list[str], processes: int = 2, timeout: float = 180
) -> subprocess.CompletedProcess:
    """``taptr ARGS`` under torchrun with ``processes`` CPU processes (gloo), one thread each."""
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=os.pathsep.join(sys.path))
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone"]
    command += ["--nproc_per_node", str(processes), "-m", "taptr.cli.main"]
    return subprocess.run(
        [*command, *args], env=env, capture_output=True, text=True, timeout=timeout
    )


def panning_clip(count: int, speed: int, seed: int) -> np.ndarray:
    """(count, 32, 48, 3) frames of a random texture panning left by ``speed`` pixels a frame."""
    texture = np.random.default_rng(seed).integers(0, 256, (32, 48 + count * speed, 3), np.uint8)
    return np.stack([texture[:, speed * t : speed * t + 48] for t in range(count)])


def write_truncated_clip(path: Path) -> int:
    """A 24-frame clip cut short (its header still declares 24); returns the frames it decodes."""
    from taptr.io.video import read_video, video_info, write_video

    write_video(path, panning_clip(24, 2, 7), fps=10)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * 0.8)])
    decoded = len(read_video(path))
    assert video_info(path).num_frames == 24 and decoded < 24
    return decoded
