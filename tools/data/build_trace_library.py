"""Build the ATLAS trace library (docs/attacks.md) of a Waymo-format dataset from one split.

    python tools/data/build_trace_library.py --cfg cfgs/attacks/inj_rel_easy.yaml \
        --data_path data/synthetic_waymo [--out <file>] [--set TRACE_LIBRARY.MIN_POINTS 100]

Filters and split (``SPLIT``, train by default) come from the ``TRACE_LIBRARY`` section of the
injection YAML, the sensor origin from its ``LIDAR`` section; the file is written to
``TRACE_LIBRARY.PATH`` (relative, under ``--data_path``: an absolute PATH or one with ``..`` is
refused) unless ``--out`` is given, which may name any file. Every injection variant naming that
file shares it, so an existing library built with other filters (or another split, or another
``LIDAR.ORIGIN``) is not replaced unless ``--overwrite`` is given: write it to another file
instead.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tqdm import tqdm

from pcdet_atlas.attacks.trace_library import write_trace_library
from pcdet_atlas.config import REPO_ROOT, resolve_cli_path
from pcdet_atlas.utils.cli import add_debug_flag, add_set_flag, run_tool
from pcdet_atlas.utils.common import create_logger


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_debug_flag(parser)
    parser.add_argument("--cfg", "--cfg_file", dest="cfg", required=True, help="injection YAML")
    parser.add_argument(
        "--data_path", default=str(REPO_ROOT / "data" / "synthetic_waymo"), help="dataset root"
    )
    parser.add_argument("--out", default=None, help="output .npz (default TRACE_LIBRARY.PATH)")
    parser.add_argument(
        "--overwrite", action="store_true", help="replace a library built with other filters"
    )
    add_set_flag(parser, help="KEY VALUE pairs overriding config keys (last on the command line)")
    return parser.parse_args(argv)


def main(argv=None) -> Path:
    args = parse_args(argv)
    return write_trace_library(
        args.cfg, resolve_cli_path(args.data_path), set_cfgs=args.set_cfgs,
        # --out as typed (the working directory); TRACE_LIBRARY.PATH relative to the dataset root
        out=resolve_cli_path(args.out) if args.out else None, overwrite=args.overwrite,
        progress=lambda it: tqdm(list(it), desc="sequences", unit="seq"), logger=create_logger(),
    )  # fmt: skip


if __name__ == "__main__":
    run_tool(main)
