"""PointPillarScatter3d (OpenPCDet's name): voxel features on a ``(nx, ny, nz)`` grid -> a dense
BEV map with the z layers stacked into channels (DSVT's output has one layer)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from torch import nn

from pcdet_atlas.config import check_known_keys, require_keys
from pcdet_atlas.registry import MODEL_STAGES


@MODEL_STAGES.register()
class PointPillarScatter3d(nn.Module):
    """Reads ``pillar_features`` (P, C) and ``voxel_coords`` (P, 4) ``[b, z, y, x]``; writes
    ``spatial_features`` (B, C * nz, ny, nx), feature ``c`` of layer ``z`` in channel
    ``c * nz + z`` (OpenPCDet's order), zeros where there is no voxel."""

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
        check_known_keys(cfg, ["NAME", "INPUT_SHAPE", "NUM_BEV_FEATURES"], "MODEL.MAP_TO_BEV")
        require_keys(cfg, ["INPUT_SHAPE", "NUM_BEV_FEATURES"], "MODEL.MAP_TO_BEV")
        nx, ny, nz = (int(v) for v in cfg["INPUT_SHAPE"])
        grid = model_info["grid_size"]
        stride = int(model_info.get("backbone_stride", 1))
        if (nx, ny) != (grid[0] // stride, grid[1] // stride):
            raise ValueError(
                f"MODEL.MAP_TO_BEV.INPUT_SHAPE {[nx, ny, nz]}: the 3D backbone leaves a "
                f"{grid[0] // stride} x {grid[1] // stride} grid (the VFE's grid / its stride)"
            )
        if cfg["NUM_BEV_FEATURES"] != model_info["num_point_features"] * nz:
            raise ValueError(
                f"MODEL.MAP_TO_BEV.NUM_BEV_FEATURES ({cfg['NUM_BEV_FEATURES']}) must be the "
                f"3D backbone's width ({model_info['num_point_features']}) x {nz} z layers"
            )
        return cls(input_shape=(nx, ny, nz), num_bev_features=cfg["NUM_BEV_FEATURES"])

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
