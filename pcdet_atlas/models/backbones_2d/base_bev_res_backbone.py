"""BaseBEVResBackbone (OpenPCDet's, DSVT's BEV backbone): levels of residual basic blocks, each
upsampled to a common stride and concatenated."""

from __future__ import annotations

import torch
from torch import nn

from pcdet_atlas.models.backbones_2d.base_bev_backbone import BaseBEVBackbone, _bn
from pcdet_atlas.registry import MODEL_STAGES


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
class BaseBEVResBackbone(BaseBEVBackbone):
    """Reads ``spatial_features`` (B, C_in, H, W); writes ``spatial_features_2d``
    (B, sum(num_upsample_filters), H / s, W / s). Level ``i`` is a strided projecting block then
    ``layer_nums[i]`` blocks, upsampled by ``upsample_strides[i]`` (transposed conv, BN, ReLU);
    all else as ``BaseBEVBackbone``.
    """

    @staticmethod
    def _level(in_channels: int, channels: int, stride: int, num_layers: int) -> nn.Module:
        layers = [BasicBlock(in_channels, channels, stride, True)]
        layers += [BasicBlock(channels, channels) for _ in range(num_layers)]
        return nn.Sequential(*layers)
