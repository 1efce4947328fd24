"""Convert a checkpoint to taptr's own format: what ``taptr convert`` does, in Python.

    python examples/convert_checkpoint.py taptrv2.pth taptrv2-taptr.pth
    python examples/convert_checkpoint.py taptrv2.pth taptrv2-half.pth --half
    python examples/convert_checkpoint.py          # demo: a freshly built tiny model

`taptr.load_checkpoint` reads the authors' release (``taptrv2.pth`` from the Hugging Face
repository HYeungLee/TAPTR-Series) safely, with ``torch.load(weights_only=True)``, maps
its key names strictly (a readable report lists missing, unexpected and mis-shaped keys)
and returns the model in eval mode. `taptr.save_checkpoint` writes it as ``{"format":
"taptr", "version": 1, "config", "model"}``, atomically, so the file carries its own
architecture. The script then reloads the written file and checks the weights match.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("src", nargs="?", help="official release or taptr checkpoint")
    parser.add_argument("dst", nargs="?", default="outputs/converted.pth", help="output file")
    parser.add_argument("--half", action="store_true", help="store float16 weights")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Converts, reloads, compares."""
    args = parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="taptr-example-") as scratch:
        return run(args, Path(scratch))


def run(args: argparse.Namespace, scratch: Path) -> int:
    """`main` with a scratch folder for the generated source checkpoint, removed afterwards."""
    import torch

    import taptr

    src = args.src
    if src is None:
        torch.manual_seed(0)
        src = str(scratch / "tiny.pth")
        taptr.save_checkpoint(taptr.build_model("tiny"), src)
        print(f"no source given: converting a freshly built tiny model ({src})")
    model = taptr.load_checkpoint(src)
    path = taptr.save_checkpoint(model, args.dst, half=args.half)

    reloaded = taptr.load_checkpoint(path)
    tolerance = 1e-3 if args.half else 0.0  # float16 rounds to ~3 significant digits
    worst = max(
        float((a.float() - b.float()).abs().max()) if a.numel() else 0.0
        for a, b in zip(model.state_dict().values(), reloaded.state_dict().values(), strict=True)
    )
    largest = max(float(p.detach().abs().max()) for p in model.parameters())
    if worst > tolerance * max(1.0, largest):
        raise SystemExit(f"reloaded weights differ by {worst:g}")
    params = sum(p.numel() for p in model.parameters())
    config = model.config
    size = config.input_size if config is not None else "?"
    print(f"wrote {path}: {params:,} parameters, input size {size}, max difference {worst:g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
