"""CenterFormer's BEV feature pyramid (the convolutional part of its ``RPN_transformer`` neck).

From the 3D backbone's map ``x0``: ``x = blocks[0](x0)`` at the same stride, ``x_down =
blocks[1](x)`` at twice it, and the query map ``x_up = cat(blocks[2](x_down), up(x))`` at
``1 / UPSAMPLE_STRIDE`` of it (both branches transposed convolutions); every block ends in channel
and spatial attention (CBAM). The dense head reads ``x_up`` and the pyramid ``[x_up, x, x_down]``.
"""

from __future__ import annotations

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


class ChannelAttention(nn.Module):
    """Channel gate: a shared two-layer 1x1 MLP (``C / 16`` hidden) on average- and max-pooled
    features, summed, sigmoid."""

    def __init__(self, channels: int, ratio: int = 16):
        super().__init__()
        hidden = max(1, channels // ratio)
        self.fc = nn.Sequential(
            nn.Conv2d(channels, hidden, 1, bias=False), nn.ReLU(),
            nn.Conv2d(hidden, channels, 1, bias=False),
        )  # fmt: skip

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        gate = self.fc(x.mean(dim=(2, 3), keepdim=True)) + self.fc(x.amax(dim=(2, 3), keepdim=True))
        return torch.sigmoid(gate) * x


class SpatialAttention(nn.Module):
    """Spatial gate: a 7x7 conv of the channel mean and max, sigmoid."""

    def __init__(self, kernel_size: int = 7):
        super().__init__()
        self.conv1 = nn.Conv2d(2, 1, kernel_size, padding=kernel_size // 2, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pooled = torch.cat([x.mean(dim=1, keepdim=True), x.amax(dim=1, keepdim=True)], dim=1)
        return torch.sigmoid(self.conv1(pooled)) * x


def _block(cin: int, cout: int, num_layers: int, stride: int, transposed: bool) -> nn.Sequential:
    """First layer (strided conv, or transposed conv upsampling by ``stride``), ``num_layers``
    conv3x3-BN-ReLU, then CBAM."""
    first: nn.Module
    if transposed:
        first = nn.ConvTranspose2d(cin, cout, stride, stride=stride, bias=False)
        layers: list[nn.Module] = [first, _bn(cout), nn.ReLU()]
    else:
        first = nn.Conv2d(cin, cout, 3, stride=stride, bias=False)
        layers = [nn.ZeroPad2d(1), first, _bn(cout), nn.ReLU()]
    for _ in range(num_layers):
        layers += [nn.Conv2d(cout, cout, 3, padding=1, bias=False), _bn(cout), nn.ReLU()]
    layers += [ChannelAttention(cout), SpatialAttention()]
    return nn.Sequential(*layers)


@dataclass(frozen=True, kw_only=True)
class CenterFormerBEVBackboneConfig(StageConfig):
    """``MODEL.BACKBONE_2D`` of CenterFormerBEVBackbone."""

    layer_nums: tuple[int, ...] = setting(ge=0, doc="convs per block")
    num_filters: tuple[int, ...] = setting(ge=1, doc="width per block")
    upsample_stride: int = setting(2, ge=1, doc="upsampling of the query map")


@MODEL_STAGES.register()
class CenterFormerBEVBackbone(nn.Module):
    """Reads ``spatial_features`` (B, C_in, H, W); writes ``spatial_features_2d`` (B, 2 * F2,
    U * H, U * W), the query map, and ``multi_scale_features_2d``, the pyramid ``[x_up, x (B, F0,
    H, W), x_down (B, F1, H / 2, W / 2)]``; the cross-attention reads all three with one
    projection, so ``F0 = F1 = 2 * F2`` (CenterFormer's 256, 256, 128)."""

    CONFIG = CenterFormerBEVBackboneConfig

    def __init__(
        self,
        *,
        input_channels: int,
        layer_nums: Sequence[int],
        num_filters: Sequence[int],
        upsample_stride: int = CenterFormerBEVBackboneConfig.upsample_stride,
    ):
        """
        Args:
            input_channels: C_in of ``spatial_features``.
            layer_nums: conv layers after the first of blocks 0, 1, 2.
            num_filters: F0, F1, F2: widths of ``x``, ``x_down`` and each half of ``x_up``.
            upsample_stride: U, query-map cells per cell of ``x`` along x and y (2 released).
        """
        super().__init__()
        if len(layer_nums) != 3 or len(num_filters) != 3:
            raise ValueError(
                f"CenterFormerBEVBackbone: LAYER_NUMS and NUM_FILTERS need 3 entries (blocks 0, 1, "
                f"2), got {list(layer_nums)} and {list(num_filters)}"
            )
        if int(upsample_stride) < 1:
            raise ValueError(f"UPSAMPLE_STRIDE must be >= 1, got {upsample_stride}")
        f0, f1, f2 = (int(f) for f in num_filters)
        if not f0 == f1 == 2 * f2:
            raise ValueError(
                f"CenterFormerBEVBackbone: NUM_FILTERS {list(num_filters)} must be [2 F, 2 F, F] "
                "(the pyramid's three levels share one width, 2 F, for the cross-attention)"
            )
        u = int(upsample_stride)
        self.blocks = nn.ModuleList([
            _block(input_channels, f0, int(layer_nums[0]), 1, transposed=False),
            _block(f0, f1, int(layer_nums[1]), 2, transposed=False),
            _block(f1, f2, int(layer_nums[2]), 2 * u, transposed=True),
        ])  # fmt: skip
        self.up = nn.Sequential(
            nn.ConvTranspose2d(f0, f2, u, stride=u, bias=False), _bn(f2), nn.ReLU()
        )
        self.output_stride = 1.0 / u
        self.num_bev_features = 2 * f2

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> CenterFormerBEVBackbone:
        settings = read_stage(cls, cfg, "MODEL.BACKBONE_2D")
        grid = model_info.get("grid_size")
        before = int(model_info.get("backbone_stride", 1))
        if grid is not None and ((grid[0] // before) % 2 or (grid[1] // before) % 2):
            raise ConfigError(
                f"MODEL.BACKBONE_2D: the BEV map {(grid[0] // before, grid[1] // before)} must "
                "have even sides (CenterFormerBEVBackbone halves it once)"
            )
        return cls(
            input_channels=model_info["num_bev_features"],
            layer_nums=as_lists(settings.layer_nums),
            num_filters=as_lists(settings.num_filters),
            upsample_stride=settings.upsample_stride,
        )

    def forward(self, batch_dict: dict) -> dict:
        x = self.blocks[0](batch_dict["spatial_features"])  # (B, F0, H, W)
        x_down = self.blocks[1](x)  # (B, F1, H / 2, W / 2)
        x_up = torch.cat([self.blocks[2](x_down), self.up(x)], dim=1)  # (B, 2 F2, U H, U W)
        batch_dict["spatial_features_2d"] = x_up
        batch_dict["multi_scale_features_2d"] = [x_up, x, x_down]
        return batch_dict
