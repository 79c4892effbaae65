"""PointPillarScatter3d (OpenPCDet's name): voxel features on a ``(nx, ny, nz)`` grid -> a dense
BEV map with the z layers stacked into channels (DSVT's output has one layer)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from torch import nn

from pcdet_atlas.config_values import setting
from pcdet_atlas.models.stage_config import StageConfig, read_stage
from pcdet_atlas.registry import MODEL_STAGES


@dataclass(frozen=True, kw_only=True)
class PointPillarScatter3dConfig(StageConfig):
    input_shape: tuple[int, int, int] = setting(ge=1, doc="[nx, ny, nz] of the sparse grid")
    num_bev_features: int = setting(ge=1, doc="the 3D backbone's width x nz")


@MODEL_STAGES.register()
class PointPillarScatter3d(nn.Module):
    """Reads ``pillar_features`` (P, C) and ``voxel_coords`` (P, 4) ``[b, z, y, x]``; writes
    ``spatial_features`` (B, C * nz, ny, nx), feature ``c`` of layer ``z`` in channel
    ``c * nz + z`` (OpenPCDet's order), zeros where there is no voxel."""

    CONFIG = PointPillarScatter3dConfig

    def __init__(self, *, input_shape: Sequence[int], num_bev_features: int):
        super().__init__()
        self.nx, self.ny, self.nz = (int(v) for v in input_shape)
        if num_bev_features % self.nz:
            raise ValueError(
                f"PointPillarScatter3d: NUM_BEV_FEATURES ({num_bev_features}) must be a multiple "
                f"of the z layers of INPUT_SHAPE ({self.nz})"
            )
        self.num_bev_features = int(num_bev_features)
        self.num_bev_features_before_compression = self.num_bev_features // self.nz

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> PointPillarScatter3d:
        settings = read_stage(cls, cfg, "MODEL.MAP_TO_BEV")
        nx, ny, nz = settings.input_shape
        grid = model_info["grid_size"]
        stride = int(model_info.get("backbone_stride", 1))
        if (nx, ny) != (grid[0] // stride, grid[1] // stride):
            raise ValueError(
                f"MODEL.MAP_TO_BEV.INPUT_SHAPE {[nx, ny, nz]}: the 3D backbone leaves a "
                f"{grid[0] // stride} x {grid[1] // stride} grid (the VFE's grid / its stride)"
            )
        if settings.num_bev_features != model_info["num_point_features"] * nz:
            raise ValueError(
                f"MODEL.MAP_TO_BEV.NUM_BEV_FEATURES ({settings.num_bev_features}) must be the "
                f"3D backbone's width ({model_info['num_point_features']}) x {nz} z layers"
            )
        return cls(input_shape=(nx, ny, nz), num_bev_features=settings.num_bev_features)

    def forward(self, batch_dict: dict) -> dict:
        feats = batch_dict["pillar_features"]  # (P, C)
        coords = batch_dict["voxel_coords"].long()  # (P, 4)
        B = int(batch_dict["batch_size"])
        c = self.num_bev_features_before_compression
        flat = ((coords[:, 0] * self.nz + coords[:, 1]) * self.ny + coords[:, 2]) * self.nx
        flat = flat + coords[:, 3]  # (P,)
        canvas = feats.new_zeros(B * self.nz * self.ny * self.nx, c)
        canvas = canvas.index_put((flat,), feats)  # voxel keys are unique
        canvas = canvas.view(B, self.nz, self.ny, self.nx, c).permute(0, 4, 1, 2, 3)
        # (B, C, nz, ny, nx) -> (B, C * nz, ny, nx), OpenPCDet's channel order c * nz + z
        batch_dict["spatial_features"] = canvas.reshape(B, c * self.nz, self.ny, self.nx)
        return batch_dict
