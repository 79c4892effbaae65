"""Score a detector's predictions on ATLAS variants: results.json as tools/test.py writes it.

    python tools/evaluate_predictions.py --data_cfg cfgs/atlas/synthetic/cp4f.yaml \\
        --predictions clean=clean/result.pkl rem_40=rem_40/result.pkl --out_dir scored/

``--data_cfg`` is a DATA_CONFIG YAML or a model config holding one (its ``CLASS_NAMES``,
``ATLAS.MODEL_NAME`` and ``ATLAS.TEMPORAL_WINDOW`` are then used); ``--set KEY VALUE ...``
overrides its keys, ``--data_path`` its ``DATA_PATH``. Each ``--predictions VARIANT=FILE``
names a variant and the file of its per-frame predictions. The variant is an attack name
(``cfgs/attacks/<VARIANT>.yaml``) or an attack YAML's path, whose targets, runs and lifecycle
are drawn on the source data exactly as the evaluation of the project's own models draws them,
or the output folder of ``tools/data/generate_atlas.py``, whose recorded ones are read. The file is
OpenPCDet's ``result.pkl``, a JSON list of frames, a folder of one ``.npz`` per frame or
Waymo's submission ``.bin`` (``--format``, else a folder is npz, a file by extension or
content). A variant whose confidence is scored against the clean run (removal) needs
``clean=FILE``. Writes ``--out_dir/results.json``.

The work is the library's (:mod:`pcdet_atlas.train_utils.score_predictions`, whose docstring
states the per-frame fields and their checks).
"""

from __future__ import annotations

import argparse

from pcdet_atlas.config import cfg_from_list, cfg_from_yaml_file, resolve_cli_path
from pcdet_atlas.train_utils.atlas_eval import atlas_section
from pcdet_atlas.train_utils.score_predictions import FORMATS, score_predictions
from pcdet_atlas.utils.cli import (
    add_debug_flag,
    add_plugin_flag,
    add_set_flag,
    import_plugins,
    run_tool,
)
from pcdet_atlas.utils.common import create_logger

DEFAULT_CLASSES = "Vehicle,Pedestrian,Cyclist"


def prediction_arg(text: str) -> tuple[str, str]:
    variant, sep, path = text.partition("=")
    if not sep or not variant or not path:
        raise argparse.ArgumentTypeError(f"{text!r}: expected VARIANT=FILE")
    return variant, path


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_debug_flag(parser)
    add_plugin_flag(parser)
    parser.add_argument(
        "--data_cfg", required=True, help="DATA_CONFIG YAML, or a model config holding one"
    )
    parser.add_argument("--data_path", default=None, help="the dataset root (its DATA_PATH)")
    add_set_flag(parser, help="KEY VALUE ... overrides of --data_cfg (last on the line)")
    parser.add_argument(
        "--predictions", type=prediction_arg, nargs="+", required=True, metavar="VARIANT=FILE",
        help="per variant, the file of its per-frame predictions",
    )  # fmt: skip
    parser.add_argument("--out_dir", required=True, help="where results.json is written")
    parser.add_argument("--format", choices=FORMATS, default=None, help="the files' format")
    parser.add_argument(
        "--class_names", default=None,
        help=f"comma list (a DATA_CONFIG file only; default {DEFAULT_CLASSES})",
    )  # fmt: skip
    parser.add_argument(
        "--temporal_window", type=int, default=None,
        help="lifecycle window (a DATA_CONFIG file only; a model config's ATLAS.TEMPORAL_WINDOW)",
    )  # fmt: skip
    parser.add_argument("--model_name", default=None, help="results.json 'model' field")
    return parser.parse_args(argv)


def main(argv=None) -> dict:
    args = parse_args(argv)
    import_plugins(args.plugin)
    cfg = cfg_from_yaml_file(args.data_cfg)
    if args.set_cfgs:
        cfg_from_list(args.set_cfgs, cfg)
    model_cfg = "DATA_CONFIG" in cfg
    if model_cfg and (args.class_names is not None or args.temporal_window is not None):
        raise SystemExit(
            f"{args.data_cfg} is a model config: its CLASS_NAMES and ATLAS.TEMPORAL_WINDOW apply; "
            "drop --class_names / --temporal_window"
        )
    data_cfg = cfg.DATA_CONFIG if model_cfg else cfg
    atlas_cfg = cfg.get("ATLAS", {}) if model_cfg else {}
    if args.data_path is not None:
        data_cfg.DATA_PATH = str(resolve_cli_path(args.data_path))
    if model_cfg:
        class_names = list(cfg.CLASS_NAMES)
    else:
        class_names = [c.strip() for c in (args.class_names or DEFAULT_CLASSES).split(",")]
    atlas = atlas_section(atlas_cfg)
    window = atlas.temporal_window if model_cfg else args.temporal_window
    model = args.model_name or atlas.model_name or "predictions"
    predictions = {}
    for variant, path in args.predictions:
        if variant in predictions:
            raise SystemExit(f"--predictions names variant {variant!r} twice")
        predictions[variant] = path
    results = score_predictions(
        data_cfg, class_names, predictions, args.out_dir, model=model,
        config=str(args.data_cfg), atlas_cfg=atlas_cfg, temporal_window=window, fmt=args.format,
        logger=create_logger(),
    )  # fmt: skip
    return results


if __name__ == "__main__":
    run_tool(main)
