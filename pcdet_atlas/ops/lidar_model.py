"""The spinning-LiDAR model (docs/attacks.md): beams, azimuth bins, sensor origin, field of view.

One (azimuth bin, beam) pair is one ray. All spherical coordinates are taken relative to the
sensor origin, never the vehicle-frame origin.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from pcdet_atlas.config_values import read_section, setting
from pcdet_atlas.ops.beam_fit import fit_beam_table
from pcdet_atlas.ops.lidar_presets import (
    LIDAR_PRESETS,
    WAYMO_AZIMUTH_BINS,
    WAYMO_TOP_FOV_DEG,
    WAYMO_TOP_ORIGIN,
    lidar_preset,
    waymo_top_inclinations_deg,
)

__all__ = [
    "LidarConfig",
    "LidarModel",
    "WAYMO_AZIMUTH_BINS",
    "WAYMO_TOP_FOV_DEG",
    "WAYMO_TOP_ORIGIN",
    "spherical_offsets",
    "waymo_top_inclinations_deg",
]

#: Points closer to the sensor axis than this (m) are binned as if at this distance (offsets).
_MIN_HORIZ_M = 1e-6
#: Points per chunk of the offset binning (bounds its (n, B) float64 work arrays).
_OFFSET_CHUNK = 65536


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


def _ascending(angles: Sequence[float]) -> bool:
    return len(angles) >= 2 and all(x < y for x, y in zip(angles, angles[1:]))


@dataclass(frozen=True, kw_only=True)
class LidarConfig:
    """The ``LIDAR`` section of an attack config: one beam table (a preset, or inclinations in
    radians or degrees; none: the default Waymo TOP table) and the binning."""

    preset: str | None = setting(
        None,
        choices=sorted(LIDAR_PRESETS),
        expected=f"one of the LiDAR presets {', '.join(sorted(LIDAR_PRESETS))}",
        doc="a named sensor (its beam table, offsets and azimuth bins)",
    )
    inclinations: tuple[float, ...] | None = setting(
        None,
        check=_ascending,
        expected="a list of at least 2 beam inclinations in radians, ascending",
        doc="beam elevation angles, rad",
    )
    inclinations_deg: tuple[float, ...] | None = setting(
        None,
        check=_ascending,
        expected="a list of at least 2 beam inclinations in degrees, ascending",
        doc="beam elevation angles, degrees",
    )
    offsets: tuple[float, ...] | None = setting(
        None, doc="height of each laser above ORIGIN, m (one per beam of an explicit table)"
    )
    azimuth_bins: int | None = setting(
        None, ge=1, expected="a positive integer", doc="azimuth columns (the preset's, else 2651)"
    )
    origin: tuple[float, float, float] = setting(
        WAYMO_TOP_ORIGIN, expected="[x, y, z] in metres", doc="sensor position, m"
    )
    max_range: float = setting(
        75.0, gt=0, expected="a positive range in metres", doc="maximum return range, m"
    )

    def __post_init__(self) -> None:
        tables = [
            key
            for key, value in (
                ("PRESET", self.preset),
                ("INCLINATIONS", self.inclinations),
                ("INCLINATIONS_DEG", self.inclinations_deg),
            )
            if value is not None
        ]
        if len(tables) > 1:
            raise ValueError(
                f"give one of PRESET, INCLINATIONS (rad), INCLINATIONS_DEG, not {tables}"
            )
        if self.offsets is None:
            return
        if tables in ([], ["PRESET"]):
            raise ValueError(
                "OFFSETS needs an explicit table (INCLINATIONS or INCLINATIONS_DEG): a "
                "preset carries its own offsets"
            )
        num = len(self.inclinations or self.inclinations_deg)
        if len(self.offsets) != num:
            raise ValueError(
                f"OFFSETS = {list(self.offsets)!r}: expected {num} laser heights above "
                f"ORIGIN in metres, one per beam of {tables[0]}"
            )


class LidarModel:
    """Beam table, azimuth binning, origin and range of a spinning LiDAR.

    Args:
        inclinations: ``(B,)`` beam elevation angles in radians, strictly ascending.
        azimuth_bins: number of azimuth columns ``M`` over 360°.
        origin: sensor position in the vehicle frame, metres.
        max_range: maximum return range, metres.
        offsets: ``(B,)`` height of each laser above the origin, metres (``None`` or all zeros:
            every laser at the origin). With offsets, a point at horizontal distance ``d`` from
            the origin is seen by beam ``k`` at elevation ``atan(tan(theta_k) + c_k / d)``, and
            the binning picks the beam whose elevation *at the point's distance* is nearest.
    """

    def __init__(
        self,
        inclinations: Sequence[float] | np.ndarray | torch.Tensor,
        azimuth_bins: int = WAYMO_AZIMUTH_BINS,
        origin: Sequence[float] = WAYMO_TOP_ORIGIN,
        max_range: float = 75.0,
        offsets: Sequence[float] | np.ndarray | torch.Tensor | None = None,
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
        if offsets is not None:
            offsets = torch.as_tensor(np.asarray(offsets, dtype=np.float64)).flatten()
            if offsets.shape != incl.shape or not torch.isfinite(offsets).all():
                raise ValueError(
                    f"LidarModel offsets must be {incl.numel()} finite values (one per beam, m), "
                    f"got {offsets.numel()}"
                )
            if not offsets.any():
                offsets = None  # all lasers at the origin: the single-origin binning
        #: ``(B,)`` float64 laser heights above the origin (m), or ``None`` (single origin)
        self.offsets = offsets
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
    def preset(cls, name: str, **kwargs) -> LidarModel:
        """A named sensor of :mod:`pcdet_atlas.ops.lidar_presets` (``waymo_top``, ``hdl64e``,
        ``hdl32e``): its beam table, laser offsets and azimuth bins; ``kwargs`` (``origin``,
        ``max_range``, ``azimuth_bins``) override."""
        spec = lidar_preset(name)
        kwargs.setdefault("azimuth_bins", spec.azimuth_bins)
        return cls(np.deg2rad(spec.inclinations_deg), offsets=spec.offsets_m, **kwargs)

    @classmethod
    def fit(
        cls,
        points_xyz,
        num_beams: int = 64,
        origin: Sequence[float] = WAYMO_TOP_ORIGIN,
        offsets: str = "auto",
        init: str = "data",
        **kwargs,
    ) -> LidarModel:
        """Estimate the beam table (and, where the data shows parallax, each laser's vertical
        offset) from TOP-LiDAR points: :func:`pcdet_atlas.ops.beam_fit.fit_beam_table`.

        Args:
            points_xyz: ``(N, 3+)`` points in the vehicle frame (numpy or torch), ideally
                several frames of one sequence.
            offsets: ``"auto"`` (fit them, keep them when they bring the points closer to their
                beams), ``"on"`` or ``"off"``.
            init: ``"data"`` (elevation-histogram peaks) or ``"default_table"`` (Lloyd from
                the default Waymo table, the older method, kept for comparison).
            **kwargs: passed to :class:`LidarModel` (``azimuth_bins``, ``max_range``).
        """
        pts = np.asarray(
            points_xyz.detach().cpu().numpy() if torch.is_tensor(points_xyz) else points_xyz
        )
        fitted = fit_beam_table(pts, num_beams, origin, offsets=offsets, init=init)
        return cls(fitted.inclinations, origin=origin, offsets=fitted.offsets, **kwargs)

    @classmethod
    def from_config(cls, cfg: Mapping | None) -> LidarModel:
        """Build from a ``LIDAR`` config section (:class:`LidarConfig`; ``{}``: the default
        Waymo TOP table)."""
        return cls.from_settings(read_section(LidarConfig, cfg, "LIDAR"))

    @classmethod
    def from_settings(cls, settings: LidarConfig) -> LidarModel:
        """Build from a read ``LIDAR`` section."""
        kwargs = {"origin": settings.origin, "max_range": settings.max_range}
        if settings.azimuth_bins is not None:  # else the preset's, or the paper's 2651
            kwargs["azimuth_bins"] = settings.azimuth_bins
        if settings.preset is not None:
            return cls.preset(settings.preset, **kwargs)
        if settings.offsets is not None:
            kwargs["offsets"] = list(settings.offsets)
        if settings.inclinations is not None:
            return cls(list(settings.inclinations), **kwargs)
        if settings.inclinations_deg is not None:
            radians = np.deg2rad(np.asarray(settings.inclinations_deg, dtype=np.float64))
            return cls(radians, **kwargs)
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
        # in place on one temporary (the same arithmetic as ``floor((theta + pi) / width)``)
        return (azimuth + math.pi).div_(width).floor_().clamp_(0, self.azimuth_bins - 1).long()

    def beam_index(
        self, elevation: torch.Tensor, horiz: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Index of the nearest inclination (a tie at a midpoint goes to the lower beam).

        With laser offsets, the nearest beam elevation at each point's horizontal distance
        ``horiz`` (m, required then) from the origin: :meth:`beam_elevations`.
        """
        if self.offsets is None:
            return torch.bucketize(elevation, self._constants(elevation.device)[1])
        return self._offset_binning(elevation, self._need_horiz(horiz))[0]

    def in_fov(self, elevation: torch.Tensor, horiz: torch.Tensor | None = None) -> torch.Tensor:
        """Whether an elevation lies in the fan (within half a spacing of the outermost beams;
        with laser offsets, of their elevations at the horizontal distance ``horiz``)."""
        if self.offsets is None:
            return (elevation >= self.fov_min) & (elevation <= self.fov_max)
        return self._offset_binning(elevation, self._need_horiz(horiz))[1]

    def beam_elevations(self, horiz: torch.Tensor) -> torch.Tensor:
        """``(N, B)`` float64 elevation of each beam seen from the origin at horizontal
        distances ``(N,)`` (m): ``atan(tan(theta_k) + c_k / d)`` (``theta_k`` without offsets)."""
        incl = self.inclinations.to(horiz.device)
        if self.offsets is None:
            return incl.expand(horiz.shape[0], -1)
        d = horiz.to(torch.float64).clamp(min=_MIN_HORIZ_M)[:, None]
        return torch.atan(torch.tan(incl) + self.offsets.to(horiz.device) / d)

    def _need_horiz(self, horiz: torch.Tensor | None) -> torch.Tensor:
        if horiz is None:
            raise ValueError(
                "this LidarModel has laser offsets: beam_index / in_fov need each point's "
                "horizontal distance from the origin (horiz)"
            )
        return horiz

    def _offset_binning(
        self, elevation: torch.Tensor, horiz: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Beam (nearest beam elevation at the point's distance, ties to the lower index) and
        FOV flag of points with laser offsets, in chunks of bounded ``(n, B)`` memory."""
        incl = self.inclinations
        lo_half = float(incl[1] - incl[0]) / 2
        hi_half = float(incl[-1] - incl[-2]) / 2
        beams, fovs = [], []
        for start in range(0, elevation.shape[0], _OFFSET_CHUNK):
            el = elevation[start : start + _OFFSET_CHUNK].to(torch.float64)
            pred = self.beam_elevations(horiz[start : start + _OFFSET_CHUNK])  # (n, B)
            beams.append(torch.argmin((el[:, None] - pred).abs(), dim=1))
            fovs.append((el >= pred[:, 0] - lo_half) & (el <= pred[:, -1] + hi_half))
        if not beams:
            empty = torch.zeros(0, dtype=torch.long, device=elevation.device)
            return empty, empty.bool()
        return torch.cat(beams), torch.cat(fovs)

    def bin_index(self, xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Ray id, FOV flag and range of ``(N, 3)`` points.

        Returns:
            bin: ``(N,)`` long, ``beam * azimuth_bins + azimuth_bin``.
            in_fov: ``(N,)`` bool.
            range: ``(N,)`` float64 metres from the sensor origin.
        """
        azimuth, elevation, rng = self.spherical(xyz)
        if self.offsets is None:
            beam, fov = self.beam_index(elevation), self.in_fov(elevation)
        else:
            beam, fov = self._offset_binning(elevation, rng * torch.cos(elevation))
        return torch.add(self.azimuth_index(azimuth), beam, alpha=self.azimuth_bins), fov, rng

    def to_config(self) -> dict:
        """A ``LIDAR`` config section that rebuilds this model exactly."""
        cfg = {"INCLINATIONS": [float(v) for v in self.inclinations]}
        if self.offsets is not None:
            cfg["OFFSETS"] = [float(v) for v in self.offsets]
        cfg.update(
            AZIMUTH_BINS=self.azimuth_bins,
            ORIGIN=[float(v) for v in self.origin],
            MAX_RANGE=self.max_range,
        )
        return cfg

    def __repr__(self) -> str:
        lo, hi = (0.0, 0.0) if self.offsets is None else (self.offsets.min(), self.offsets.max())
        return (
            f"LidarModel(beams={self.num_beams}, azimuth_bins={self.azimuth_bins}, "
            f"fov_deg=({math.degrees(self.fov_min):.2f}, {math.degrees(self.fov_max):.2f}), "
            f"origin={tuple(round(float(v), 3) for v in self.origin)}, max_range={self.max_range}"
            + ("" if self.offsets is None else f", offsets_m=({lo:.3f}..{hi:.3f})")
            + ")"
        )
