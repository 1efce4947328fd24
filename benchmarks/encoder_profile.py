"""Where OpenVINO's encoder spends a frame, by layer type and kernel, per precision.

Compiles an export's encoder (float32, bfloat16, int8: `taptr.onnx.precisions`) for one
frame with OpenVINO's per-layer counters on, runs ``--frames`` frames after one untimed,
and prints one JSON object: per precision, the seconds per frame of each layer type (with
the kernels that ran it: ``brgconv_avx512_core_vnni_I8`` is an int8 convolution), largest
first, and the total. What stays in float32 in an int8 graph shows here.

    python benchmarks/encoder_profile.py r18_export/ --threads 2
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict

import openvino

from taptr.onnx.calibration_frames import calibration_frames
from taptr.onnx.openvino_engine import check_bfloat16, compile_config
from taptr.onnx.precisions import PRECISIONS, precision_files
from taptr.onnx.v3_manifest import V3Manifest


def profile(folder: str, precision: str, frames: int, threads: int) -> dict:
    """Seconds per frame by layer type (kernels named) of the encoder in ``precision``."""
    core = openvino.Core()
    if precision == "bfloat16":
        check_bfloat16(core, "CPU")
    manifest = V3Manifest.load(folder)
    path = precision_files(folder, manifest, precision)["encoder"]
    model = core.read_model(path)
    model.reshape({"frames": [1, 3, *manifest.input_size]})
    config = {**compile_config(precision, threads, None), "PERF_COUNT": "YES"}
    request = core.compile_model(model, "CPU", config).create_infer_request()
    clip = calibration_frames(frames + 1, tuple(manifest.input_size), seed=5)
    request.infer({"frames": clip[:1]})
    seconds: dict[str, float] = defaultdict(float)
    kernels: dict[str, set] = defaultdict(set)
    for frame in clip[1:]:
        request.infer({"frames": frame[None]})
        for layer in request.get_profiling_info():
            seconds[layer.node_type] += layer.real_time.total_seconds() / frames
            kernels[layer.node_type].add(layer.exec_type)
    ranked = sorted(seconds.items(), key=lambda item: -item[1])
    return {
        "total_seconds_per_frame": sum(seconds.values()),
        "by_layer_type": [
            {"type": name, "seconds": s, "kernels": sorted(kernels[name])} for name, s in ranked
        ],
    }


def main(argv: list[str] | None = None) -> int:
    """Profiles the encoder in each precision and prints one JSON object."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("export", help="a TAPTRv3 export folder")
    parser.add_argument("--precisions", nargs="+", default=list(PRECISIONS), choices=PRECISIONS)
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    report = {p: profile(args.export, p, args.frames, args.threads) for p in args.precisions}
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
