"""Estimate the TOP LiDAR beam table from a sequence and print it as an attack-YAML LIDAR section.

    python tools/fit_lidar_model.py --data_path data/waymo --sequence segment-..._with_camera_labels

Paste the printed ``LIDAR:`` block into ``cfgs/attacks/_base_/common.yaml`` (or a variant) to run
the attacks with the fitted table instead of the documented default (docs/attacks.md).
"""

from __future__ import annotations

import argparse
import math

import yaml

from pcdet_atlas.attacks.lidar_fit import fit_lidar_from_sequence
from pcdet_atlas.ops.lidar_model import LidarModel


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data_path", required=True, help="dataset root (holds ImageSets/)")
    parser.add_argument("--sequence", required=True, help="sequence folder name")
    parser.add_argument("--frames", type=int, nargs="*", default=None, help="sample indices")
    args = parser.parse_args()
    lidar = fit_lidar_from_sequence(args.data_path, args.sequence, frames=args.frames)
    default = LidarModel.waymo_top()
    diff = (lidar.inclinations - default.inclinations).abs()
    print(f"# fitted {lidar}")
    print(
        f"# vs the default table: max |diff| {math.degrees(float(diff.max())):.3f} deg, "
        f"mean {math.degrees(float(diff.mean())):.3f} deg"
    )
    cfg = lidar.to_config()
    cfg["INCLINATIONS_DEG"] = [round(math.degrees(v), 4) for v in cfg.pop("INCLINATIONS")]
    print(yaml.safe_dump({"LIDAR": cfg}, sort_keys=False, default_flow_style=None))


if __name__ == "__main__":
    main()
