"""Named spinning-LiDAR presets (``LIDAR.PRESET`` in an attack YAML, docs/attacks.md).

A preset is a sensor's own geometry: beam table, per-laser vertical offsets and firings per
turn. Where the sensor sits on the vehicle (``ORIGIN``) and what range the spoofer may inject
(``MAX_RANGE``) are properties of the setup, not of the sensor, and stay separate keys.

Sources of the published facts (tables are generated from them, nothing is copied):

- ``waymo_top``: the documented default TOP table of :func:`waymo_top_inclinations_deg`
  (published FOV -17.6 deg to +2.4 deg, 2651 columns as in the ATLAS paper), single origin.
- ``hdl64e``: the Velodyne HDL-64E S2 user manual and datasheet: 64 lasers in two blocks of 32,
  upper block +2.0 deg down to -8.33 deg in 1/3 deg steps, lower block -8.83 deg down to
  -24.33 deg in 1/2 deg steps (vertical FOV ~26.9 deg); each laser's vertical offset from the
  sensor frame in the unit calibration is about 0.20 m (upper block) and 0.12 m (lower block);
  2005 firings per turn at 10 Hz.
- ``hdl32e``: the Velodyne HDL-32E user manual: 32 lasers from -30.67 deg to +10.67 deg in
  1.33 deg steps, one block on the rotation axis (no vertical offsets); firing cycle 46.08 us,
  so 2170 firings per turn at 10 Hz.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "LidarPreset",
    "LIDAR_PRESETS",
    "WAYMO_AZIMUTH_BINS",
    "WAYMO_TOP_FOV_DEG",
    "WAYMO_TOP_ORIGIN",
    "lidar_preset",
    "hdl64e_inclinations_deg",
    "waymo_top_inclinations_deg",
]

#: Vertical field of view of the Waymo TOP LiDAR (published spec), degrees.
WAYMO_TOP_FOV_DEG = (-17.6, 2.4)
#: Azimuth bins: ceil(360 / 0.1358) as in the ATLAS paper.
WAYMO_AZIMUTH_BINS = math.ceil(360.0 / 0.1358)
#: Sensor position in the vehicle frame (m): Waymo's TOP extrinsic, rounded.
WAYMO_TOP_ORIGIN = (1.43, 0.0, 2.184)
#: Spacing at the top of the fan relative to the mean spacing (the rest grows linearly downward).
_TOP_SPACING_RATIO = 4.0 / 7.0


def waymo_top_inclinations_deg(num_beams: int = 64) -> np.ndarray:
    """The documented default TOP beam table, ascending, in degrees.

    The real 64 values live in each frame's calibration, which OpenPCDet's ``.npy`` files do not
    keep and which is not public elsewhere. This default is an **assumption**: the beams span the
    published FOV [-17.6°, +2.4°] with spacing that shrinks linearly toward the horizon, from
    about 0.45° at the bottom to 0.18° at the top (denser near the horizon, as on the real
    sensor). With real data, use :meth:`LidarModel.fit` on a sequence's TOP points instead.
    """
    lo, hi = WAYMO_TOP_FOV_DEG
    a = _TOP_SPACING_RATIO
    u = np.linspace(0.0, 1.0, num_beams)
    warp = a * u + (1.0 - a) * (1.0 - (1.0 - u) ** 2)  # g(0)=0, g(1)=1, g'(1)=a, g'(0)=2-a
    return lo + (hi - lo) * warp


@dataclass(frozen=True)
class LidarPreset:
    """A sensor's geometry: ``(B,)`` ascending elevations (deg), ``(B,)`` vertical offsets of
    each laser above the sensor origin (m, ``None``: single origin), firings per turn."""

    inclinations_deg: tuple[float, ...]
    offsets_m: tuple[float, ...] | None
    azimuth_bins: int
    description: str


def hdl64e_inclinations_deg() -> tuple[np.ndarray, np.ndarray]:
    """HDL-64E elevations (deg, ascending) and the block of each laser (0 lower, 1 upper)."""
    upper = 2.0 - np.arange(32) / 3.0  # +2.0 .. -8.33, 1/3 deg steps
    lower = -8.83 - 0.5 * np.arange(32)  # -8.83 .. -24.33, 1/2 deg steps
    incl = np.concatenate([lower[::-1], upper[::-1]])
    block = np.concatenate([np.zeros(32, dtype=np.int64), np.ones(32, dtype=np.int64)])
    return incl, block


def _waymo_top() -> LidarPreset:
    return LidarPreset(
        tuple(float(v) for v in waymo_top_inclinations_deg()),
        None,
        WAYMO_AZIMUTH_BINS,
        "Waymo TOP, documented default table (-17.6 to +2.4 deg), 2651 columns",
    )


def _hdl64e() -> LidarPreset:
    incl, block = hdl64e_inclinations_deg()
    offsets = np.where(block == 1, 0.20, 0.12)
    return LidarPreset(
        tuple(float(v) for v in incl),
        tuple(float(v) for v in offsets),
        2005,
        "64-beam two-block spinning LiDAR (HDL-64E table), -24.33 to +2.0 deg, lasers 0.12 / "
        "0.20 m above the origin, 2005 firings per turn",
    )


def _hdl32e() -> LidarPreset:
    incl = -30.67 + (4.0 / 3.0) * np.arange(32)  # -30.67 .. +10.66, 1.33 deg steps
    return LidarPreset(
        tuple(float(v) for v in incl),
        None,
        2170,
        "32-beam spinning LiDAR (HDL-32E table), -30.67 to +10.67 deg in 1.33 deg steps, 2170 "
        "firings per turn",
    )


#: preset name -> builder (built on demand: the Waymo table comes from lidar_model)
LIDAR_PRESETS = {"waymo_top": _waymo_top, "hdl64e": _hdl64e, "hdl32e": _hdl32e}


def lidar_preset(name: str) -> LidarPreset:
    """The preset called ``name``; an unknown name is an error listing the known ones."""
    if name not in LIDAR_PRESETS:
        raise KeyError(
            f"unknown LiDAR preset {name!r}: expected one of {', '.join(sorted(LIDAR_PRESETS))}"
        )
    return LIDAR_PRESETS[name]()
