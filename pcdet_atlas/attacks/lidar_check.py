"""Check a sensor-model fit against sensors of known geometry (docs/attacks.md).

For a preset sensor (:func:`~pcdet_atlas.datasets.synthetic.sensor_scan.known_sensor`), scan a
street scene, fit the model from the scan alone, and measure what the attacks care about: beam
errors against the true table, and how often a phantom injected through the fitted model puts
two points in one (beam, firing) of the true sensor, which a real sensor cannot return.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from pcdet_atlas.attacks.raycast import raycast_merge
from pcdet_atlas.datasets.synthetic.sensor_scan import (
    known_sensor,
    scan_known_sensor,
    street_scene,
)
from pcdet_atlas.ops.beam_fit import estimate_azimuth_bins, fit_report
from pcdet_atlas.ops.lidar_model import LidarModel

__all__ = [
    "FIT_METHODS",
    "PHANTOM_RANGES_M",
    "TableError",
    "table_error",
    "open_azimuth",
    "phantom_points",
    "phantom_collisions",
    "check_known_sensor",
]

#: fit methods compared, as (init, offsets) of :meth:`LidarModel.fit`: the older fit (Lloyd
#: from Waymo's table), the data-initialised single-origin table, and the full fit
FIT_METHODS = {
    "old": ("default_table", "off"),
    "single": ("data", "off"),
    "new": ("data", "auto"),
}
PHANTOM_RANGES_M = (10.0, 20.0, 40.0)
#: default azimuth of a phantom (rad); :func:`open_azimuth` finds one the scene leaves open
_PHANTOM_AZIMUTH = math.radians(18.0)


@dataclass
class TableError:
    median_deg: float
    max_deg: float
    within_half_spacing: float  #: share of beams within half the local true spacing


def table_error(fitted: LidarModel, true: LidarModel) -> TableError:
    """Beam-by-beam error of a fitted table against the true one."""
    t = true.inclinations.numpy()
    err = np.abs(fitted.inclinations.numpy() - t)
    gaps = np.diff(t)
    half = np.concatenate([[gaps[0]], np.minimum(gaps[1:], gaps[:-1]), [gaps[-1]]]) / 2
    return TableError(
        math.degrees(float(np.median(err))),
        math.degrees(float(err.max())),
        float(np.mean(err <= half)),
    )


def open_azimuth(scene_xyz: np.ndarray, lidar: LidarModel, range_m: float) -> float:
    """The azimuth (rad, 5 deg steps) whose 30 deg wedge holds the fewest raised scene points
    (> 0.3 m above the ground) nearer than ``range_m + 3``: where a phantom is not hidden."""
    rel = scene_xyz[:, :3] - np.asarray(lidar.origin_xyz)
    raised = (scene_xyz[:, 2] > 0.3) & (np.hypot(rel[:, 0], rel[:, 1]) < range_m + 3.0)
    az = np.arctan2(rel[raised, 1], rel[raised, 0])
    cands = np.deg2rad(np.arange(0.0, 360.0, 5.0))
    wrapped = np.angle(np.exp(1j * (az[None, :] - cands[:, None])))  # (A, n)
    return float(cands[np.argmin((np.abs(wrapped) < math.radians(15.0)).sum(axis=1))])


def phantom_points(
    lidar: LidarModel,
    range_m: float,
    generator: torch.Generator,
    count: int = 4000,
    azimuth_rad: float = _PHANTOM_AZIMUTH,
) -> torch.Tensor:
    """``(count, 3)`` float64 points on the surface of a car-sized box (4.5 x 1.9 x 1.6 m)
    standing on the ground ``range_m`` from the sensor at ``azimuth_rad``, facing it: a dense
    phantom trace."""
    length, width, height = 4.5, 1.9, 1.6
    ox, oy, _ = lidar.origin_xyz
    c, s = math.cos(azimuth_rad), math.sin(azimuth_rad)
    u = torch.rand((count, 3), generator=generator, dtype=torch.float64) - 0.5
    face = torch.randint(0, 3, (count,), generator=generator)
    sign = torch.where(u[:, 0] >= 0, 0.5, -0.5).to(torch.float64)
    u[face == 0, 0] = sign[face == 0]  # front/back faces
    u[face == 1, 1] = sign[face == 1]  # sides
    u[face == 2, 2] = 0.5  # roof
    local = u * torch.tensor([length, width, height], dtype=torch.float64)
    x = ox + (range_m + local[:, 0]) * c - local[:, 1] * s
    y = oy + (range_m + local[:, 0]) * s + local[:, 1] * c
    return torch.stack([x, y, local[:, 2] + height / 2], dim=1)


def phantom_collisions(
    scene_xyz: np.ndarray, phantom: torch.Tensor, model: LidarModel, true: LidarModel
) -> tuple[float, int]:
    """Inject ``phantom`` through ``model`` (one echo per ray of the model); return the share of
    the kept phantom points that share a (beam, firing) of the ``true`` sensor with another kept
    point, and the number kept."""
    _, keep = raycast_merge(torch.from_numpy(scene_xyz), phantom, model, p_dual=0.0)
    kept = phantom[keep]
    if kept.shape[0] == 0:
        return 0.0, 0
    bins, fov, _ = true.bin_index(kept)
    _, inverse, counts = torch.unique(bins, return_inverse=True, return_counts=True)
    return float((counts[inverse] > 1).double().mean()), int(kept.shape[0])


def check_known_sensor(
    preset: str, seed: int = 0, angle_noise_deg: float = 0.005, frames: int = 1
) -> dict:
    """Scan a known sensor, fit it with each of :data:`FIT_METHODS`, and measure each fit.

    Returns a dict: ``true`` (the sensor), ``scan`` (``(N, 3)`` points of the first frame),
    and per method ``model``, ``error`` (:class:`TableError`), ``on_beam`` (report share),
    ``warnings``, ``collisions`` (range -> share of kept phantom points in a shared true ray),
    plus ``true_collisions`` (the same through the true model) and ``azimuth_bins`` (estimated
    from the new fit's beams).
    """
    gen = torch.Generator().manual_seed(seed)
    true = known_sensor(preset, gen)
    scans = [
        scan_known_sensor(true, street_scene(gen), gen, angle_noise_deg=angle_noise_deg)[0]
        for _ in range(frames)
    ]
    points = np.concatenate(scans)
    out: dict = {"true": true, "scan": scans[0]}
    phantoms = {
        r: phantom_points(true, r, gen, azimuth_rad=open_azimuth(scans[0], true, r))
        for r in PHANTOM_RANGES_M
    }
    out["true_collisions"] = {
        r: phantom_collisions(scans[0], p, true, true)[0] for r, p in phantoms.items()
    }
    for method, (init, offsets) in FIT_METHODS.items():
        model = LidarModel.fit(
            points, true.num_beams, true.origin_xyz, offsets=offsets, init=init,
            azimuth_bins=true.azimuth_bins,
        )  # fmt: skip
        report = fit_report(model, points)
        out[method] = {
            "model": model,
            "error": table_error(model, true),
            "on_beam": report.on_beam_share,
            "warnings": report.warnings,
            "collisions": {
                r: phantom_collisions(scans[0], p, model, true)[0] for r, p in phantoms.items()
            },
        }
    out["azimuth_bins"] = estimate_azimuth_bins(scans, out["new"]["model"])[0]
    return out
