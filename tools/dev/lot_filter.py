"""What a PHiM+LOT checkpoint's filter keeps, and how its forecast compares with a range prior.

    python tools/dev/lot_filter.py --cfg cfgs/atlas/synthetic/phim_lot/stage3_finetune.yaml \\
        --fit_frames 60 --frames 60 --attack inj_global_hard

Fits on every k-th frame of the train split (``--fit_frames`` of them; no augmentation): the
filter threshold of the rule "the highest that keeps at least ``--recall`` of the voxels inside
ground-truth boxes" and the range prior. Then prints, on every k-th frame of the test split
(``--frames``): the keep rates of in-box and background voxels at the config's
``MODEL.LOT.FILTER_THRESH`` and at the fitted threshold, and the forecast's focal loss beside the
range prior's (lower is better; :mod:`pcdet_atlas.train_utils.lot_analysis`). ``--attack``
adds the keep rate of phantom voxels on that injection variant's spoofed test frames.
"""

from __future__ import annotations

import argparse
import copy
import itertools

from torch.utils.data import DataLoader, Subset

from pcdet_atlas.config import resolve_cli_path, resolve_repo_path
from pcdet_atlas.datasets import build_dataloader
from pcdet_atlas.models import build_network_from_config
from pcdet_atlas.train_utils.atlas_eval import (
    atlas_section,
    build_attack_loader,
    resolve_variants,
)
from pcdet_atlas.train_utils.lot_analysis import (
    collect_confidences,
    forecast_quality,
    keep_rate,
    range_prior,
    threshold_for_recall,
)
from pcdet_atlas.train_utils.setup import count_arg, load_cfg, require_dataset
from pcdet_atlas.utils.cli import add_debug_flag, add_set_flag, run_tool


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_debug_flag(parser)
    parser.add_argument("--cfg", "--cfg_file", dest="cfg", required=True, help="PHiM+LOT config")
    parser.add_argument("--ckpt", default=None, help="checkpoint (default: ATLAS.CHECKPOINT)")
    parser.add_argument("--data_path", default=None, help="dataset root (default: DATA_PATH)")
    parser.add_argument("--fit_frames", type=count_arg(1), default=60, help="train frames")
    parser.add_argument("--frames", type=count_arg(1), default=60, help="test frames")
    parser.add_argument("--recall", type=float, default=0.95, help="in-box keep rate of the rule")
    parser.add_argument("--attack", default=None, help="an injection variant for phantom voxels")
    add_set_flag(parser, help="KEY VALUE pairs overriding config keys (last on the command line)")
    return parser.parse_args(argv)


def spread(dataset, count: int) -> DataLoader:
    """Batches of single frames, ``count`` of them spread evenly over ``dataset`` (only those
    frames are read)."""
    step = max(1, len(dataset) // count)
    frames = Subset(dataset, range(0, len(dataset), step)[:count])
    return DataLoader(frames, batch_size=1, collate_fn=dataset.collate_batch)


def main(argv=None) -> dict:
    args = parse_args(argv)
    cfg = load_cfg(args.cfg, args.set_cfgs)
    if args.data_path is not None:
        cfg.DATA_CONFIG.DATA_PATH = str(resolve_cli_path(args.data_path))
    require_dataset(cfg, args.cfg)
    if "LOT" not in cfg.MODEL:
        raise SystemExit(f"{args.cfg}: MODEL has no LOT section (a PHiM+LOT config is needed)")
    shipped = atlas_section(cfg.get("ATLAS")).checkpoint
    if args.ckpt is None and not shipped:
        raise SystemExit(f"{args.cfg}: no ATLAS.CHECKPOINT; pass --ckpt")
    ckpt = resolve_cli_path(args.ckpt) if args.ckpt else resolve_repo_path(shipped)
    model = build_network_from_config(cfg)
    model.load_params_from_file(ckpt)
    model.eval()
    batches = {}
    for split, count in (("train", args.fit_frames), ("test", args.frames)):
        data_cfg = copy.deepcopy(cfg.DATA_CONFIG)  # the split read without augmentation
        data_cfg.DATA_SPLIT["test"] = cfg.DATA_CONFIG.DATA_SPLIT[split]
        dataset, _, _ = build_dataloader(
            data_cfg, cfg.CLASS_NAMES, batch_size=1, dist=False, workers=0, training=False
        )
        batches[split] = spread(dataset, count)
    fit, fit_maps = collect_confidences(model, batches["train"])
    thresh = threshold_for_recall(fit.of("in_box"), args.recall)
    prior = range_prior(fit_maps)
    test, test_maps = collect_confidences(model, batches["test"])
    configured = float(model.lot.filter_thresh)
    out = {
        "fitted_thresh": thresh,
        "configured_thresh": configured,
        "forecast_focal_loss": forecast_quality(test_maps, prior),
        "keep": {
            name: {
                "configured": keep_rate(test.of(name), configured),
                "fitted": keep_rate(test.of(name), thresh),
                "voxels": int(test.of(name).size),
            }
            for name in ("in_box", "background")
        },
    }
    if args.attack:
        ((name, path),) = resolve_variants(args.attack, cfg.ATLAS)
        dataset, loader = build_attack_loader(
            cfg.DATA_CONFIG, cfg.CLASS_NAMES, path, batch_size=1, dist=False, workers=0, seed=0
        )
        spoofed = (b for b in loader if b["attack"][0].get("spoofed"))
        attacked, _ = collect_confidences(model, itertools.islice(spoofed, args.frames))
        out["keep"]["phantom"] = {
            "configured": keep_rate(attacked.of("phantom"), configured),
            "fitted": keep_rate(attacked.of("phantom"), thresh),
            "voxels": int(attacked.of("phantom").size),
            "variant": name,
        }
    print(f"rule: keep >= {args.recall:.2f} of in-box train voxels -> threshold {thresh:.4f} "
          f"(config: {configured:.4f}), from {args.fit_frames} train frames")  # fmt: skip
    print(f"{'voxels':<12}{'count':>10}{'kept @ config':>15}{'kept @ rule':>13}")
    for name, row in out["keep"].items():
        cells = [f"{row[k]:.3f}" if row[k] is not None else "-" for k in ("configured", "fitted")]
        print(f"{name:<12}{row['voxels']:>10}{cells[0]:>15}{cells[1]:>13}")
    q = out["forecast_focal_loss"]
    print(f"forecast focal loss on {args.frames} test frames: {q['forecast']:.4f} "
          f"(range prior {q['range_prior']:.4f}; lower is better)")  # fmt: skip
    return out


if __name__ == "__main__":
    run_tool(main)
