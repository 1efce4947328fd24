"""Where a TAPTRv3's CPU bfloat16 path loses precision: bfloat16 in one part at a time.

    OMP_NUM_THREADS=1 python benchmarks/bf16_precision.py --model CHECKPOINT \\
        --videos data/synthetic/val --num-videos 4 --frames 24 --points 64 \\
        --reference taptr-small-synthetic
    OMP_NUM_THREADS=1 python benchmarks/bf16_precision.py --model taptrv3 --frames 4 \\
        --points 800 --size 384 512

Tracks the same videos and queries in float32 and in bfloat16 switched on in one part of
the model at a time, and prints one JSON object: per setting, how far the points moved
against float32 (pixels of the input video, over the frames after each query frame and on
the first of them alone), how many visibility decisions flipped at the model's threshold,
and the seconds a tracked frame took. ``all (predictor)`` is
``Predictor(autocast=torch.bfloat16)`` as users run it; the other settings run a float32
predictor whose chosen modules enter the bfloat16 product type
(`taptr.model.ops.dense.bfloat16_products`) from a forward pre-hook to the matching
post-hook, and ``trunk`` stores the backbone in bfloat16 (`TAPTR.bfloat16_trunk`). A module
pattern mapped to float32 switches bfloat16 off again inside an enclosing bfloat16 part.
Every predictor keeps the oneDNN products (the only ones with bfloat16 kernels), so the
float32 side differs from bfloat16 by the product type alone.

``--model`` is a checkpoint, a bundled name or a preset (random weights); ``--videos`` a
Kubric-layout folder whose ground-truth points give the queries (each on its first visible
frame), else the rendered sample clip with random queries on frame 0. ``--reference``
runs float32 and ``all (predictor)`` for a second model on the same videos and queries.
Needs a CPU with native bfloat16 (AVX512-BF16 or AMX).
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import fnmatch
import json
import sys
import time
from collections.abc import Iterator

import numpy as np
import torch
from torch import nn

from taptr.api.predictor import Predictor
from taptr.data.kubric import list_sequences, read_sequence
from taptr.data.sample_video import make_sample_clip
from taptr.model.ops import dense
from taptr.model.taptr import TAPTR
from taptr.weights.registry import load_model

BF16, F32 = torch.bfloat16, torch.float32
LAYERS = "decoder.layers.*."
ALL_PARTS = {"input_projections": BF16, "encoder": BF16, "query_init": BF16, "decoder": BF16}
SETTINGS: dict[str, tuple[bool, dict[str, torch.dtype]]] = {
    "all (hooks)": (True, ALL_PARTS),
    "trunk": (True, {}),
    "encoder": (False, {"encoder": BF16}),
    "query_init": (False, {"query_init": BF16}),
    "decoder": (False, {"decoder": BF16}),
    "cross_attention": (False, {LAYERS + "cross_attention": BF16}),
    "cross_attention.similarity": (False, {LAYERS + "cross_attention.similarity": BF16}),
    "long_temporal": (False, {LAYERS + "long_temporal": BF16}),
    "decoder rest": (
        False,
        {"decoder": BF16, LAYERS + "cross_attention": F32, LAYERS + "long_temporal": F32},
    ),
    **{
        f"cross_attention.{part}": (False, {f"{LAYERS}cross_attention.{part}": BF16})
        for part in ("sampling_offsets", "key_proj", "value_proj", "query_proj", "output_proj")
    },
    "position_heads": (False, {"decoder.position_heads.*": BF16}),
    "ffn": (False, {LAYERS + "ffn": BF16}),
    "all but sampling_offsets": (
        True,
        {**ALL_PARTS, LAYERS + "cross_attention.sampling_offsets": F32},
    ),
    "all but similarity": (True, {**ALL_PARTS, LAYERS + "cross_attention.similarity": F32}),
    "all but cross_attention": (True, {**ALL_PARTS, LAYERS + "cross_attention": F32}),
}
"""Setting → (trunk stored in bfloat16, module-name pattern → product type inside it)."""
CONTROL = "float32 (BLAS products)"


def layer_types(model: nn.Module, parts: dict[str, torch.dtype]) -> dict[int, torch.dtype]:
    """id(module) → product type of each module matching a pattern of ``parts`` (the last)."""
    types = {}
    for name, module in model.named_modules():
        matched = [kind for pattern, kind in parts.items() if fnmatch.fnmatchcase(name, pattern)]
        if matched:
            types[id(module)] = matched[-1]
    return types


@contextlib.contextmanager
def product_type(kind: torch.dtype | None) -> Iterator[None]:
    """Runs the block in product type ``kind`` (None: as it is)."""
    if kind is None:
        yield
        return
    token = dense._PRODUCT_TYPE.set(kind)
    try:
        yield
    finally:
        dense._PRODUCT_TYPE.reset(token)


def product_hooks(model: nn.Module, types: dict[int, torch.dtype]) -> None:
    """Forward hooks that run each module of ``types`` (`layer_types`) in its product type."""
    for module in model.modules():
        kind = types.get(id(module))
        if kind is None:
            continue
        scopes: list = []

        def enter(_module, _args, kind=kind, scopes=scopes) -> None:
            scopes.append(product_type(kind))
            scopes[-1].__enter__()

        def leave(_module, _args, _output, scopes=scopes) -> None:
            scopes.pop().__exit__(None, None, None)

        module.register_forward_pre_hook(enter)
        module.register_forward_hook(leave)


@contextlib.contextmanager
def layer_calls(types: dict[int, torch.dtype]) -> Iterator[None]:
    """Treats ``apply_linear(layer, ...)`` like a call of ``layer`` for `product_hooks`.

    The models run most linear layers through ``dense.apply_linear``, not the module's
    call, so a module hook never sees them: every taptr module's name for it is swapped
    for one that enters the layer's product type, and put back after the block.
    """
    original = dense.apply_linear

    def apply_linear(layer: nn.Linear, x: torch.Tensor, **options) -> torch.Tensor:
        with product_type(types.get(id(layer))):
            return original(layer, x, **options)

    holders = [
        module
        for name, module in list(sys.modules.items())
        if name.startswith("taptr.") and getattr(module, "apply_linear", None) is original
    ]
    for module in holders:
        module.apply_linear = apply_linear
    try:
        yield
    finally:
        for module in holders:
            module.apply_linear = original


def predictor_for(model: TAPTR, threshold: float | None, autocast: torch.dtype | None):
    """A CPU predictor on a copy of ``model`` that keeps the oneDNN products, no capture."""
    predictor = Predictor(
        copy.deepcopy(model),
        device="cpu",
        autocast=autocast,
        visibility_threshold=threshold,
        frames_per_call=1,
        capture="off",
    )
    # the float32 choice may have picked the BLAS: the products must be oneDNN's to compare
    predictor.model.set_execution(
        dataclasses.replace(predictor.model.execution, onednn_linear=True)
    )
    return predictor


def track_all(predictor: Predictor, clips: list) -> tuple[list, float]:
    """Tracks every (video, queries) pair; returns the results and seconds per frame."""
    results, frames = [], 0
    start = time.perf_counter()
    for video, queries in clips:
        results.append(predictor.track(video, queries))
        frames += video.shape[0]
    return results, (time.perf_counter() - start) / frames


def compare(base: list, runs: list, clips: list) -> dict:
    """Position moves (pixels) and visibility flips of ``runs`` against ``base``.

    Counted on the frames after each query frame (the query frame returns the query
    itself); ``first frame`` is the first of them, the only one a random model keeps sane.
    """
    moved, first, flips = [], [], []
    for b, r, (video, queries) in zip(base, runs, clips, strict=True):
        frames = np.arange(video.shape[0])[:, None]
        starts = queries[None, :, 0].astype(int)
        move = (r.tracks[0] - b.tracks[0]).norm(dim=-1).numpy()  # (T, N)
        flip = (r.visibility[0] != b.visibility[0]).numpy()
        moved.append(move[frames > starts])
        first.append(move[frames == starts + 1])
        flips.append(flip[frames > starts])
    moved_all, first_all, flips_all = (np.concatenate(x) for x in (moved, first, flips))
    return {
        "max_px": round(float(moved_all.max()), 3),
        "p99_px": round(float(np.percentile(moved_all, 99)), 3),
        "median_px": round(float(np.median(moved_all)), 4),
        "over_1px_percent": round(100 * float((moved_all > 1).mean()), 2),
        "first_frame_max_px": round(float(first_all.max()), 3),
        "first_frame_median_px": round(float(np.median(first_all)), 4),
        "flips_percent": round(100 * float(flips_all.mean()), 2),
        "decisions": int(flips_all.size),
    }


def kubric_clips(root: str, count: int, frames: int, points: int, seed: int) -> list:
    """(video (T, H, W, 3), queries (N, 3)) pairs: true points on their first visible frame."""
    rng = np.random.default_rng(seed)
    clips = []
    for folder in list_sequences(root)[:count]:
        sample = read_sequence(folder)
        visible = sample.visible[:frames]
        candidates = np.flatnonzero(visible[:-1].any(0))  # seen before the last frame
        chosen = rng.choice(candidates, min(points, len(candidates)), replace=False)
        starts = visible[:, chosen].argmax(0)
        xy = sample.tracks[starts, chosen]
        queries = np.concatenate([starts[:, None], xy], axis=1).astype(np.float32)
        clips.append((sample.video[:frames], queries))
    return clips


def sample_clips(frames: int, points: int, size: tuple[int, int], seed: int) -> list:
    """The rendered sample clip with random queries on frame 0."""
    video = make_sample_clip(num_frames=frames, height=size[0], width=size[1], seed=seed).video
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 1, (points, 2)) * np.array([size[1] - 1, size[0] - 1])
    queries = np.concatenate([np.zeros((points, 1)), xy], axis=1).astype(np.float32)
    return [(video, queries)]


def run_settings(
    model: TAPTR, threshold: float | None, clips: list, names: list[str]
) -> dict[str, dict]:
    """Float32, then each setting, compared with float32."""
    base, seconds = track_all(predictor_for(model, threshold, None), clips)
    report = {"float32": {"seconds_per_frame": round(seconds, 4)}}
    for name in [CONTROL, "all (predictor)", *names]:
        types: dict[int, torch.dtype] = {}
        if name == "all (predictor)":
            predictor = predictor_for(model, threshold, BF16)
        elif name == CONTROL:  # float32 summed in another order: the model's own chaos
            predictor = predictor_for(model, threshold, None)
            execution = dataclasses.replace(predictor.model.execution, onednn_linear=False)
            predictor.model.set_execution(execution)
        else:
            trunk, parts = SETTINGS[name]
            predictor = predictor_for(model, threshold, None)
            if trunk:
                predictor.model.bfloat16_trunk()
            types = layer_types(predictor.model, parts)
            product_hooks(predictor.model, types)
        with layer_calls(types):
            results, seconds = track_all(predictor, clips)
        report[name] = {**compare(base, results, clips), "seconds_per_frame": round(seconds, 4)}
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", required=True, help="checkpoint, bundled name or preset")
    parser.add_argument("--videos", help="Kubric-layout folder (default: the sample clip)")
    parser.add_argument("--num-videos", type=int, default=4)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--points", type=int, default=64)
    parser.add_argument("--size", type=int, nargs=2, default=(384, 512), help="sample clip H W")
    parser.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    parser.add_argument("--reference", help="second model: float32 and all (predictor) only")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if not dense.native_bfloat16():
        parser.error("this CPU has no native bfloat16 (AVX512-BF16 or AMX)")
    torch.manual_seed(args.seed)  # a preset's random weights
    if args.videos:
        clips = kubric_clips(args.videos, args.num_videos, args.frames, args.points, args.seed)
    else:
        clips = sample_clips(args.frames, args.points, tuple(args.size), args.seed)
    choice = load_model(args.model)
    out = {
        "model": args.model,
        "videos": args.videos or "sample clip",
        "clips": len(clips),
        "frames": args.frames,
        "points": args.points,
        "threads": torch.get_num_threads(),
        "settings": run_settings(choice.model, choice.visibility_threshold, clips, args.settings),
    }
    if args.reference:
        ref = load_model(args.reference)
        out["reference"] = {
            "model": args.reference,
            "settings": run_settings(ref.model, ref.visibility_threshold, clips, []),
        }
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
