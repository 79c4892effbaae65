"""Build the GT-sampling database(s) of a processed-Waymo dataset (OpenPCDet's
``create_waymo_gt_database``): single-frame or multi-frame according to each config's
``SEQUENCE_CONFIG``.

    python tools/data/create_gt_database.py \
        --cfg_file cfgs/dataset_configs/synthetic_waymo.yaml \
                   cfgs/dataset_configs/synthetic_waymo_multiframe.yaml
"""

from __future__ import annotations

import argparse

from pcdet_atlas.config import cfg_from_list, cfg_from_yaml_file, resolve_cli_path
from pcdet_atlas.datasets import WaymoDataset
from pcdet_atlas.datasets.gt_database import create_groundtruth_database, write_split_infos
from pcdet_atlas.utils.cli import add_debug_flag, add_set_flag, run_tool
from pcdet_atlas.utils.common import create_logger


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_debug_flag(parser)
    parser.add_argument("--cfg_file", "--cfg", nargs="+", required=True, help="dataset configs")
    parser.add_argument("--data_path", default=None, help="data root (default: DATA_PATH)")
    parser.add_argument("--split", default="train", help='split whose objects are cut out (default: train)')
    parser.add_argument("--sampled_interval", type=int, default=1, help='every n-th frame (default: 1)')
    parser.add_argument("--class_names", nargs="+", default=["Vehicle", "Pedestrian", "Cyclist"], help='classes kept (default: Vehicle Pedestrian Cyclist)')
    parser.add_argument(
        "--workers", type=int, default=0,
        help="processes cutting out the frames' objects (0: this one); the output does not "
        "depend on it",
    )  # fmt: skip
    add_set_flag(parser, help="KEY VALUE pairs overriding config keys (last on the command line)")
    args = parser.parse_args(argv)
    logger = create_logger()
    for cfg_file in args.cfg_file:
        dataset_cfg = cfg_from_yaml_file(cfg_file)
        if args.set_cfgs:
            cfg_from_list(args.set_cfgs, dataset_cfg)
        root = None if args.data_path is None else resolve_cli_path(args.data_path)
        dataset = WaymoDataset(
            dataset_cfg, args.class_names, training=False, root_path=root, logger=logger
        )
        dataset.set_split(args.split)
        infos_path = write_split_infos(dataset)
        logger.info(f"split infos: {infos_path}")
        paths = create_groundtruth_database(
            dataset,
            sampled_interval=args.sampled_interval,
            used_classes=args.class_names,
            logger=logger,
            workers=args.workers,
        )
        logger.info(f"{cfg_file}: wrote {paths['info']}, {paths['global']}, {paths['dir']}/")


if __name__ == "__main__":
    run_tool(main)
