"""Polar voxel feature encoder of PHiM: points -> one feature per (height, azimuth, range) cell.

Dynamic polar voxelization in torch (:func:`polar_voxelize`, no point or voxel cap), every point
decorated with its range, its offset from the voxel's point mean and its offset from the cell
centre in metres along range, arc and height, then PointNet layers whose per-voxel max is a
scatter (:class:`~pcdet_atlas.models.vfe.dynamic_pillar_vfe.PFNLayer`, as the pillar VFE).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import nn

from pcdet_atlas.config_values import setting
from pcdet_atlas.models.model_utils.polar_grid import PolarGrid, polar_coordinates, polar_voxelize
from pcdet_atlas.models.model_utils.scatter import scatter_mean
from pcdet_atlas.models.model_utils.voxelize import check_point_columns
from pcdet_atlas.models.stage_config import StageConfig, read_stage
from pcdet_atlas.models.vfe.dynamic_pillar_vfe import PFNLayer
from pcdet_atlas.registry import MODEL_STAGES

__all__ = ["PolarVFE"]


@dataclass(frozen=True, kw_only=True)
class PolarVFEConfig(StageConfig):
    """``MODEL.VFE`` of PolarVFE."""

    range_m: tuple[float, float] = setting(
        ge=0,
        check=lambda r: r[0] < r[1],
        expected="[r_min, r_max] with 0 <= r_min < r_max",
        doc="radial range, m",
    )
    grid_size: tuple[int, ...] = setting(ge=1, doc="polar grid cells")
    num_sectors: int = setting(ge=1, doc="azimuth sectors")
    origin_xy: tuple[float, float] = setting((0.0, 0.0), doc="polar origin, m")
    num_filters: tuple[int, ...] = setting((32, 32), ge=1, doc="widths of the PFN layers")
    use_norm: bool = setting(True, doc="BatchNorm in the PFN layers")


@MODEL_STAGES.register()
class PolarVFE(nn.Module):
    """Points -> polar voxel features.

    Reads ``points`` (N, 1 + C); writes ``voxel_features`` (V, F), ``voxel_coords`` (V, 4)
    ``[b, z, azimuth, range]``, and for the stages that go back to points ``voxel_point_idx``
    (N_in,) (the voxel of every point inside the grid) and ``voxel_point_xy`` (N_in, 2).
    """

    CONFIG = PolarVFEConfig

    def __init__(
        self,
        *,
        num_point_features: int,
        grid: PolarGrid,
        num_filters: Sequence[int] = (32, 32),
        use_norm: bool = True,
    ):
        """
        Args:
            num_point_features: C, point columns after the batch index (x, y, z first).
            grid: the polar grid (its sectors are the backbone's).
            num_filters: output widths of the PFN layers.
        """
        super().__init__()
        if num_point_features < 3:
            raise ValueError(f"num_point_features must be >= 3, got {num_point_features}")
        if not num_filters:
            raise ValueError("PolarVFE: NUM_FILTERS must not be empty")
        self.grid = grid
        self.num_point_features = num_point_features
        widths = [num_point_features + 7, *num_filters]  # + range, mean offset, centre offset
        self.pfn_layers = nn.ModuleList(
            PFNLayer(widths[i], widths[i + 1], use_norm, last_layer=i == len(widths) - 2)
            for i in range(len(widths) - 1)
        )
        self.num_output_features = widths[-1]

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> PolarVFE:
        settings = read_stage(cls, cfg, "MODEL.VFE")
        pcr = model_info["point_cloud_range"]
        grid = PolarGrid(
            range_m=settings.range_m,
            z_range_m=(float(pcr[2]), float(pcr[5])),
            grid_size=settings.grid_size,
            num_sectors=settings.num_sectors,
            origin_xy=settings.origin_xy,
        )
        return cls(
            num_point_features=model_info["num_point_features"],
            grid=grid,
            num_filters=settings.num_filters,
            use_norm=settings.use_norm,
        )

    def get_output_feature_dim(self) -> int:
        return self.num_output_features

    def forward(self, batch_dict: dict) -> dict:
        points = batch_dict["points"]  # (N, 1 + C)
        check_point_columns(points, self.num_point_features, "PolarVFE")
        vox = polar_voxelize(points, self.grid)
        pts = points[vox.point_mask, 1:].float()  # (N_in, C)
        idx, coords = vox.point_voxel_idx, vox.voxel_coords
        num_voxels = coords.shape[0]
        polar = polar_coordinates(pts[:, :3], self.grid.origin_xy).to(
            pts.dtype
        )  # (N_in, 3) r, theta, z
        mean = scatter_mean(pts[:, :3], idx, num_voxels, vox.voxel_num_points)  # (V, 3)
        centre = self.grid.cell_centres(coords).to(pts.dtype).index_select(0, idx)  # (N_in, 3)
        dtheta = torch.remainder(polar[:, 1] - centre[:, 1] + torch.pi, 2 * torch.pi) - torch.pi
        x = torch.cat(
            [
                pts,
                polar[:, :1],
                pts[:, :3] - mean.index_select(0, idx),
                torch.stack(
                    [polar[:, 0] - centre[:, 0], dtheta * polar[:, 0], polar[:, 2] - centre[:, 2]],
                    dim=1,
                ),
            ],
            dim=1,
        )  # (N_in, C + 7)
        for layer in self.pfn_layers:
            x = layer(x, idx, num_voxels)
        batch_dict["voxel_features"] = x  # (V, F)
        batch_dict["voxel_coords"] = coords  # (V, 4) b, z, a, r
        batch_dict["voxel_point_idx"] = idx  # (N_in,)
        batch_dict["voxel_point_xy"] = pts[:, :2]  # (N_in, 2)
        return batch_dict
