"""BaseBEVResBackbone (OpenPCDet's, DSVT's BEV backbone): levels of residual basic blocks, each
upsampled to a common stride and concatenated."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch
from torch import nn

from pcdet_atlas.config import ConfigError
from pcdet_atlas.config_values import as_lists
from pcdet_atlas.models.backbones_2d.base_bev_backbone import BEVBackboneConfig
from pcdet_atlas.models.stage_config import read_stage
from pcdet_atlas.registry import MODEL_STAGES


def _bn(channels: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(channels, eps=1e-3, momentum=0.01)


class BasicBlock(nn.Module):
    """ResNet's basic block: two 3x3 convs with BN, a 1x1 projection on the shortcut when the
    block changes width or stride (``downsample``)."""

    def __init__(self, inplanes: int, planes: int, stride: int = 1, downsample: bool = False):
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 3, stride=stride, padding=1, bias=False)
        self.bn1 = _bn(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, padding=1, bias=False)
        self.bn2 = _bn(planes)
        self.downsample = downsample
        if downsample:
            self.downsample_layer = nn.Sequential(
                nn.Conv2d(inplanes, planes, 1, stride=stride, bias=False), _bn(planes)
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.bn2(self.conv2(torch.relu(self.bn1(self.conv1(x)))))
        identity = self.downsample_layer(x) if self.downsample else x
        return torch.relu(out + identity)


@MODEL_STAGES.register()
class BaseBEVResBackbone(nn.Module):
    """Reads ``spatial_features`` (B, C_in, H, W); writes ``spatial_features_2d``
    (B, sum(num_upsample_filters), H / s, W / s). Level ``i`` is a strided projecting block then
    ``layer_nums[i]`` blocks, upsampled by ``upsample_strides[i]`` (transposed conv, BN, ReLU).
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
        total, out_strides = 1, []
        for i in range(n):
            layers = [BasicBlock(in_channels[i], num_filters[i], layer_strides[i], True)]
            layers += [BasicBlock(num_filters[i], num_filters[i]) for _ in range(layer_nums[i])]
            self.blocks.append(nn.Sequential(*layers))
            total *= layer_strides[i]
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
            out_strides.append(total / upsample_strides[i])
        if len(set(out_strides)) != 1:
            raise ValueError(
                f"BaseBEVResBackbone: levels end at different strides {out_strides}; "
                "choose UPSAMPLE_STRIDES so that all levels meet at one stride"
            )
        self.output_stride = out_strides[0]
        self.num_bev_features = int(sum(num_upsample_filters))

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> BaseBEVResBackbone:
        settings = read_stage(cls, cfg, "MODEL.BACKBONE_2D")
        total = math.prod(settings.layer_strides)
        grid = model_info.get("grid_size")
        before = int(model_info.get("backbone_stride", 1))
        if grid is not None and ((grid[0] // before) % total or (grid[1] // before) % total):
            raise ConfigError(
                f"MODEL.BACKBONE_2D.LAYER_STRIDES (product {total}) must divide the BEV map "
                f"{(grid[0] // before, grid[1] // before)}, or the levels misalign"
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
