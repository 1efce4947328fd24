"""``taptr train``: train or fine-tune a model from a config file and ``KEY=VALUE`` overrides.

Run it alone, or under ``torchrun --nproc-per-node G -m taptr.cli.main train ...`` for data
parallelism (NCCL on GPUs, gloo on CPU).
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from taptr.cli.common.options import check_output_folder

if TYPE_CHECKING:
    from taptr.train.config import TrainConfig


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    parser = subparsers.add_parser(
        "train",
        help="train a model (presets: taptrv2, small)",
        description="Trains TAPTRv2 on Kubric-layout data. Settings come from the taptrv2 "
        "preset, then --config, then KEY=VALUE overrides (e.g. preset=small steps=100 "
        "data.root=DIR model.d_model=64). The resolved config is saved as "
        "OUT_DIR/config.json; checkpoints go to OUT_DIR/checkpoint.pt and the final EMA "
        "weights to OUT_DIR/model.pt.",
    )
    parser.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="config overrides")
    parser.add_argument("--config", help="TOML or JSON config file (see configs/)")
    parser.add_argument("--out", help="run folder (overrides out_dir)")
    parser.add_argument(
        "--init-from",
        metavar="CHECKPOINT",
        help="start from these weights: a taptr checkpoint or the authors' release",
    )
    parser.add_argument(
        "--resume",
        nargs="?",
        const="",
        metavar="CHECKPOINT",
        help="continue a run (default: OUT_DIR/checkpoint.pt; without --config, the "
        "checkpoint's own config is used)",
    )
    parser.set_defaults(func=run)


def _config(args: argparse.Namespace) -> TrainConfig:
    """The preset, then the file (or the resumed checkpoint's config), then the overrides."""
    from taptr.train.config import from_dict, merge, parse_overrides, read_config_file

    overrides = list(args.overrides)
    if args.out:
        overrides.append(f"out_dir={args.out}")
    if args.init_from:
        overrides.append(f"init_from={args.init_from}")
    if args.config:
        base = read_config_file(args.config)
    elif args.resume:
        from taptr.weights.checkpoint import (
            read_file,  # torch: only to read the checkpoint's config
        )

        data = read_file(args.resume)
        base = data.get("train_config") if isinstance(data, dict) else None
        if not isinstance(base, dict):
            raise ValueError(f"--resume {args.resume} is not a taptr training checkpoint")
    else:
        base = {}
    return from_dict(merge(base, parse_overrides(overrides)))


def run(args: argparse.Namespace) -> int:
    """Trains; prints the path of the final weights."""
    if args.out:
        check_output_folder(args.out)
    config = _config(args)
    check_output_folder(config.out_dir, "out_dir")
    resume = None
    if args.resume is not None:
        from taptr.train.run_state import CHECKPOINT_NAME

        resume = Path(args.resume or Path(config.out_dir) / CHECKPOINT_NAME)
        if not resume.is_file():
            raise FileNotFoundError(f"--resume: no checkpoint to resume from: {resume}")
    check_input_paths(config)
    from taptr.train.loop import NonFiniteLossError, train  # torch: after every cheap check

    logging.getLogger("taptr.train").setLevel(logging.INFO)  # progress without -v
    run_dir = Path(config.out_dir)
    existing = set(run_dir.iterdir()) if run_dir.is_dir() else None
    try:
        final = train(config, resume=resume)
    except NonFiniteLossError as error:
        print(f"taptr train: {error}")
        _after_failure(run_dir, existing)
        return 1
    except BaseException:
        _after_failure(run_dir, existing)
        raise
    print(f"wrote {final}")
    return 0


def check_input_paths(config: TrainConfig) -> None:
    """Raises FileNotFoundError for a missing ``init_from`` file or dataset folder (by key).

    Checked before torch loads and before the run folder is written, so a missing folder
    costs a second and leaves nothing behind.
    """
    if config.init_from and not Path(config.init_from).is_file():
        raise FileNotFoundError(f"checkpoint not found: {config.init_from}")
    folders = [("data.root", config.data.root)]
    folders += [("data.extra_roots", root) for root in config.data.extra_roots]
    if config.data.val_root and config.eval_every:
        folders.append(("data.val_root", config.data.val_root))
    for key, folder in folders:
        if Path(folder).is_dir():
            continue
        hint = (
            f"'taptr make-synthetic --out {folder}' writes synthetic videos there "
            "(docs/TRAINING.md: the data layout)"
        )
        if key == "data.val_root":
            hint += f", or train without held-out evaluation: {key}= (or eval_every=0)"
        raise FileNotFoundError(f"{key} {folder}: dataset folder not found; {hint}")


def _after_failure(run_dir: Path, existing: set[Path] | None) -> None:
    """Keeps a run folder that can be resumed; otherwise removes what this run created.

    Only the first process cleans up under torchrun; the others leave it to it.
    """
    from taptr.train.run_state import CHECKPOINT_NAME

    if os.environ.get("RANK", "0") != "0" or not run_dir.is_dir():
        return
    if (run_dir / CHECKPOINT_NAME).is_file():
        print(
            f"taptr train: kept {run_dir}: 'taptr train --resume --out {run_dir}' continues "
            f"from its {CHECKPOINT_NAME}",
            file=sys.stderr,
        )
        return
    if existing is None:
        shutil.rmtree(run_dir, ignore_errors=True)
    else:
        for entry in set(run_dir.iterdir()) - existing:
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
