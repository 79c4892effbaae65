"""Benchmark of the synthetic generator's ray caster: windowed (culled) vs brute force.

Side by side on the same frames of one synthetic scene: ``raycast_scan`` (each primitive tested
only against the rays of its beam x azimuth window) and a brute-force cast of every ray against
every primitive (chunked per primitive, same kernels). Checks that both give the same first
hits, then prints median times, the speed-up, pairs tested, and the full ``generate_frame`` time
(ray casting + return model + labels).

    python tools/bench/bench_synthetic.py --frames 5 --threads 1
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import torch

from pcdet_atlas.datasets.synthetic.generator import generate_frame, lidar_directions
from pcdet_atlas.datasets.synthetic.raycast import (
    _box_windows,
    _cylinder_windows,
    ray_box_distance,
    ray_cylinder_distance,
    raycast_scan,
)
from pcdet_atlas.datasets.synthetic.scene import SyntheticScene
from pcdet_atlas.datasets.synthetic.sensor import SensorModel
from pcdet_atlas.ops.lidar_model import LidarModel
from pcdet_atlas.utils.cli import add_debug_flag, run_tool


def brute_force(origin, dirs, prims, max_range):
    """``(R,)`` nearest hit range over ground and all primitives, no culling."""
    best = torch.full((dirs.shape[0],), math.inf, dtype=dirs.dtype)
    for k in range(prims.num_boxes):
        best = torch.minimum(
            best, ray_box_distance(origin, dirs, prims.boxes[k].expand(dirs.shape[0], 7))
        )
    for k in range(prims.num_cylinders):
        best = torch.minimum(
            best, ray_cylinder_distance(origin, dirs, prims.cylinders[k].expand(dirs.shape[0], 5))
        )
    down = dirs[:, 2] < -1e-9
    ground = torch.where(down, -origin[2] / torch.where(down, dirs[:, 2], -1.0), math.inf)
    best = torch.minimum(best, ground)
    return torch.where(best > max_range, torch.full_like(best, math.inf), best)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_debug_flag(parser)
    parser.add_argument("--frames", type=int, default=5, help="frames cast (default: 5)")
    parser.add_argument(
        "--threads", type=int, default=1, help="torch intra-op threads (default: 1)"
    )
    parser.add_argument("--seed", type=int, default=0, help="scene seed")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    lidar, sensor = LidarModel.waymo_top(), SensorModel()
    scene = SyntheticScene(args.seed, "val", 0, 198)
    origin = lidar.origin.to(torch.float32)
    dirs = lidar_directions(lidar, "cpu")
    t_win, t_brute, t_frame, pairs_win, pairs_all = [], [], [], [], []
    for f in torch.linspace(0, 197, args.frames).round().long().tolist():
        prims = scene.primitives(f)
        tic = time.perf_counter()
        hits = raycast_scan(origin, lidar.inclinations, lidar.azimuth_bins, prims, dirs=dirs)
        t_win.append(time.perf_counter() - tic)
        tic = time.perf_counter()
        ref = brute_force(origin, dirs, prims, lidar.max_range)
        t_brute.append(time.perf_counter() - tic)
        same = torch.equal(torch.isfinite(ref), torch.isfinite(hits.range_m))
        fin = torch.isfinite(ref)
        err = float((ref[fin] - hits.range_m[fin]).abs().max()) if fin.any() else 0.0
        if not same or err > 1e-4:
            raise SystemExit(f"frame {f}: windowed and brute-force casts differ (max {err} m)")
        incl = lidar.inclinations.to(torch.float32)
        _, nb, _, nc = _box_windows(origin, prims.boxes, incl, lidar.azimuth_bins)
        _, nb2, _, nc2 = _cylinder_windows(origin, prims.cylinders, incl, lidar.azimuth_bins)
        pairs_win.append(int((nb * nc).sum() + (nb2 * nc2).sum()))
        pairs_all.append(dirs.shape[0] * (prims.num_boxes + prims.num_cylinders))
        tic = time.perf_counter()
        generate_frame(scene, f, lidar, sensor, dirs=dirs)
        t_frame.append(time.perf_counter() - tic)
        print(
            f"frame {f:3d}: {prims.num_boxes} boxes + {prims.num_cylinders} cylinders, "
            f"windowed {t_win[-1] * 1e3:.0f} ms, brute force {t_brute[-1] * 1e3:.0f} ms, "
            f"identical first hits (max diff {err:.1e} m)"
        )
    med = statistics.median
    print(f"threads {args.threads}, {args.frames} frames, rays/frame {dirs.shape[0]}")
    print(f"pairs tested: windowed {med(pairs_win):,.0f}, brute force {med(pairs_all):,.0f}")
    print(
        f"median raycast: windowed {med(t_win) * 1e3:.0f} ms, brute force "
        f"{med(t_brute) * 1e3:.0f} ms, speed-up {med(t_brute) / med(t_win):.1f}x"
    )
    print(f"median generate_frame (cast + returns + labels): {med(t_frame) * 1e3:.0f} ms")


if __name__ == "__main__":
    run_tool(main)
