"""Dynamic voxelization / pillarization as a torch op inside the model.

Points are grouped by the integer cell they fall in; there is no per-voxel point cap and no voxel
cap (OpenPCDet's dynamic VFEs), so no point is dropped inside the range. Each point gets a linear
cell key; keys are grouped through a dense per-cell table (pillar grids) or ``torch.unique``
(large 3D grids). Both are deterministic on CPU and GPU and give the same result.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch

from pcdet_atlas.config import ConfigError, key_source

__all__ = [
    "VoxelGrid",
    "Voxelization",
    "check_point_columns",
    "check_voxel_size_placeholder",
    "voxelize",
]

# grids with at most this many cells (batch included) group points with a dense per-cell table
# (bincount, O(N + cells)); larger ones (fine 3D voxels) sort the keys with torch.unique
DENSE_KEY_LIMIT = 1 << 25


@dataclass(frozen=True)
class VoxelGrid:
    """A regular grid over ``point_cloud_range``.

    Attributes:
        point_cloud_range: ``(x_min, y_min, z_min, x_max, y_max, z_max)`` in metres.
        voxel_size: ``(vx, vy, vz)`` in metres (a pillar grid has ``vz = z_max - z_min``).
    """

    point_cloud_range: tuple[float, float, float, float, float, float]
    voxel_size: tuple[float, float, float]

    def __post_init__(self) -> None:
        pcr, vs = self.point_cloud_range, self.voxel_size
        if len(pcr) != 6 or len(vs) != 3:
            raise ValueError(
                f"VoxelGrid: point_cloud_range needs 6 values and voxel_size 3, got {pcr}, {vs}"
            )
        for i in range(3):
            if not pcr[i + 3] > pcr[i]:
                raise ValueError(f"VoxelGrid: empty point_cloud_range {pcr}")
            if not vs[i] > 0:
                raise ValueError(f"VoxelGrid: voxel_size must be positive, got {vs}")
        size = self.grid_size
        for i in range(3):
            if abs(size[i] * vs[i] - (pcr[i + 3] - pcr[i])) > 1e-3 * vs[i]:
                raise ValueError(
                    f"VoxelGrid: the range {pcr[i]}..{pcr[i + 3]} along axis {'xyz'[i]} is not a "
                    f"whole number of voxels of {vs[i]} m"
                )

    @property
    def grid_size(self) -> tuple[int, int, int]:
        """``(nx, ny, nz)`` number of cells per axis."""
        pcr, vs = self.point_cloud_range, self.voxel_size
        return tuple(int(round((pcr[i + 3] - pcr[i]) / vs[i])) for i in range(3))


@dataclass
class Voxelization:
    """The result of :func:`voxelize` for a batch.

    Attributes:
        point_mask: (N,) bool, points inside the range (the others belong to no voxel).
        point_voxel_idx: (N_in,) int64, voxel of each kept point (index into ``voxel_coords``).
        voxel_coords: (V, 4) int64 ``[batch_idx, z, y, x]`` cell indices (OpenPCDet's order).
        voxel_num_points: (V,) int64 number of points per voxel.
    """

    point_mask: torch.Tensor
    point_voxel_idx: torch.Tensor
    voxel_coords: torch.Tensor
    voxel_num_points: torch.Tensor


def voxelize(points: torch.Tensor, grid: VoxelGrid, *, bound_z: bool = True) -> Voxelization:
    """Group batched points into the cells of ``grid``.

    Args:
        points: (N, 1 + C) float, ``[batch_idx, x, y, z, ...]`` (the collate layout).
        grid: the voxel grid.
        bound_z: False (a pillar grid, one z cell): a point below or above the z range still
            falls in the pillar under it, as in OpenPCDet's ``DynamicPillarVFE``, which bounds x
            and y only.

    Returns:
        A :class:`Voxelization`. Voxels are sorted by ``(batch, z, y, x)``. A point on the upper
        boundary of the range is outside (half-open cells). Cells are
        ``floor((p - range_min) / voxel_size)`` in the points' dtype (float32 for half
        precision), the range and size rounded to it first, as spconv's voxel generator.
    """
    if points.dim() != 2 or points.shape[1] < 4:
        raise ValueError(f"voxelize: points must be (N, 1 + C>=3), got {tuple(points.shape)}")
    nx, ny, nz = grid.grid_size
    if not bound_z and nz != 1:
        raise ValueError(f"voxelize: bound_z=False needs a pillar grid (1 z cell), got {nz}")
    # spconv's generator (OpenPCDet's data processor) and OpenPCDet's dynamic VFEs compute
    # floor((p - range_min) / voxel_size) in the points' dtype, range and size cast to it: a
    # float32 point within rounding of a cell edge lands in the cell that arithmetic gives
    dtype = points.dtype if points.dtype in (torch.float32, torch.float64) else torch.float32
    pc_min = points.new_tensor(grid.point_cloud_range[:3], dtype=dtype)
    vsize = points.new_tensor(grid.voxel_size, dtype=dtype)
    cell = points[:, 1:4].to(dtype, copy=True).sub_(pc_min).div_(vsize).floor_().long()
    if not bound_z:
        cell[:, 2] = 0
    upper = torch.tensor([nx, ny, nz], device=points.device)
    mask = ((cell >= 0) & (cell < upper)).all(dim=1)  # (N,)
    # linear key of every point (garbage outside the range), then one 1-D selection
    key = (
        points[:, 0].to(torch.int64, copy=True).mul_(nz).add_(cell[:, 2]).mul_(ny).add_(cell[:, 1])
    )
    key = key.mul_(nx).add_(cell[:, 0])[mask]
    num_cells = (int(key.max()) // (nx * ny * nz) + 1) * nx * ny * nz if key.numel() else 0
    if num_cells <= DENSE_KEY_LIMIT:
        # dense path (pillar grids): occupancy counts per cell, no sort; same result as unique
        counts_all = torch.bincount(key, minlength=num_cells)
        unq = torch.nonzero(counts_all).squeeze(1)
        slot = torch.full((num_cells,), -1, dtype=torch.long, device=key.device)
        slot[unq] = torch.arange(unq.numel(), device=key.device)
        inverse, counts = slot[key], counts_all[unq]
    else:
        unq, inverse, counts = torch.unique(key, return_inverse=True, return_counts=True)
    x = unq % nx
    y = (unq // nx) % ny
    z = (unq // (nx * ny)) % nz
    b = unq // (nx * ny * nz)
    coords = torch.stack([b, z, y, x], dim=1)
    return Voxelization(
        point_mask=mask, point_voxel_idx=inverse, voxel_coords=coords, voxel_num_points=counts
    )


def check_voxel_size_placeholder(
    cfg: Mapping, voxel_size: Sequence[float], model_info: Mapping
) -> None:
    """A VFE's ``voxel_size`` (from ``MODEL.VFE`` ``cfg``) must equal the VOXEL_SIZE the data
    processor's ``transform_points_to_voxels_placeholder`` states (``model_info['voxel_size']``,
    when there is one)."""
    data_size = model_info.get("voxel_size")
    if data_size is not None and tuple(float(v) for v in voxel_size) != tuple(data_size):
        raise ConfigError(
            f"MODEL.VFE.VOXEL_SIZE {list(voxel_size)} (from {key_source(cfg, 'VOXEL_SIZE')}) "
            f"differs from the DATA_PROCESSOR placeholder's VOXEL_SIZE {list(data_size)}"
        )


def check_point_columns(points: torch.Tensor, num_point_features: int, owner: str) -> None:
    """A ValueError naming ``owner`` unless ``points`` is ``(N, 1 + num_point_features)``."""
    if points.dim() != 2 or points.shape[1] != 1 + num_point_features:
        raise ValueError(
            f"{owner}: points must be (N, 1 + {num_point_features}) [batch_idx, x, y, z, ...], "
            f"got {tuple(points.shape)}"
        )
