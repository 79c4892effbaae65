"""HeightCompression (OpenPCDet's): the 3D backbone's stride-8 sparse tensor -> BEV map, the z
layers stacked into channels."""

from __future__ import annotations

from collections.abc import Mapping

from torch import nn

from pcdet_atlas.config import check_known_keys, require_keys
from pcdet_atlas.registry import MODEL_STAGES


@MODEL_STAGES.register()
class HeightCompression(nn.Module):
    """Reads ``encoded_spconv_tensor`` (a ``SparseConvTensor`` of ``(B, C, D, H, W)``); writes
    ``spatial_features`` (B, C * D, H, W) and ``spatial_features_stride``."""

    def __init__(self, *, num_bev_features: int):
        super().__init__()
        self.num_bev_features = num_bev_features

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> HeightCompression:
        check_known_keys(cfg, ["NAME", "NUM_BEV_FEATURES"], "MODEL.MAP_TO_BEV")
        require_keys(cfg, ["NUM_BEV_FEATURES"], "MODEL.MAP_TO_BEV")
        return cls(num_bev_features=int(cfg["NUM_BEV_FEATURES"]))

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
