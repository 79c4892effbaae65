"""Fit the sensor model to scans of known sensors and print how close each fit method gets.

    python tools/dev/check_lidar_fit.py --sensors hdl64e hdl32e waymo_top --seed 0

For each preset sensor (per-laser offsets jittered, one street scene, 2 cm range noise,
``--angle_noise_deg`` jitter) it prints, for the older fit (Lloyd from Waymo's table, single
origin), the data-initialised single-origin table and the full fit (with laser offsets where
the data shows parallax): beam error (median / max, deg), share of beams within half the
local spacing, share of points on a beam, and the share of a dense phantom's points at 10/20/40 m
that fall in one (beam, firing) of the true sensor with another (the true model: 0).
"""

from __future__ import annotations

import argparse

from pcdet_atlas.attacks.lidar_check import FIT_METHODS, PHANTOM_RANGES_M, check_known_sensor
from pcdet_atlas.ops.lidar_presets import LIDAR_PRESETS
from pcdet_atlas.utils.cli import add_debug_flag, run_tool


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_debug_flag(parser)
    parser.add_argument(
        "--sensors", nargs="+", choices=sorted(LIDAR_PRESETS), default=sorted(LIDAR_PRESETS),
        help="presets to scan and fit",
    )  # fmt: skip
    parser.add_argument("--seed", type=int, default=0, help="seed of the scene and the noise")
    parser.add_argument(
        "--angle_noise_deg", type=float, default=0.005, help="per-point angle jitter, deg"
    )
    args = parser.parse_args()
    ranges = "/".join(f"{r:g}" for r in PHANTOM_RANGES_M)
    print(
        f"sensor     fit    median_deg  max_deg  beams<=half  on_beam  offsets  "
        f"phantom shared true ray at {ranges} m"
    )
    for name in args.sensors:
        res = check_known_sensor(name, seed=args.seed, angle_noise_deg=args.angle_noise_deg)
        true_c = " ".join(f"{100 * v:5.1f}%" for v in res["true_collisions"].values())
        print(f"{name:10s} true   {'':48s} {true_c}")
        for method in FIT_METHODS:
            r = res[method]
            e = r["error"]
            shared = " ".join(f"{100 * v:5.1f}%" for v in r["collisions"].values())
            offsets = "yes" if r["model"].offsets is not None else "no"
            print(
                f"{name:10s} {method:6s} {e.median_deg:10.4f} {e.max_deg:8.4f} "
                f"{100 * e.within_half_spacing:10.1f}% {100 * r['on_beam']:7.1f}% {offsets:>7s}  "
                f"{shared}"
            )
        print(
            f"{name:10s} azimuth bins estimated {res['azimuth_bins']} "
            f"(true {res['true'].azimuth_bins})"
        )


if __name__ == "__main__":
    run_tool(main)
