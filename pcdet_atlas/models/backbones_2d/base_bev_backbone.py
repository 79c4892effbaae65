"""BaseBEVBackbone: multi-scale conv blocks, each upsampled to a common stride and concatenated."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import nn

from pcdet_atlas.config import ConfigError
from pcdet_atlas.config_values import as_lists, setting
from pcdet_atlas.models.stage_config import StageConfig, read_stage
from pcdet_atlas.registry import MODEL_STAGES


def _bn(channels: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(channels, eps=1e-3, momentum=0.01)


@dataclass(frozen=True, kw_only=True)
class BEVBackboneConfig(StageConfig):
    """``MODEL.BACKBONE_2D`` of the BEV backbones (OpenPCDet's keys)."""

    layer_nums: tuple[int, ...] = setting(ge=0, doc="convs per level")
    layer_strides: tuple[int, ...] = setting(ge=1, doc="stride of each level")
    num_filters: tuple[int, ...] = setting(ge=1, doc="width of each level")
    upsample_strides: tuple[float, ...] = setting(gt=0, doc="upsampling of each level")
    num_upsample_filters: tuple[int, ...] = setting(ge=1, doc="width of each upsampled level")


@MODEL_STAGES.register()
class BaseBEVBackbone(nn.Module):
    """Reads ``spatial_features`` (B, C_in, H, W); writes ``spatial_features_2d``
    (B, sum(num_upsample_filters), H / s, W / s), ``s = layer_strides[0] / upsample_strides[0]``.
    """

    CONFIG = BEVBackboneConfig

    def __init__(
        self,
        *,
        input_channels: int,
        layer_nums: Sequence[int],
        layer_strides: Sequence[int],
        num_filters: Sequence[int],
        upsample_strides: Sequence[float],
        num_upsample_filters: Sequence[int],
    ):
        super().__init__()
        n = len(layer_nums)
        if not (len(layer_strides) == len(num_filters) == n):
            raise ValueError("LAYER_NUMS, LAYER_STRIDES and NUM_FILTERS must have equal lengths")
        if len(upsample_strides) != len(num_upsample_filters) or len(upsample_strides) != n:
            raise ValueError("UPSAMPLE_STRIDES and NUM_UPSAMPLE_FILTERS need one entry per level")
        in_channels = [input_channels, *num_filters[:-1]]
        self.blocks = nn.ModuleList()
        self.deblocks = nn.ModuleList()
        total_stride = 1
        out_strides = []
        for i in range(n):
            self.blocks.append(
                self._level(in_channels[i], num_filters[i], layer_strides[i], layer_nums[i])
            )
            total_stride *= layer_strides[i]
            up = upsample_strides[i]
            if up >= 1:
                up = int(round(up))
                deconv: nn.Module = nn.ConvTranspose2d(
                    num_filters[i], num_upsample_filters[i], up, stride=up, bias=False
                )
            else:
                down = int(round(1 / up))
                deconv = nn.Conv2d(
                    num_filters[i], num_upsample_filters[i], down, stride=down, bias=False
                )
            self.deblocks.append(nn.Sequential(deconv, _bn(num_upsample_filters[i]), nn.ReLU()))
            out_strides.append(total_stride / upsample_strides[i])
        if len(set(out_strides)) != 1:
            raise ValueError(
                f"{type(self).__name__}: levels end at different strides {out_strides}; "
                "choose UPSAMPLE_STRIDES so that all levels meet at one stride"
            )
        self.output_stride = out_strides[0]
        self.num_bev_features = int(sum(num_upsample_filters))

    @staticmethod
    def _level(in_channels: int, channels: int, stride: int, num_layers: int) -> nn.Module:
        """One level: a strided 3x3 conv then ``num_layers`` 3x3 convs, each with BN and ReLU."""
        layers: list[nn.Module] = [
            nn.ZeroPad2d(1),
            nn.Conv2d(in_channels, channels, 3, stride=stride, bias=False),
            _bn(channels),
            nn.ReLU(),
        ]
        for _ in range(num_layers):
            layers += [
                nn.Conv2d(channels, channels, 3, padding=1, bias=False),
                _bn(channels),
                nn.ReLU(),
            ]
        return nn.Sequential(*layers)

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> BaseBEVBackbone:
        settings = read_stage(cls, cfg, "MODEL.BACKBONE_2D")
        total = math.prod(settings.layer_strides)
        grid = model_info.get("grid_size")
        # the map this backbone sees: the voxel grid, or what a 3D backbone's stride leaves of it
        before = int(model_info.get("backbone_stride", 1))
        if grid is not None and ((grid[0] // before) % total or (grid[1] // before) % total):
            seen = (grid[0] // before, grid[1] // before)
            raise ConfigError(
                f"MODEL.BACKBONE_2D.LAYER_STRIDES (product {total}) must divide the BEV map "
                f"{seen} (POINT_CLOUD_RANGE / VOXEL_SIZE"
                + (f" / the 3D backbone's stride {before}" if before > 1 else "")
                + "), or the levels misalign"
            )
        return cls(
            input_channels=model_info["num_bev_features"],
            layer_nums=as_lists(settings.layer_nums),
            layer_strides=as_lists(settings.layer_strides),
            num_filters=as_lists(settings.num_filters),
            upsample_strides=as_lists(settings.upsample_strides),
            num_upsample_filters=as_lists(settings.num_upsample_filters),
        )

    def forward(self, batch_dict: dict) -> dict:
        x = batch_dict["spatial_features"]  # (B, C, H, W)
        ups = []
        for block, deblock in zip(self.blocks, self.deblocks):
            x = block(x)
            ups.append(deblock(x))
        batch_dict["spatial_features_2d"] = torch.cat(ups, dim=1) if len(ups) > 1 else ups[0]
        return batch_dict
