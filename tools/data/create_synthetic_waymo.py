"""Generate the synthetic Waymo-format dataset (OpenPCDet's processed layout).

Example::

    python tools/data/create_synthetic_waymo.py --out_dir data/synthetic_waymo \
        --train_sequences 12 --train_frames 60 --val_sequences 1 --val_frames 198 --seed 0

Re-running with the same arguments completes an interrupted run and rewrites nothing finished;
other arguments into an existing root are an error (see docs/synthetic.md).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from pcdet_atlas.config import REPO_ROOT
from pcdet_atlas.datasets.synthetic import (
    DEFAULT_FRAMES_PER_SEQUENCE,
    DEFAULT_NUM_SEQUENCES,
    create_synthetic_waymo,
    format_summary,
)
from pcdet_atlas.train_utils.setup import device_arg
from pcdet_atlas.utils.cli import RenamedFlag, add_debug_flag, run_tool
from pcdet_atlas.utils.common import create_logger

DEFAULT_ROOT = REPO_ROOT / "data" / "synthetic_waymo"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_debug_flag(parser)
    parser.add_argument("--out_dir", "--root", action=RenamedFlag, old=("--root",), type=Path,
                        default=DEFAULT_ROOT, help="output dataset root (default: %(default)s)")
    for split in ("train", "val"):
        parser.add_argument(
            f"--{split}_sequences", f"--{split}-sequences", action=RenamedFlag,
            old=(f"--{split}-sequences",), type=int, default=DEFAULT_NUM_SEQUENCES[split],
            help=f"{split} sequences (default: %(default)s)",
        )
        parser.add_argument(
            f"--{split}_frames", f"--{split}-frames", action=RenamedFlag,
            old=(f"--{split}-frames",), type=int, default=DEFAULT_FRAMES_PER_SEQUENCE[split],
            help=f"frames per {split} sequence (default: %(default)s)",
        )
    parser.add_argument("--seed", type=int, default=0, help="the dataset's seed (default: 0)")
    parser.add_argument(
        "--device", type=device_arg, default="cpu", help="torch device for ray casting"
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=min(2, os.cpu_count() or 1),
        help="parallel processes (the output does not depend on it)",
    )
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    logger = create_logger()
    summary = create_synthetic_waymo(
        args.out_dir,
        num_sequences={"train": args.train_sequences, "val": args.val_sequences},
        frames_per_sequence={"train": args.train_frames, "val": args.val_frames},
        seed=args.seed,
        device=args.device,
        logger=logger,
        workers=args.workers,
    )
    print(format_summary(summary))
    return summary


if __name__ == "__main__":
    run_tool(main)
