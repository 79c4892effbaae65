"""HeightCompression (OpenPCDet's): the 3D backbone's stride-8 sparse tensor -> BEV map, the z
layers stacked into channels."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from torch import nn

from pcdet_atlas.config_values import setting
from pcdet_atlas.models.stage_config import StageConfig, read_stage
from pcdet_atlas.registry import MODEL_STAGES


@dataclass(frozen=True, kw_only=True)
class HeightCompressionConfig(StageConfig):
    num_bev_features: int = setting(ge=1, doc="C * D of the 3D backbone's output")


@MODEL_STAGES.register()
class HeightCompression(nn.Module):
    """Reads ``encoded_spconv_tensor`` (a ``SparseConvTensor`` of ``(B, C, D, H, W)``); writes
    ``spatial_features`` (B, C * D, H, W) and ``spatial_features_stride``."""

    CONFIG = HeightCompressionConfig

    def __init__(self, *, num_bev_features: int):
        super().__init__()
        self.num_bev_features = num_bev_features

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> HeightCompression:
        settings = read_stage(cls, cfg, "MODEL.MAP_TO_BEV")
        return cls(num_bev_features=settings.num_bev_features)

    def forward(self, batch_dict: dict) -> dict:
        encoded = batch_dict["encoded_spconv_tensor"]
        dense = encoded.dense()  # (B, C, D, H, W)
        b, c, d, h, w = dense.shape
        if c * d != self.num_bev_features:
            raise ValueError(
                f"HeightCompression: the 3D backbone gives C * D = {c} * {d} = {c * d} BEV "
                f"channels, MAP_TO_BEV.NUM_BEV_FEATURES is {self.num_bev_features}"
            )
        batch_dict["spatial_features"] = dense.view(b, c * d, h, w)
        batch_dict["spatial_features_stride"] = batch_dict["encoded_spconv_tensor_stride"]
        return batch_dict
