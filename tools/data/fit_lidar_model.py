"""Fit a sequence's LiDAR model (beams, laser offsets, azimuth bins), print it as a LIDAR section.

    python tools/data/fit_lidar_model.py --data_path data/waymo --sequence segment-..._with_camera_labels

Options: ``--origin X Y Z`` (where the sensor sits in the vehicle frame; default Waymo's TOP
mount), ``--num_beams N``, ``--azimuth_bins M`` or ``--estimate_azimuth_bins``, ``--offsets
auto|on|off`` (per-laser vertical offsets), ``--frames``. The fit report (share of points on a
beam, per-beam residuals, warnings when the origin looks wrong) is printed as comments above the
``LIDAR:`` block; paste the block into an attack YAML (docs/attacks.md, "Fitting the sensor model").
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import yaml

from pcdet_atlas.attacks.lidar_fit import fit_lidar_from_sequence
from pcdet_atlas.ops.lidar_model import WAYMO_AZIMUTH_BINS, WAYMO_TOP_ORIGIN
from pcdet_atlas.utils.cli import add_debug_flag, run_tool


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_debug_flag(parser)
    parser.add_argument("--data_path", required=True, help="dataset root (holds ImageSets/)")
    parser.add_argument("--sequence", required=True, help="sequence folder name")
    parser.add_argument(
        "--frames", type=int, nargs="*", default=None,
        help="sample indices (default: 10 spread over the sequence)",
    )  # fmt: skip
    parser.add_argument(
        "--origin", type=float, nargs=3, default=list(WAYMO_TOP_ORIGIN), metavar=("X", "Y", "Z"),
        help="sensor position in the vehicle frame, m (default: Waymo's TOP mount)",
    )  # fmt: skip
    parser.add_argument("--num_beams", type=int, default=64, help="number of lasers")
    az = parser.add_mutually_exclusive_group()
    az.add_argument(
        "--azimuth_bins", type=int, default=None,
        help=f"firings per turn (default {WAYMO_AZIMUTH_BINS}, the paper's)",
    )  # fmt: skip
    az.add_argument(
        "--estimate_azimuth_bins", action="store_true",
        help="estimate the firings per turn from the azimuth gaps between returns of one beam",
    )  # fmt: skip
    parser.add_argument(
        "--offsets", choices=("auto", "on", "off"), default="auto",
        help="per-laser vertical offsets: fitted and kept when the data shows parallax (auto)",
    )  # fmt: skip
    args = parser.parse_args()
    fit = fit_lidar_from_sequence(
        args.data_path, args.sequence, frames=args.frames, origin=args.origin,
        num_beams=args.num_beams, offsets=args.offsets,
        azimuth_bins="estimate" if args.estimate_azimuth_bins else args.azimuth_bins,
    )  # fmt: skip
    lidar = fit.lidar
    incl_deg = np.degrees(lidar.inclinations.numpy())
    offsets = None if lidar.offsets is None else lidar.offsets.numpy()
    print(f"# fitted {lidar}")
    if fit.azimuth_share is not None:
        print(
            f"# azimuth bins estimated: {lidar.azimuth_bins} "
            f"({100 * fit.azimuth_share:.1f}% of the gaps are whole firing steps)"
        )
    print(fit.report.format(incl_deg, offsets))
    cfg = lidar.to_config()
    cfg["INCLINATIONS_DEG"] = [round(math.degrees(v), 5) for v in cfg.pop("INCLINATIONS")]
    if "OFFSETS" in cfg:
        cfg["OFFSETS"] = [round(v, 4) for v in cfg.pop("OFFSETS")]
    print(yaml.safe_dump({"LIDAR": cfg}, sort_keys=False, default_flow_style=None))


if __name__ == "__main__":
    run_tool(main)
