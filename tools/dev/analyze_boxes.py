"""Where a detector's AP is lost: L2 AP at several IoU thresholds and per-parameter box errors.

    python tools/dev/analyze_boxes.py --cfg cfgs/atlas/synthetic/cp4f.yaml \\
        --result output/.../eval/<ckpt>/val/default/clean/result.pkl

``--result`` is a ``result.pkl`` written by ``tools/test.py`` (one variant's predictions); the
ground truth comes from the config's dataset (the split of ``DATA_SPLIT.test``), matched by
``frame_id``. Prints the class's L2 AP / APH at each ``--iou`` threshold (the official Vehicle
threshold is 0.7) and, for predictions matched one to one to ground-truth boxes by 3D IoU, the
bias, median and 90th percentile of each box parameter's error in the ground-truth box frame
(:mod:`pcdet_atlas.evaluation.localization`). ``--project`` adds the AP at the official
threshold with the matched boxes' error halved, one parameter at a time, all together, and
removed (:func:`~pcdet_atlas.evaluation.localization.projected_ap`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from pcdet_atlas.config import cfg_from_list, cfg_from_yaml_file
from pcdet_atlas.datasets import WaymoDataset
from pcdet_atlas.evaluation.localization import (
    ERROR_COMPONENTS,
    ap_by_iou,
    localization_errors,
    projected_ap,
)
from pcdet_atlas.utils.cli import add_debug_flag, add_set_flag, run_tool
from pcdet_atlas.utils.safe_pickle import load_pickle

#: Components scaled by ``--project`` (the centre's along / across errors move together).
PROJECTED = ("center", "z", "length", "width", "height", "heading")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_debug_flag(parser)
    parser.add_argument("--cfg", "--cfg_file", dest="cfg", required=True, help="model config")
    parser.add_argument("--result", required=True, help="result.pkl of tools/test.py")
    parser.add_argument("--class_name", default="Vehicle", help="class analysed (default: Vehicle)")
    parser.add_argument("--iou", default="0.3,0.5,0.6,0.7,0.8", help="IoU thresholds for AP")
    parser.add_argument("--min_points", type=int, default=1, help="GT boxes with fewer: left out")
    parser.add_argument("--score", type=float, default=0.3, help="predictions below: left out")
    parser.add_argument(
        "--project", action="store_true", help="AP with the matched boxes' errors scaled"
    )
    add_set_flag(parser, help="KEY VALUE pairs overriding config keys (last on the command line)")
    return parser.parse_args(argv)


def load_pairs(cfg, result_path: Path) -> tuple[list[dict], list[dict]]:
    """Ground-truth annos aligned with the predictions of ``result_path`` by ``frame_id``."""
    det_annos = load_pickle(result_path)
    dataset = WaymoDataset(cfg.DATA_CONFIG, cfg.CLASS_NAMES, training=False)
    by_id = {info["frame_id"]: info["annos"] for info in dataset.infos}
    missing = [d["frame_id"] for d in det_annos if d["frame_id"] not in by_id]
    if missing:
        raise SystemExit(
            f"{result_path}: {len(missing)} frame(s) not in the config's "
            f"{dataset.split!r} split (first: {missing[0]}); pass the config the result came from"
        )
    return [by_id[d["frame_id"]] for d in det_annos], det_annos


def main(argv=None) -> dict:
    args = parse_args(argv)
    cfg = cfg_from_yaml_file(args.cfg)
    if args.set_cfgs:
        cfg_from_list(args.set_cfgs, cfg)
    gt_annos, det_annos = load_pairs(cfg, Path(args.result))
    thresholds = [float(v) for v in args.iou.split(",")]
    ap = ap_by_iou(gt_annos, det_annos, args.class_name, thresholds)
    print(f"{args.class_name}: {len(det_annos)} frames ({args.result})")
    print(f"{'IoU':>6}  {'L2 AP':>6}  {'L2 APH':>6}")
    for thr, (ap_v, aph_v) in ap.items():
        print(f"{thr:>6.2f}  {ap_v:>6.3f}  {aph_v:>6.3f}")
    report = localization_errors(gt_annos, det_annos, args.class_name, args.min_points, args.score)
    print(
        f"matched {report['num_matched']} of {report['num_gt']} GT boxes with >= "
        f"{args.min_points} points (predictions scoring >= {args.score}, 3D IoU >= 0.1); "
        f"median IoU {report['iou_median']:.3f}, heading flipped in "
        f"{report['flipped_fraction']:.1%}"
    )
    print(f"{'error':>8}  {'bias':>7}  {'median|e|':>9}  {'p90|e|':>7}")
    for name in ERROR_COMPONENTS:
        row = report[name]
        unit = "rad" if name == "heading" else "m"
        print(f"{name:>8}  {row['bias']:>+7.3f}  {row['median_abs']:>9.3f}  "
              f"{row['p90_abs']:>7.3f}  {unit}")  # fmt: skip
    out = {"ap_by_iou": ap, "localization": report}
    if args.project:
        cases = {f"{name} x0.5": {name: 0.5} for name in PROJECTED}
        cases["all x0.5"] = dict.fromkeys(PROJECTED, 0.5)
        cases["all x0"] = dict.fromkeys(PROJECTED, 0.0)
        out["projected"] = {
            label: projected_ap(gt_annos, det_annos, args.class_name, factors)
            for label, factors in cases.items()
        }
        print("L2 AP at the official threshold with the matched boxes' errors scaled "
              "(score-first matching at 3D IoU >= 0.3):")  # fmt: skip
        for label, value in out["projected"].items():
            print(f"{label:>14}  {value:.3f}")
    return out


if __name__ == "__main__":
    run_tool(main)
