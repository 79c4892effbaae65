"""Scans of a known sensor over a small street scene, for checking a fitted sensor model.

:func:`street_scene` lays a ground plane, parked cars, walls and poles at ranges from 3 m to
60 m around the sensor (so every beam, down to the lowest, sees surfaces at several ranges);
:func:`scan_known_sensor` ray-casts it with a :class:`LidarModel`, each laser from its own
height above the origin (``LidarModel.offsets``), one return per (beam, firing).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pcdet_atlas.datasets.synthetic.raycast import (
    GROUND_ID,
    NO_HIT_ID,
    Primitives,
    column_azimuths,
    ray_directions,
    raycast_scan,
)
from pcdet_atlas.ops.lidar_model import LidarModel

__all__ = ["known_sensor", "street_scene", "scan_known_sensor"]

#: Per-laser spread of the vertical offsets of a generated two-block sensor around its block's
#: value (m): unit calibrations differ laser by laser. Drawn in steps of LASER_OFFSET_STEP_M
#: (lasers of one height are cast together).
LASER_OFFSET_SPREAD_M, LASER_OFFSET_STEP_M = 0.01, 0.005


def known_sensor(
    preset: str, generator: torch.Generator, origin=(0.0, 0.0, 1.9), max_range: float = 75.0
) -> LidarModel:
    """A sensor of the named preset (:mod:`pcdet_atlas.ops.lidar_presets`) at ``origin``, each
    laser's offset moved by up to ``LASER_OFFSET_SPREAD_M`` (uniform steps, from ``generator``)."""
    base = LidarModel.preset(preset, origin=origin, max_range=max_range)
    offsets = None
    if base.offsets is not None:
        steps = round(LASER_OFFSET_SPREAD_M / LASER_OFFSET_STEP_M)
        spread = torch.randint(-steps, steps + 1, (base.num_beams,), generator=generator)
        offsets = base.offsets + LASER_OFFSET_STEP_M * spread.to(torch.float64)
    return LidarModel(
        base.inclinations, base.azimuth_bins, origin, max_range=max_range, offsets=offsets
    )


def street_scene(generator: torch.Generator, center_xy=(0.0, 0.0)) -> Primitives:
    """Cars (3-50 m), buildings (12-60 m, 14 m tall) and poles around ``center_xy``, with
    positions jittered by ``generator``."""

    def u(lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(torch.rand((), generator=generator, dtype=torch.float64))

    cx, cy = center_xy
    boxes = []
    car_ranges = [3.0, 4.5, 6.0, 8.0, 11.0, 15.0, 20.0, 27.0, 35.0, 50.0]
    for i, r in enumerate(car_ranges):
        a = 2 * math.pi * i / len(car_ranges) + u(-0.2, 0.2)
        boxes.append([cx + r * math.cos(a), cy + r * math.sin(a), 0.8, 4.5, 1.9, 1.6, u(-3, 3)])
    for i, r in enumerate([12.0, 18.0, 25.0, 33.0, 42.0, 60.0]):
        a = 2 * math.pi * (i + 0.5) / 6 + u(-0.15, 0.15)
        boxes.append([cx + r * math.cos(a), cy + r * math.sin(a), 7.0, 3.0, 24.0, 14.0, a])
    cyl = []
    for i, r in enumerate([5.0, 7.5, 10.0, 14.0, 22.0, 30.0]):
        a = 2 * math.pi * (i + 0.25) / 6 + u(-0.2, 0.2)
        cyl.append([cx + r * math.cos(a), cy + r * math.sin(a), 0.0, 8.0, 0.25])
    boxes_t = torch.tensor(boxes, dtype=torch.float64)
    cyl_t = torch.tensor(cyl, dtype=torch.float64)
    return Primitives(
        boxes=boxes_t,
        box_albedo=torch.full((len(boxes),), 0.3, dtype=torch.float64),
        box_surface=torch.zeros(len(boxes), dtype=torch.long),
        cylinders=cyl_t,
        cyl_albedo=torch.full((len(cyl),), 0.3, dtype=torch.float64),
        cyl_surface=torch.zeros(len(cyl), dtype=torch.long),
    )


def scan_known_sensor(
    lidar: LidarModel,
    prims: Primitives,
    generator: torch.Generator,
    range_noise_m: float = 0.02,
    angle_noise_deg: float = 0.0,
    ground_z: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """One turn of ``lidar`` over the scene: ``(N, 3)`` float64 points (vehicle frame) and their
    ``(N,)`` true ray ids ``beam * M + firing``.

    Laser ``k`` fires from ``origin + (0, 0, offsets[k])`` at elevation ``inclinations[k]`` and
    the centre azimuth of each of the ``M = azimuth_bins`` firings; the range gets Gaussian
    noise of ``range_noise_m`` and each point's direction, about its laser, Gaussian jitter of
    ``angle_noise_deg`` in elevation and azimuth (both drawn from ``generator``). Returns beyond
    ``max_range`` are lost.
    """
    incl = lidar.inclinations
    offsets = torch.zeros_like(incl) if lidar.offsets is None else lidar.offsets
    m = lidar.azimuth_bins
    az = column_azimuths(m, dtype=torch.float64)
    pts, ids = [], []
    for c in torch.unique(offsets).tolist():
        beams = torch.nonzero(offsets == c).flatten()
        origin = lidar.origin + torch.tensor([0.0, 0.0, c], dtype=torch.float64)
        dirs = ray_directions(incl[beams], az)  # (b * M, 3)
        hits = raycast_scan(
            origin, incl[beams], m, prims, ground_z=ground_z, max_range=lidar.max_range, dirs=dirs
        )
        hit = (hits.prim_id != NO_HIT_ID) & torch.isfinite(hits.range_m)
        hit &= (hits.prim_id >= 0) | (hits.prim_id == GROUND_ID)
        idx = torch.nonzero(hit).flatten()
        noise = torch.randn((3, idx.numel()), generator=generator, dtype=torch.float64)
        rng = hits.range_m[idx] + range_noise_m * noise[0]
        sigma = math.radians(angle_noise_deg)
        el = incl[beams][idx // m] + sigma * noise[1]
        a = az[idx % m] + sigma * noise[2]
        ray = torch.stack([el.cos() * a.cos(), el.cos() * a.sin(), el.sin()], dim=1)  # (n, 3)
        pts.append(origin + rng[:, None] * ray)
        ids.append(beams[idx // m] * m + idx % m)
    return torch.cat(pts).numpy(), torch.cat(ids).numpy()
