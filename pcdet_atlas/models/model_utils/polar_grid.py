"""The polar voxel grid of the streaming detectors: (height, azimuth, range) cells and sectors.

Azimuth ``theta = atan2(y, x)`` runs over ``[-pi, pi)`` (a point at exactly ``+pi`` belongs to
the first bin, the seam is one bin edge); azimuth bin ``a`` covers
``[-pi + a * 2pi / T, -pi + (a + 1) * 2pi / T)``. Sectors are ``num_sectors`` equal runs of
azimuth bins, numbered in increasing azimuth from the seam, which is the order a frame's sectors
are streamed in. Voxel coordinates are ``[batch, z, azimuth, range]`` (the ``(z, t, r)`` order of
the occupancy grid, docs/model_zoo.md "PHiM"). Range and azimuth are measured from the grid's
``origin_xy``, the sensor's position in the vehicle frame, so a ray of the LiDAR stays in one
azimuth bin.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from pcdet_atlas.models.model_utils.voxelize import VoxelGrid, Voxelization, voxelize

__all__ = ["PolarGrid", "polar_coordinates", "polar_voxelize"]


@dataclass(frozen=True)
class PolarGrid:
    """Cells of ``range_m`` x ``[-pi, pi)`` x ``z_range_m`` split into ``grid_size`` bins.

    Attributes:
        range_m: ``(r_min, r_max)`` horizontal distance from the sensor, metres.
        z_range_m: ``(z_min, z_max)`` metres.
        grid_size: ``(num_range, num_azimuth, num_z)`` bins.
        num_sectors: azimuth sectors; ``num_azimuth`` must be a multiple.
        origin_xy: ``(x, y)`` metres, the vehicle-frame point range and azimuth are measured
            from (the LiDAR's mount; z stays the vehicle frame's).
    """

    range_m: tuple[float, float]
    z_range_m: tuple[float, float]
    grid_size: tuple[int, int, int]
    num_sectors: int
    origin_xy: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        (r0, r1), (z0, z1) = self.range_m, self.z_range_m
        if not (0.0 <= r0 < r1 and z0 < z1):
            raise ValueError(
                f"PolarGrid: need 0 <= r_min < r_max and z_min < z_max, got range "
                f"{self.range_m}, z {self.z_range_m}"
            )
        if len(self.grid_size) != 3 or min(self.grid_size) < 1:
            raise ValueError(f"PolarGrid: grid_size needs 3 positive counts, got {self.grid_size}")
        if len(self.origin_xy) != 2 or not all(math.isfinite(v) for v in self.origin_xy):
            raise ValueError(f"PolarGrid: origin_xy needs 2 finite metres, got {self.origin_xy}")
        if self.num_sectors < 1 or self.grid_size[1] % self.num_sectors:
            raise ValueError(
                f"PolarGrid: the {self.grid_size[1]} azimuth bins do not split into "
                f"{self.num_sectors} equal sectors"
            )

    @property
    def cell_size(self) -> tuple[float, float, float]:
        """``(range_m, azimuth_rad, z_m)`` size of one cell."""
        nr, na, nz = self.grid_size
        return (
            (self.range_m[1] - self.range_m[0]) / nr,
            2 * math.pi / na,
            (self.z_range_m[1] - self.z_range_m[0]) / nz,
        )

    @property
    def sector_bins(self) -> int:
        """Azimuth bins per sector."""
        return self.grid_size[1] // self.num_sectors

    def as_voxel_grid(self) -> VoxelGrid:
        """The same cells as a regular grid over ``(r, theta, z)`` (x <- range, y <- azimuth)."""
        (r0, r1), (z0, z1) = self.range_m, self.z_range_m
        return VoxelGrid((r0, -math.pi, z0, r1, math.pi, z1), self.cell_size)

    def cell_centres(self, coords: torch.Tensor) -> torch.Tensor:
        """``(V, 3)`` ``(r, theta, z)`` centres of cells ``coords`` ``(V, 4)`` ``[b, z, a, r]``."""
        dr, da, dz = self.cell_size
        c = coords.to(torch.float32)
        return torch.stack(
            [
                self.range_m[0] + (c[:, 3] + 0.5) * dr,
                -math.pi + (c[:, 2] + 0.5) * da,
                self.z_range_m[0] + (c[:, 1] + 0.5) * dz,
            ],
            dim=1,
        )


def polar_coordinates(
    xyz: torch.Tensor, origin_xy: tuple[float, float] = (0.0, 0.0)
) -> torch.Tensor:
    """``(N, 3)`` Cartesian -> ``(N, 3)`` float64 ``(r, theta, z)`` about ``origin_xy`` (metres),
    theta in ``[-pi, pi)``."""
    p = xyz.to(torch.float64)
    if origin_xy[0] or origin_xy[1]:
        p = p - p.new_tensor([origin_xy[0], origin_xy[1], 0.0])
    theta = torch.atan2(p[:, 1], p[:, 0])
    theta = torch.where(theta >= math.pi, theta - 2 * math.pi, theta)  # +pi joins the first bin
    # just below +pi, theta + pi may round up to 2 pi and leave the grid: keep it in the last bin
    theta = theta.clamp(max=math.pi - 1e-12)
    return torch.stack([torch.hypot(p[:, 0], p[:, 1]), theta, p[:, 2]], dim=1)


def polar_voxelize(points: torch.Tensor, grid: PolarGrid) -> Voxelization:
    """Group batched points ``(N, 1 + C)`` ``[b, x, y, z, ...]`` into the cells of ``grid``.

    Returns :func:`~pcdet_atlas.models.model_utils.voxelize.voxelize`'s result on the polar
    coordinates about ``grid.origin_xy``: ``voxel_coords`` ``[b, z, azimuth, range]``, sorted by
    ``(b, z, a, r)``; points outside ``range_m`` or ``z_range_m`` belong to no voxel.
    """
    if points.dim() != 2 or points.shape[1] < 4:
        raise ValueError(f"polar_voxelize: points must be (N, 1 + C>=3), got {tuple(points.shape)}")
    polar = torch.cat(
        [points[:, :1].to(torch.float64), polar_coordinates(points[:, 1:4], grid.origin_xy)], 1
    )
    return voxelize(polar, grid.as_voxel_grid())
