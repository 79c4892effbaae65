"""PHiM's sector feature buffer: the polar voxel features of a frame's sectors gathered into the
Cartesian BEV map that the full-scan branch (a BEV backbone and the CenterHead) reads.

Every point inside the polar grid carries its voxel's feature to the Cartesian cell it falls in,
and a cell keeps the per-channel maximum (a cell is empty, zero, where no point fell). Going
through the points rather than the voxel centres keeps the map dense at long range, where one
azimuth bin is wider than a BEV cell.

With ``POINT_OFFSETS`` a point also carries where it lies inside its BEV cell (its x and y offset
from the cell centre, in cells): every point of one polar voxel otherwise brings the same
feature to each cell it reaches, so a cell cannot tell where in it the object's points are, and
on a polar voxel wider than the cell the centre regression has nothing finer than the voxel to
go on.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import nn

from pcdet_atlas.config_values import setting
from pcdet_atlas.models.model_utils.scatter import scatter_max
from pcdet_atlas.models.model_utils.voxelize import VoxelGrid
from pcdet_atlas.models.stage_config import StageConfig, read_stage
from pcdet_atlas.registry import MODEL_STAGES

__all__ = ["SectorFeatureBuffer"]


@dataclass(frozen=True, kw_only=True)
class SectorFeatureBufferConfig(StageConfig):
    num_bev_features: int = setting(ge=1, doc="BEV channels")
    bev_cell_m: tuple[float, float] = setting(gt=0, doc="BEV cell size [x, y], m")
    point_offsets: bool = setting(
        default=False, doc="append each point's offset from its BEV cell centre to its feature"
    )


@MODEL_STAGES.register()
class SectorFeatureBuffer(nn.Module):
    """Reads ``voxel_features`` (V, C), ``voxel_coords`` (V, 4), ``voxel_point_idx`` (N_in,),
    ``voxel_point_xy`` (N_in, 2) and ``batch_size``; writes ``spatial_features`` (B, C, ny, nx)
    over :attr:`bev_grid`, features as the BEV backbone expects them (Linear, BN, ReLU)."""

    CONFIG = SectorFeatureBufferConfig

    def __init__(
        self,
        *,
        input_channels: int,
        num_bev_features: int,
        point_cloud_range: Sequence[float],
        bev_cell_m: Sequence[float],
        point_offsets: bool = False,
    ):
        super().__init__()
        pcr = tuple(float(v) for v in point_cloud_range)
        self.bev_grid = VoxelGrid(
            pcr, (float(bev_cell_m[0]), float(bev_cell_m[1]), pcr[5] - pcr[2])
        )
        self.num_bev_features = num_bev_features
        self.point_offsets = bool(point_offsets)
        self.proj = nn.Sequential(
            nn.Linear(input_channels + 2 * self.point_offsets, num_bev_features, bias=False),
            nn.BatchNorm1d(num_bev_features, eps=1e-3, momentum=0.01),
            nn.ReLU(),
        )

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> SectorFeatureBuffer:
        settings = read_stage(cls, cfg, "MODEL.MAP_TO_BEV")
        return cls(
            input_channels=model_info["num_point_features"],
            num_bev_features=settings.num_bev_features,
            point_cloud_range=model_info["point_cloud_range"],
            bev_cell_m=settings.bev_cell_m,
            point_offsets=settings.point_offsets,
        )

    def forward(self, batch_dict: dict) -> dict:
        idx = batch_dict["voxel_point_idx"]  # (N_in,)
        xy = batch_dict["voxel_point_xy"]  # (N_in, 2)
        B = int(batch_dict["batch_size"])
        nx, ny, _ = self.bev_grid.grid_size
        pcr, vs = self.bev_grid.point_cloud_range, self.bev_grid.voxel_size
        fx = (xy[:, 0].double() - pcr[0]) / vs[0]
        fy = (xy[:, 1].double() - pcr[1]) / vs[1]
        ix, iy = torch.floor(fx).long(), torch.floor(fy).long()
        inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        b = batch_dict["voxel_coords"][:, 0].index_select(0, idx)
        key = ((b * ny + iy) * nx + ix)[inside]  # (N_bev,)
        voxel_features = batch_dict["voxel_features"]
        if self.point_offsets:  # project per point: (N_bev, C + 2) -> (N_bev, C_bev) >= 0
            offsets = torch.stack((fx - ix - 0.5, fy - iy - 0.5), dim=1)[inside]
            point_in = torch.cat(
                (voxel_features.index_select(0, idx[inside]), offsets.to(voxel_features.dtype)),
                dim=1,
            )
            point_features = self.proj(point_in)
        else:  # project per voxel, then hand the feature to its points: (N_bev, C_bev) >= 0
            point_features = self.proj(voxel_features).index_select(0, idx[inside])
        canvas = scatter_max(point_features, key, B * ny * nx)
        batch_dict["spatial_features"] = (
            canvas.view(B, ny, nx, -1).permute(0, 3, 1, 2).contiguous()
        )  # (B, C, ny, nx)
        return batch_dict
