"""Evaluate a detector on ATLAS variants: Waymo L2 mAP/mAPH and attack success rate per variant.

    python tools/test.py --cfg cfgs/atlas/synthetic/cp4f.yaml --attacks clean,inj_global_hard,rem_40
    python tools/test.py --cfg cfgs/atlas/synthetic/cp4f.yaml --attacks all
    torchrun --nproc_per_node 2 tools/test.py --cfg ... --launcher pytorch

``--ckpt`` defaults to the config's ``ATLAS.CHECKPOINT``. Output:
``output/<group>/<tag>/<extra_tag>/eval/<ckpt stem>/<split>/<eval_tag>/`` with ``results.json``
(schema in ``pcdet_atlas.evaluation.results``), ``<variant>/result.pkl``, the merged config and a
log; the table is printed as the paper lays it out.
"""

from __future__ import annotations

import argparse
import datetime
from pathlib import Path

from pcdet_atlas.config import REPO_ROOT, ConfigError, save_config
from pcdet_atlas.evaluation import build_results, format_table, save_results
from pcdet_atlas.models import build_network_from_config
from pcdet_atlas.train_utils.atlas_eval import evaluate_variant, resolve_variants
from pcdet_atlas.train_utils.setup import add_common_args, load_cfg, output_dir_for, setup_runtime
from pcdet_atlas.utils.common import create_logger


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_common_args(parser)
    parser.add_argument("--attacks", default="clean", help="'all' or a comma list of variants")
    parser.add_argument("--eval_tag", default="default")
    parser.add_argument("--no_progress", action="store_true", default=False, help="no tqdm bars")
    return parser.parse_args(argv)


def resolve_checkpoint(arg: str | None, atlas_cfg) -> Path:
    ckpt = arg if arg is not None else atlas_cfg.get("CHECKPOINT")
    if ckpt is None:
        raise ConfigError("no checkpoint: pass --ckpt (the config's ATLAS.CHECKPOINT is null)")
    path = Path(ckpt)
    if not path.is_absolute() and not path.is_file():
        path = REPO_ROOT / path
    if not path.is_file():
        raise FileNotFoundError(
            f"checkpoint {ckpt} not found (train one with tools/train.py, or pass --ckpt)"
        )
    return path


def main(argv=None) -> dict:
    args = parse_args(argv)
    cfg = load_cfg(args.cfg_file, args.set_cfgs)
    atlas_cfg = cfg.get("ATLAS", {})
    variants = resolve_variants(args.attacks, atlas_cfg)
    ckpt = resolve_checkpoint(args.ckpt, atlas_cfg)
    dist, rank, world, device = setup_runtime(args)
    batch_size = args.batch_size or world
    if batch_size % world:
        raise ValueError(f"--batch_size {batch_size} is not divisible by {world} processes")

    split = cfg.DATA_CONFIG.DATA_SPLIT["test"]
    out_dir = output_dir_for(cfg, args.output_root, args.extra_tag) / "eval" / ckpt.stem
    out_dir = out_dir / str(split) / args.eval_tag
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    logger = create_logger(out_dir / f"log_eval_{stamp}.txt", rank=rank)
    logger.info(f"{args.cfg_file}  checkpoint {ckpt}  variants {[v for v, _ in variants]}")
    logger.info(f"processes: {world}  device: {device}  batch: {batch_size}  output: {out_dir}")
    if rank == 0:
        save_config(cfg, out_dir / f"{cfg.TAG}.yaml")

    model = build_network_from_config(cfg)
    model.load_params_from_file(ckpt)  # strict: CheckpointMismatchError names what differs
    model.to(device).eval()

    entries: dict = {}
    clean_annos = None
    for variant, yaml_path in variants:
        entry, det_annos = evaluate_variant(
            model, variant, yaml_path, data_cfg=cfg.DATA_CONFIG, class_names=cfg.CLASS_NAMES,
            device=device, batch_size=batch_size // world, dist=dist, workers=args.workers,
            seed=args.seed, temporal_window=atlas_cfg.get("TEMPORAL_WINDOW"),
            clean_det_annos=clean_annos, out_dir=out_dir / variant, logger=logger,
            show_progress=not args.no_progress,
        )  # fmt: skip
        if variant == "clean":
            clean_annos = det_annos
        if rank == 0:
            entries[variant] = entry

    if rank != 0:
        return {}
    results = build_results(
        model=atlas_cfg.get("MODEL_NAME", cfg.TAG), config=str(args.cfg_file),
        checkpoint=str(ckpt), class_names=cfg.CLASS_NAMES, variants=entries,
        extra={"processes": world, "device": str(device), "batch_size": batch_size},
    )  # fmt: skip
    path = save_results(results, out_dir / "results.json")
    print("\n" + format_table(results))
    logger.info(f"results: {path}")
    return {"results": results, "output_dir": out_dir}


if __name__ == "__main__":
    main()
