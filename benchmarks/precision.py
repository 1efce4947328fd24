"""Accuracy of half-precision autocast against float32 on the golden cases.

    python benchmarks/precision.py [--device cuda]

Builds the paper model on the golden fixtures' seed-1 weights (tests/fixtures), runs each
golden case (tests/fixtures/v2_*.npz: the official code's inputs) with the official forward
in float32, then under ``torch.autocast`` in bfloat16 and float16 (weights stay float32, as
``Predictor(autocast=...)`` and ``taptr track --dtype`` run them) and, on a CPU with native
bfloat16, with the fast execution's products in bfloat16 (`bfloat16_products`, what
``--dtype bfloat16`` runs on such a CPU), and prints, per case and
type: the largest position change in pixels of the case's frames, the largest visibility
logit change, and the share of visibility decisions that stay the same; float32 is also
compared with the official outputs. Writes benchmarks/results/precision-DEVICE.json, with
the machine it ran on.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the golden fixtures' helpers live with the tests

from tests.helpers import FIXTURES, golden_inputs, seed1_official_weights  # noqa: E402

from taptr.apps.benchmark import machine  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
CASES = ("v2_small_nonsquare", "v2_long")
TYPES = {"bfloat16": torch.bfloat16, "float16": torch.float16}


def seed1_model(device: str):
    """The paper model with the golden fixtures' generated weights."""
    import tempfile

    import taptr

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "taptrv2_seed1.pth"
        # laid out as the authors' release
        torch.save({"ema_model": seed1_official_weights("official-state-dict.txt")}, path)
        model = taptr.load_checkpoint(path)
    return model.to(device).eval()


def precision(device: str, name: str | None):
    """The context a type runs in: autocast, or (``bfloat16 products``) oneDNN bfloat16."""
    from taptr.model.ops.dense import bfloat16_products

    if name == "bfloat16 products":
        return bfloat16_products()
    dtype = TYPES.get(name)
    return torch.autocast(device, dtype=dtype, enabled=dtype is not None)


def run_case(model, golden: dict, device: str, name: str | None) -> dict:
    """Positions (N, T, 2) normalised and visibility logits (N, T) of one golden case."""
    import taptr

    inputs = [x.to(device) for x in golden_inputs(golden)]
    with torch.no_grad(), precision(device, name):
        out = taptr.official_forward(model, *inputs)
    positions = out["positions"].float().transpose(0, 1).cpu().numpy()
    logits = out["visibility_logits"][..., 1].float().transpose(0, 1).cpu().numpy()
    return {"positions": positions, "logits": logits}


def compare(run: dict, base_positions: np.ndarray, base_logits: np.ndarray, size) -> dict:
    """Largest pixel and logit changes and the share of equal visibility decisions."""
    height, width = size
    scale = np.array([width - 1, height - 1])
    written = np.isfinite(base_logits)
    return {
        "max_position_px": float(np.abs((run["positions"] - base_positions) * scale).max()),
        "max_logit": float(np.abs(run["logits"] - base_logits)[written].max()),
        "same_visibility": float(((run["logits"] > 0) == (base_logits > 0))[written].mean()),
    }


def main(argv: list[str] | None = None) -> int:
    from taptr.model.ops.dense import native_bfloat16

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    model = seed1_model(args.device)
    names = list(TYPES)
    if args.device == "cpu" and native_bfloat16():
        names.append("bfloat16 products")
    rows = {}
    for case in CASES:
        with np.load(FIXTURES / f"{case}.npz") as data:
            golden = {k: data[k] for k in data.files}
        size = golden["in_video_u8"].shape[-2:]
        base = run_case(model, golden, args.device, None)
        official = (golden["out_pred_xy_norm"], golden["out_vis_logits"][..., 1])
        rows[f"{case} float32 vs official"] = compare(base, *official, size)
        for name in names:
            # what --dtype bfloat16 runs on such a CPU: the trunk stored in bfloat16 too
            runner = copy.deepcopy(model).bfloat16_trunk() if name.endswith("products") else model
            run = run_case(runner, golden, args.device, name)
            rows[f"{case} {name} vs float32"] = compare(
                run, base["positions"], base["logits"], size
            )
    print(f"{'case':<44} {'max Δ px':>10} {'max Δ logit':>12} {'same vis.':>10}")
    for name, row in rows.items():
        print(
            f"{name:<44} {row['max_position_px']:>10.4f} {row['max_logit']:>12.4f} "
            f"{row['same_visibility']:>10.4f}"
        )
    RESULTS.mkdir(exist_ok=True)
    out = RESULTS / f"precision-{args.device}.json"
    record = {"device": args.device, "machine": machine(), "rows": rows}
    out.write_text(json.dumps(record, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
