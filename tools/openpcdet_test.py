"""Evaluate an OpenPCDet checkpoint, any architecture, on the ATLAS variants: results.json.

    python tools/openpcdet_test.py --cfg_file <OpenPCDet model config> --ckpt <checkpoint.pth> \\
        --attacks all --out_dir output/openpcdet/pv_rcnn

Needs OpenPCDet 0.6.0 installed (``pcdet``, with its CUDA ops). The config is read by
OpenPCDet's own ``cfg_from_yaml_file`` (run from OpenPCDet's ``tools/`` folder when its
``_BASE_CONFIG_`` paths are relative, as OpenPCDet's own ``test.py`` is), the model built by its
``build_network`` and loaded by ``load_params_from_file``; the frames come from OpenPCDet's
Waymo infos through ``pcdet_atlas.integrations.openpcdet.AtlasWaymoDataset``, attacked on the fly
(every history frame of a sequence input too). ``--attacks`` is ``all`` (every
``cfgs/attacks/*.yaml``: clean and the 12 attacks) or a comma list of variant names or attack
YAMLs. Writes ``--out_dir/results.json`` (scored as ``tools/evaluate_predictions.py`` scores
predictions; ``tools/report.py`` reads it) and ``--out_dir/<variant>/result.pkl``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from pcdet_atlas.config import resolve_cli_path
from pcdet_atlas.integrations import openpcdet
from pcdet_atlas.train_utils.setup import count_arg
from pcdet_atlas.utils.cli import (
    add_debug_flag,
    add_plugin_flag,
    add_set_flag,
    import_plugins,
    run_tool,
)
from pcdet_atlas.utils.common import create_logger


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_debug_flag(parser)
    add_plugin_flag(parser)
    model = parser.add_argument_group("model and data")
    model.add_argument(
        "--cfg_file", "--cfg", dest="cfg_file", required=True, help="OpenPCDet model config"
    )
    model.add_argument("--ckpt", required=True, help="OpenPCDet checkpoint")
    model.add_argument(
        "--data_path", default=None, help="the Waymo data root (default: DATA_CONFIG.DATA_PATH)"
    )
    add_set_flag(
        model, help="KEY VALUE ... overrides of the config, by OpenPCDet's cfg_from_list (last)"
    )
    evaluation = parser.add_argument_group("evaluation")
    evaluation.add_argument("--attacks", default="all", help="'all' or a comma list of variants")
    evaluation.add_argument(
        "--temporal_window", type=count_arg(1), default=None,
        help="lifecycle window (default: the input frames of DATA_CONFIG.SEQUENCE_CONFIG, or 1)",
    )  # fmt: skip
    evaluation.add_argument(
        "--model_name", default=None, help="results.json 'model' field (default: config name)"
    )
    evaluation.add_argument("--out_dir", required=True, help="where results.json is written")
    runtime = parser.add_argument_group("runtime")
    runtime.add_argument(
        "--batch_size", type=count_arg(1), default=1, help="frames per batch (default: 1)"
    )
    runtime.add_argument("--workers", type=count_arg(0), default=4, help="loader workers")
    runtime.add_argument("--device", default="cuda", help="torch device of the model")
    return parser.parse_args(argv)


def main(argv=None) -> dict:
    args = parse_args(argv)
    import_plugins(args.plugin)
    openpcdet.require_openpcdet()
    from pcdet.config import cfg, cfg_from_list, cfg_from_yaml_file  # OpenPCDet's own

    cfg_from_yaml_file(args.cfg_file, cfg)
    if args.set_cfgs:
        cfg_from_list(args.set_cfgs, cfg)
    data_path = None if args.data_path is None else resolve_cli_path(args.data_path)
    return openpcdet.evaluate_openpcdet(
        cfg, resolve_cli_path(args.ckpt), args.attacks, resolve_cli_path(args.out_dir),
        config=str(args.cfg_file), model_name=args.model_name or Path(args.cfg_file).stem,
        batch_size=args.batch_size, workers=args.workers, root_path=data_path,
        device=args.device, temporal_window=args.temporal_window, logger=create_logger(),
    )  # fmt: skip


if __name__ == "__main__":
    run_tool(main)
