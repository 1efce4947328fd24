"""How far TAPTRv3 lands from the official code on the golden cases, in numbers.

    python benchmarks/golden_v3.py

Loads the v3 golden fixtures' ResNet-18 weights (generated as the official release is laid
out, tests/fixtures), runs every v3 golden case (tests/fixtures/v3_*.npz: the official
streaming evaluation's inputs and outputs) through `taptr.official_forward` in float32 with
the fast and the reference execution, and the cases that have float64 references in float64,
and prints the largest normalised position and visibility-logit differences and the visibility
decisions that differ at 0.45. tests/test_golden_v3.py asserts the bounds; this prints the
values. Writes benchmarks/results/golden-v3.json.
"""

from __future__ import annotations

import copy
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the golden fixtures' helpers live with the tests

from tests.helpers import (  # noqa: E402
    V3_FINGERPRINT,
    V3_SEED,
    generated_official_weights,
    golden_inputs,
    load_golden,
)

RESULTS = Path(__file__).resolve().parent / "results"
CASES = {"v3_r18_small": None, "v3_r18_long": None, "v3_r18_fifo": 16}
"""Each case and its history limit."""
FLOAT64_CASES = ("v3_r18_small", "v3_r18_long")
THRESHOLD = 0.45


def v3_model():
    """TAPTRv3-R18 on the golden weights, loaded through the released-file path."""
    import taptr

    weights = generated_official_weights("official-v3-r18-state-dict.txt", V3_SEED, V3_FINGERPRINT)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "TAPTRv3_resnet18_384x512.pth"
        torch.save({"ema_model": weights}, path)
        return taptr.load_checkpoint(path).eval()


def deviations(model, case: str, dtype: torch.dtype, prefix: str = "") -> dict:
    """Largest |Δ| of positions (normalised) and visibility logits, and flipped decisions."""
    import taptr

    golden = load_golden(case)
    with torch.no_grad():
        out = taptr.official_forward(
            model, *golden_inputs(golden, dtype), history_frames=CASES[case]
        )
    positions = out["positions"].transpose(0, 1).double().numpy()  # (T, N, 2) → (N, T, 2)
    logits = out["visibility_logits"].transpose(0, 1).double().numpy()  # (N, T, 3)
    theirs = golden[f"{prefix}out_vis_logits"]
    visible = logits[..., 1] > np.log(THRESHOLD / (1 - THRESHOLD))
    official_visible = theirs[..., 1] > np.log(THRESHOLD / (1 - THRESHOLD))
    return {
        "position": float(np.abs(positions - golden[f"{prefix}out_pred_xy_norm"]).max()),
        "visibility_logit": float(np.abs(logits - theirs).max()),
        "decisions_differ": int((visible != official_visible).sum()),
        "decisions": int(visible.size),
    }


def main() -> int:
    model = v3_model()
    rows = {}
    for execution in ("fast", "reference"):
        run = copy.deepcopy(model).set_execution(execution)
        for case in CASES:
            rows[f"{case} float32 {execution}"] = deviations(run, case, torch.float32)
    double = copy.deepcopy(model).double().set_execution("reference")
    for case in FLOAT64_CASES:
        rows[f"{case} float64 reference"] = deviations(double, case, torch.float64, "f64_")
    print(f"{'case':<36} {'max |Δ position|':>17} {'max |Δ logit|':>14} {'decisions differ':>17}")
    for name, row in rows.items():
        print(
            f"{name:<36} {row['position']:>17.2e} {row['visibility_logit']:>14.2e} "
            f"{row['decisions_differ']:>8} / {row['decisions']}"
        )
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "golden-v3.json").write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
