"""Writes compact copies of the official golden fixtures into tests/fixtures/.

The fixtures of ../shared/reference/golden/ and golden-v3/ hold float32 videos that are
exactly ``normalize_frames(u8 / 255)`` of a uint8 video; storing the uint8 video (checked
to reconstruct bit for bit, laid out (1, T, 3, H, W)) and only the keys the tests read
keeps the repository small. The evaluation-protocol case keeps its 256 × 256 video as it
is and drops only the long description (the ``.json`` next to it holds it).

Usage:
    python scripts/compact_golden.py [REFERENCE_DIR]
"""

import json
import sys
from pathlib import Path

import numpy as np

MEAN = np.array([0.485, 0.456, 0.406], np.float32).reshape(1, 1, 3, 1, 1)
STD = np.array([0.229, 0.224, 0.225], np.float32).reshape(1, 1, 3, 1, 1)
DROP_PREFIXES = (
    "in_pt_",
    "win_",
    "f64_win_",
    "f64_layers_",
    "dbg_hs_last",
    "dbg_content_final",
    "in_query_xy_px",
    "out_pred_boxes",
    "out_pred_xy_px",
    "f64_out_pred_boxes",
    "f64_out_pred_xy_px",
    "conventions_json",
    "init_query_vis",
    "f64_init",
    "frm_",
    "f64_frm_",
)
V3_CASES = ("v3_r18_small", "v3_r18_long", "v3_r18_fifo")
OUT = Path(__file__).resolve().parents[1] / "tests" / "fixtures"


def to_uint8(video: np.ndarray) -> np.ndarray:
    u8 = np.round((video.astype(np.float64) * STD + MEAN) * 255).astype(np.uint8)
    back = (u8.astype(np.float32) / np.float32(255) - MEAN) / STD
    if not np.array_equal(back, video):
        raise SystemExit("the video does not reconstruct exactly from uint8")
    return u8


def compact(src: Path) -> dict:
    z = np.load(src)
    keep = {}
    for key in z.files:
        if key.startswith(DROP_PREFIXES):
            continue
        value = z[key]
        if key == "in_video_u8" and "in_video" in z.files:
            continue  # rebuilt from in_video in the (1, T, 3, H, W) layout
        if key == "in_video":
            keep["in_video_u8"] = to_uint8(value)
        elif key == "dbg_memory_sample":
            keep[key] = value[..., :32]  # the first 32 channels localise encoder mistakes
        elif key in ("layers_pred_boxes", "layers_ca_boxes"):
            keep[key.replace("boxes", "xy")] = value[..., :2]
        else:
            keep[key] = value
    return keep


def write(folder: Path, case: str, data: dict) -> None:
    np.savez_compressed(OUT / f"{case}.npz", **data)
    meta = json.loads((folder / f"{case}.json").read_text())
    (OUT / f"{case}.json").write_text(json.dumps(meta, indent=1) + "\n")
    print(case, sorted(data))


def main() -> None:
    reference = (
        Path(sys.argv[1])
        if len(sys.argv) > 1
        else Path(__file__).resolve().parents[2] / "shared/reference"
    )
    for case in ("v2_small_nonsquare", "v2_long", "loss_v2", "v1_small"):
        write(reference / "golden", case, compact(reference / "golden" / f"{case}.npz"))
    for case in V3_CASES:
        data = compact(reference / "golden-v3" / f"{case}.npz")
        if case == "v3_r18_fifo":  # the held frames after the last one show the FIFO order
            data["dbg_content_final"] = np.load(reference / "golden-v3" / f"{case}.npz")[
                "dbg_content_final"
            ]
        write(reference / "golden-v3", case, data)
    with np.load(reference / "golden-v3" / "v3_protocol_first.npz") as z:
        protocol = {key: z[key] for key in z.files if key != "conventions_json"}
    write(reference / "golden-v3", "v3_protocol_first", protocol)


if __name__ == "__main__":
    main()
