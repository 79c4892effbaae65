"""PointPillarScatter: pillar features -> dense BEV feature map."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from torch import nn

from pcdet_atlas.config_values import setting
from pcdet_atlas.models.stage_config import StageConfig, read_stage
from pcdet_atlas.registry import MODEL_STAGES


@dataclass(frozen=True, kw_only=True)
class PointPillarScatterConfig(StageConfig):
    num_bev_features: int | None = setting(None, ge=1, doc="the VFE's output width")


@MODEL_STAGES.register()
class PointPillarScatter(nn.Module):
    """Reads ``pillar_features`` (P, C) and ``voxel_coords`` (P, 4) ``[b, z, y, x]``; writes
    ``spatial_features`` (B, C, ny, nx) with zeros where there is no pillar."""

    CONFIG = PointPillarScatterConfig

    def __init__(self, *, num_bev_features: int, grid_size: tuple[int, int, int]):
        super().__init__()
        if grid_size[2] != 1:
            raise ValueError(f"PointPillarScatter needs a pillar grid (nz == 1), got {grid_size}")
        self.num_bev_features = num_bev_features
        self.nx, self.ny = int(grid_size[0]), int(grid_size[1])

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> PointPillarScatter:
        settings = read_stage(cls, cfg, "MODEL.MAP_TO_BEV")
        num = settings.num_bev_features
        num = model_info["num_point_features"] if num is None else num
        if num != model_info["num_point_features"]:
            raise ValueError(
                f"MODEL.MAP_TO_BEV.NUM_BEV_FEATURES ({num}) must equal the VFE output width "
                f"({model_info['num_point_features']})"
            )
        return cls(num_bev_features=num, grid_size=model_info["grid_size"])

    def forward(self, batch_dict: dict) -> dict:
        feats = batch_dict["pillar_features"]  # (P, C)
        coords = batch_dict["voxel_coords"]  # (P, 4)
        B = int(batch_dict["batch_size"])
        flat = (coords[:, 0] * self.ny + coords[:, 2]) * self.nx + coords[:, 3]  # (P,)
        canvas = feats.new_zeros(B * self.ny * self.nx, self.num_bev_features)
        canvas = canvas.index_put((flat,), feats)  # pillar keys are unique
        batch_dict["spatial_features"] = (
            canvas.view(B, self.ny, self.nx, -1).permute(0, 3, 1, 2).contiguous()
        )  # (B, C, ny, nx)
        return batch_dict
