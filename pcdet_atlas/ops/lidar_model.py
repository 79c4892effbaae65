"""The spinning-LiDAR model (docs/attacks.md): beams, azimuth bins, sensor origin, field of view.

One (azimuth bin, beam) pair is one ray. All spherical coordinates are taken relative to the
sensor origin, never the vehicle-frame origin.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import torch

from pcdet_atlas.config import ConfigError, check_known_keys
from pcdet_atlas.config_values import config_value

__all__ = ["LidarModel", "WAYMO_TOP_FOV_DEG", "spherical_offsets", "waymo_top_inclinations_deg"]

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


def spherical_offsets(
    dx: np.ndarray, dy: np.ndarray, dz: np.ndarray, with_range: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Azimuth in (-pi, pi], elevation and range (float64) of points given as ``(N,)`` float64
    offsets from the sensor origin: the numpy arithmetic that defines every CPU binning
    (``with_range=False``: the range is not computed and comes back as ``None``).

    numpy's ``sqrt`` is IEEE-exact and its ``arctan2`` gives each element the same value whatever
    its position in the array, so binning a subset of a scene gives every point the bin it gets in
    the whole scene; every CPU consumer (the raycaster, the removal sector,
    :meth:`LidarModel.spherical` on CPU tensors) goes through this one function.
    """
    horiz = np.sqrt(dx**2 + dy**2)
    azimuth = np.arctan2(dy, dx)
    azimuth[azimuth == -math.pi] = math.pi
    elevation = np.arctan2(dz, horiz)
    return azimuth, elevation, np.sqrt(horiz**2 + dz**2) if with_range else None


class LidarModel:
    """Beam table, azimuth binning, origin and range of a spinning LiDAR.

    Args:
        inclinations: ``(B,)`` beam elevation angles in radians, strictly ascending.
        azimuth_bins: number of azimuth columns ``M`` over 360°.
        origin: sensor position in the vehicle frame, metres.
        max_range: maximum return range, metres.
    """

    def __init__(
        self,
        inclinations: Sequence[float] | np.ndarray | torch.Tensor,
        azimuth_bins: int = WAYMO_AZIMUTH_BINS,
        origin: Sequence[float] = WAYMO_TOP_ORIGIN,
        max_range: float = 75.0,
    ):
        incl = torch.as_tensor(np.asarray(inclinations, dtype=np.float64)).flatten()
        if incl.numel() < 2:
            raise ValueError(f"LidarModel needs at least 2 inclinations, got {incl.numel()}")
        if not torch.isfinite(incl).all():
            raise ValueError("LidarModel inclinations must be finite")
        if not (incl[1:] > incl[:-1]).all():
            raise ValueError("LidarModel inclinations must be strictly ascending (radians)")
        if int(azimuth_bins) < 1:
            raise ValueError(f"azimuth_bins must be >= 1, got {azimuth_bins}")
        if len(origin) != 3 or not all(math.isfinite(float(v)) for v in origin):
            raise ValueError(f"origin must have 3 finite values (x, y, z), got {origin}")
        if not max_range > 0:
            raise ValueError(f"max_range must be > 0, got {max_range}")
        self.inclinations = incl  # (B,) float64, radians
        self.azimuth_bins = int(azimuth_bins)
        self.origin = torch.tensor([float(v) for v in origin], dtype=torch.float64)
        #: the origin as Python floats, for plain-float arithmetic (wedges, sector angles) that
        #: needs no tensor
        self.origin_xyz: tuple[float, float, float] = tuple(float(v) for v in origin)
        self.max_range = float(max_range)
        # Beam boundaries: midpoints between neighbours; the FOV extends half a spacing beyond the
        # outermost beams.
        self._midpoints = (incl[1:] + incl[:-1]) / 2  # (B-1,)
        self.fov_min = float(incl[0] - (incl[1] - incl[0]) / 2)
        self.fov_max = float(incl[-1] + (incl[-1] - incl[-2]) / 2)
        # per-device copies of (origin, midpoints), so CUDA calls do no host-to-device copy
        self._device_cache: dict[torch.device, tuple[torch.Tensor, torch.Tensor]] = {}
        # numpy views of the same constants for the CPU paths (read-only float64)
        self.origin_np = self.origin.numpy()
        self.midpoints_np = self._midpoints.numpy()
        self.origin_np.flags.writeable = False
        self.midpoints_np.flags.writeable = False

    def _constants(self, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        """``(origin (3,), beam midpoints (B-1,))`` float64 on ``device`` (cached)."""
        device = torch.device(device)
        if device not in self._device_cache:
            self._device_cache[device] = (self.origin.to(device), self._midpoints.to(device))
        return self._device_cache[device]

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_device_cache"] = {}  # never pickle device tensors (DataLoader workers)
        return state

    # ------------------------------------------------------------------ construction
    @classmethod
    def waymo_top(cls, **kwargs) -> LidarModel:
        """The Waymo TOP LiDAR with the documented default beam table (an assumption, see docs)."""
        return cls(np.deg2rad(waymo_top_inclinations_deg()), **kwargs)

    @classmethod
    def fit(
        cls,
        points_xyz,
        num_beams: int = 64,
        origin: Sequence[float] = WAYMO_TOP_ORIGIN,
        iterations: int = 30,
        **kwargs,
    ) -> LidarModel:
        """Estimate the beam table from TOP-LiDAR points (the first ``num_points_of_each_lidar[0]``
        rows of a frame, ideally several frames of one sequence).

        1-D Lloyd iterations on point elevations, started from the default table: each point goes
        to its nearest beam, each beam moves to the median elevation of its points. Beams that
        receive no points (e.g. sky beams) keep their default elevation.

        Args:
            points_xyz: ``(N, 3+)`` points in the vehicle frame (numpy or torch).
        """
        pts = torch.as_tensor(np.asarray(points_xyz)[:, :3], dtype=torch.float64)
        if pts.shape[0] < num_beams:
            raise ValueError(
                f"LidarModel.fit needs at least {num_beams} points, got {pts.shape[0]}"
            )
        rel = pts - torch.tensor([float(v) for v in origin], dtype=torch.float64)
        elev = torch.atan2(rel[:, 2], torch.linalg.norm(rel[:, :2], dim=1))
        centers = torch.as_tensor(np.deg2rad(waymo_top_inclinations_deg(num_beams)))
        for _ in range(iterations):
            mids = (centers[1:] + centers[:-1]) / 2
            beam = torch.bucketize(elev, mids)
            new = centers.clone()
            for b in torch.unique(beam).tolist():
                new[b] = elev[beam == b].median()
            new, _ = torch.sort(new)
            if torch.allclose(new, centers, atol=1e-9, rtol=0):
                break
            centers = new
        return cls(centers, origin=origin, **kwargs)

    @classmethod
    def from_config(cls, cfg: Mapping | None) -> LidarModel:
        """Build from a ``LIDAR`` config section.

        Keys (all optional): ``INCLINATIONS`` (radians) or ``INCLINATIONS_DEG``, ``AZIMUTH_BINS``,
        ``ORIGIN``, ``MAX_RANGE``. Without inclinations, the default Waymo TOP table is used.
        """
        cfg = cfg or {}
        check_known_keys(
            cfg,
            {"INCLINATIONS", "INCLINATIONS_DEG", "AZIMUTH_BINS", "ORIGIN", "MAX_RANGE"},
            "LIDAR",
        )
        if "INCLINATIONS" in cfg and "INCLINATIONS_DEG" in cfg:
            raise ConfigError("LIDAR: give INCLINATIONS (rad) or INCLINATIONS_DEG, not both")
        kwargs = {
            "azimuth_bins": config_value(
                cfg, "AZIMUTH_BINS", int, "LIDAR", WAYMO_AZIMUTH_BINS,
                valid=lambda m: m >= 1, expected="a positive integer",
            ),
            "origin": config_value(
                cfg, "ORIGIN", lambda o: tuple(float(v) for v in o), "LIDAR", WAYMO_TOP_ORIGIN,
                valid=lambda o: len(o) == 3, expected="[x, y, z] in metres",
            ),
            "max_range": config_value(
                cfg, "MAX_RANGE", float, "LIDAR", 75.0,
                valid=lambda r: r > 0, expected="a positive range in metres",
            ),
        }  # fmt: skip
        for key in ("INCLINATIONS", "INCLINATIONS_DEG"):
            if key in cfg:
                unit = "radians" if key == "INCLINATIONS" else "degrees"
                angles = config_value(
                    cfg, key, lambda a: [float(v) for v in a], "LIDAR",
                    valid=lambda a: len(a) >= 2 and all(x < y for x, y in zip(a, a[1:])),
                    expected=f"a list of at least 2 beam inclinations in {unit}, ascending",
                )  # fmt: skip
                if key == "INCLINATIONS_DEG":
                    angles = np.deg2rad(np.asarray(angles, dtype=np.float64))
                return cls(angles, **kwargs)
        return cls.waymo_top(**kwargs)

    # ------------------------------------------------------------------ geometry
    @property
    def num_beams(self) -> int:
        return self.midpoints_np.size + 1  # no torch call on the CPU paths

    @property
    def num_bins(self) -> int:
        """Total number of rays, ``num_beams * azimuth_bins``."""
        return self.num_beams * self.azimuth_bins

    def spherical(self, xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Azimuth in (-pi, pi], elevation and range of ``(N, 3)`` points relative to the origin.

        Computed in float64. CPU tensors go through :func:`spherical_offsets` (numpy), the
        arithmetic of every CPU path; CUDA tensors through the same formulas in torch, whose
        ``sqrt`` / ``atan2`` kernels may round the last bit differently, so a point within an
        ulp of a bin edge can fall in the neighbouring bin on a GPU (each device is
        deterministic on its own).
        Returns three ``(N,)`` float64 tensors (radians, radians, metres).
        """
        if xyz.device.type == "cpu":
            rel = xyz[:, :3].detach().to(torch.float64).numpy() - self.origin_np
            return tuple(
                torch.from_numpy(v) for v in spherical_offsets(rel[:, 0], rel[:, 1], rel[:, 2])
            )
        rel = xyz[:, :3].to(torch.float64) - self._constants(xyz.device)[0]
        horiz = torch.sqrt(rel[:, 0] ** 2 + rel[:, 1] ** 2)
        azimuth = torch.atan2(rel[:, 1], rel[:, 0])
        azimuth = torch.where(azimuth == -math.pi, torch.full_like(azimuth, math.pi), azimuth)
        elevation = torch.atan2(rel[:, 2], horiz)
        rng = torch.sqrt(horiz**2 + rel[:, 2] ** 2)
        return azimuth, elevation, rng

    def azimuth_index(self, azimuth: torch.Tensor) -> torch.Tensor:
        """Azimuth bin ``floor((theta + pi) / (2 pi / M))`` clamped to ``[0, M - 1]``, long."""
        width = 2 * math.pi / self.azimuth_bins
        return torch.clamp(
            torch.floor((azimuth + math.pi) / width), 0, self.azimuth_bins - 1
        ).long()

    def beam_index(self, elevation: torch.Tensor) -> torch.Tensor:
        """Index of the nearest inclination (a tie at a midpoint goes to the lower beam)."""
        return torch.bucketize(elevation, self._constants(elevation.device)[1])

    def in_fov(self, elevation: torch.Tensor) -> torch.Tensor:
        """Whether an elevation lies in the fan (within half a spacing of the outermost beams)."""
        return (elevation >= self.fov_min) & (elevation <= self.fov_max)

    def bin_index(self, xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Ray id, FOV flag and range of ``(N, 3)`` points.

        Returns:
            bin: ``(N,)`` long, ``beam * azimuth_bins + azimuth_bin``.
            in_fov: ``(N,)`` bool.
            range: ``(N,)`` float64 metres from the sensor origin.
        """
        azimuth, elevation, rng = self.spherical(xyz)
        beam = self.beam_index(elevation)
        return beam * self.azimuth_bins + self.azimuth_index(azimuth), self.in_fov(elevation), rng

    def to_config(self) -> dict:
        """A ``LIDAR`` config section that rebuilds this model exactly."""
        return {
            "INCLINATIONS": [float(v) for v in self.inclinations],
            "AZIMUTH_BINS": self.azimuth_bins,
            "ORIGIN": [float(v) for v in self.origin],
            "MAX_RANGE": self.max_range,
        }

    def __repr__(self) -> str:
        return (
            f"LidarModel(beams={self.num_beams}, azimuth_bins={self.azimuth_bins}, "
            f"fov_deg=({math.degrees(self.fov_min):.2f}, {math.degrees(self.fov_max):.2f}), "
            f"origin={tuple(round(float(v), 3) for v in self.origin)}, max_range={self.max_range})"
        )
