"""Build the ATLAS trace library (docs/attacks.md) of a Waymo-format dataset from one split.

    python tools/build_trace_library.py --cfg cfgs/attacks/inj_rel_easy.yaml \
        --data_path data/synthetic_waymo [--out <file>] [--set TRACE_LIBRARY.MIN_POINTS 100]

Filters and split (``SPLIT``, train by default) come from the ``TRACE_LIBRARY`` section of the
injection YAML, the sensor origin from its ``LIDAR`` section; the file is written to
``TRACE_LIBRARY.PATH`` (relative: under ``--data_path``) unless ``--out`` is given. Every injection
variant naming that file shares it, so an existing library built with other filters (or another
split, or another ``LIDAR.ORIGIN``) is not replaced unless ``--overwrite`` is given: write it to
another file instead.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pcdet_atlas.attacks.trace_library import TraceFilter, TraceLibrary, build_trace_library
from pcdet_atlas.config import (
    REPO_ROOT,
    ConfigError,
    cfg_from_list,
    cfg_from_yaml_file,
    resolve_cli_path,
)
from pcdet_atlas.ops.lidar_model import LidarModel
from pcdet_atlas.utils.common import create_logger


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cfg", "--cfg_file", dest="cfg", required=True, help="injection YAML")
    parser.add_argument(
        "--data_path", default=str(REPO_ROOT / "data" / "synthetic_waymo"), help="dataset root"
    )
    parser.add_argument("--out", default=None, help="output .npz (default TRACE_LIBRARY.PATH)")
    parser.add_argument(
        "--overwrite", action="store_true", help="replace a library built with other filters"
    )
    parser.add_argument("--set", dest="set_cfgs", nargs=argparse.REMAINDER, default=None)
    return parser.parse_args(argv)


def main(argv=None) -> Path:
    args = parse_args(argv)
    logger = create_logger()
    cfg = cfg_from_yaml_file(args.cfg)
    if args.set_cfgs:
        cfg_from_list(args.set_cfgs, cfg)
    if "TRACE_LIBRARY" not in cfg:
        raise ConfigError(f"{args.cfg}: no TRACE_LIBRARY section (not an injection attack?)")
    filters = TraceFilter.from_config(cfg.TRACE_LIBRARY)
    root = resolve_cli_path(args.data_path)
    # --out as typed (the working directory); TRACE_LIBRARY.PATH relative to the dataset root
    out = resolve_cli_path(args.out) if args.out else Path(filters.path)
    if not out.is_absolute():
        out = root / out
    lidar = LidarModel.from_config(cfg.get("LIDAR"))
    if out.is_file() and not args.overwrite:
        check_same_build(out, filters, list(lidar.origin_xyz))
    library = build_trace_library(
        root,
        filters,
        split=filters.split,
        sensor_origin=lidar.origin.tolist(),
        progress=lambda it: tqdm(list(it), desc="sequences", unit="seq"),
        logger=logger,
    )
    library.save(out)
    sizes = library.trace_sizes()
    logger.info(
        f"wrote {out}: {len(library)} traces, points per trace min/median/max "
        f"{sizes.min()}/{int(np.median(sizes))}/{sizes.max()}"
    )
    return out


def check_same_build(path: Path, filters: TraceFilter, sensor_origin: list[float]) -> None:
    """Refuse to replace the library at ``path`` when it was built with other filters, split or
    sensor origin: the injection variants that share it would stop loading (or, read by an older
    copy of their YAML, run on other traces)."""
    differs = TraceLibrary.load(path).build_mismatch(filters, sensor_origin)
    if differs:
        have = {key: pair[0] for key, pair in differs.items()}
        want = {key: pair[1] for key, pair in differs.items()}
        raise FileExistsError(
            f"{path} holds a trace library built with {have}, not {want}; every injection variant "
            "whose TRACE_LIBRARY.PATH names this file shares it. Write this one elsewhere (--out, "
            "or another TRACE_LIBRARY.PATH in its YAML) or pass --overwrite to replace it"
        )


if __name__ == "__main__":
    main()
