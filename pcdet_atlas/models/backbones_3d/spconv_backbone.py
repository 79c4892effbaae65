"""OpenPCDet's sparse voxel backbones on the pure-torch sparse conv (:mod:`pcdet_atlas.ops.spconv`).

Module and parameter names, shapes and ``indice_key`` reuse are OpenPCDet's, so its
``backbone_3d.*`` checkpoint entries (spconv 2.x layout) load unchanged (docs/model_zoo.md).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import partial

from torch import nn

from pcdet_atlas.config_values import setting
from pcdet_atlas.models.stage_config import StageConfig, read_stage
from pcdet_atlas.ops.spconv import (
    SparseConv3d,
    SparseConvTensor,
    SparseModule,
    SparseSequential,
    SubMConv3d,
)
from pcdet_atlas.registry import MODEL_STAGES

# OpenPCDet's norm for the sparse backbones
norm_fn = partial(nn.BatchNorm1d, eps=1e-3, momentum=0.01)


def post_act_block(
    in_channels: int,
    out_channels: int,
    kernel_size: int,
    indice_key: str,
    stride: int = 1,
    padding: int | Sequence[int] = 0,
    conv_type: str = "subm",
) -> SparseSequential:
    """conv -> BN -> ReLU (``subm`` or ``spconv``), numbered ``0, 1, 2`` as in OpenPCDet."""
    if conv_type == "subm":
        conv = SubMConv3d(in_channels, out_channels, kernel_size, bias=False, indice_key=indice_key)
    elif conv_type == "spconv":
        conv = SparseConv3d(
            in_channels, out_channels, kernel_size, stride=stride, padding=padding, bias=False,
            indice_key=indice_key,
        )  # fmt: skip
    else:
        raise ValueError(f"post_act_block: conv_type must be 'subm' or 'spconv', got {conv_type!r}")
    return SparseSequential(conv, norm_fn(out_channels), nn.ReLU())


class SparseBasicBlock(SparseModule):
    """Residual block of two submanifold 3x3x3 convs (with bias, as OpenPCDet) and BN."""

    expansion = 1

    def __init__(self, inplanes: int, planes: int, indice_key: str):
        super().__init__()
        self.conv1 = SubMConv3d(inplanes, planes, 3, padding=1, bias=True, indice_key=indice_key)
        self.bn1 = norm_fn(planes)
        self.relu = nn.ReLU()
        self.conv2 = SubMConv3d(planes, planes, 3, padding=1, bias=True, indice_key=indice_key)
        self.bn2 = norm_fn(planes)

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        out = self.conv1(x)
        out = out.replace_feature(self.relu(self.bn1(out.features)))
        out = self.conv2(out)
        out = out.replace_feature(self.bn2(out.features))
        return out.replace_feature(self.relu(out.features + x.features))


@dataclass(frozen=True, kw_only=True)
class VoxelBackBoneConfig(StageConfig):
    """``MODEL.BACKBONE_3D`` of the 8x voxel backbones."""

    last_pad: int = setting(0, key="last_pad", ge=0, doc="padding of conv_out")


class _VoxelBackBone(nn.Module):
    """Shared input / output of the 8x backbones; subclasses build ``conv_input`` .. ``conv_out``.

    Reads ``voxel_features`` (V, C) and ``voxel_coords`` (V, 4) ``[b, z, y, x]``; writes
    ``encoded_spconv_tensor`` (stride 8), ``encoded_spconv_tensor_stride`` and
    ``multi_scale_3d_features`` / ``multi_scale_3d_strides`` (``x_conv1`` .. ``x_conv4``).
    """

    CONFIG = VoxelBackBoneConfig

    def __init__(self, *, input_channels: int, grid_size: Sequence[int]):
        super().__init__()
        nx, ny, nz = (int(v) for v in grid_size)
        # OpenPCDet's sparse shape: grid_size[::-1] + [1, 0, 0] (one extra z layer)
        self.sparse_shape = [nz + 1, ny, nx]
        self.input_channels = input_channels
        #: voxels per BEV cell of ``encoded_spconv_tensor`` along x and y
        self.output_stride = 8

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> _VoxelBackBone:
        settings = read_stage(cls, cfg, "MODEL.BACKBONE_3D")
        return cls(
            input_channels=model_info["num_point_features"],
            grid_size=model_info["grid_size"],
            last_pad=settings.last_pad,
        )

    def forward(self, batch_dict: dict) -> dict:
        features = batch_dict["voxel_features"]  # (V, C)
        if features.dim() != 2 or features.shape[1] != self.input_channels:
            raise ValueError(
                f"{type(self).__name__}: voxel_features must be (V, {self.input_channels}), got "
                f"{tuple(features.shape)}"
            )
        x = SparseConvTensor(
            features,
            batch_dict["voxel_coords"].int(),
            self.sparse_shape,
            int(batch_dict["batch_size"]),
        )
        x = self.conv_input(x)
        x_conv1 = self.conv1(x)
        x_conv2 = self.conv2(x_conv1)
        x_conv3 = self.conv3(x_conv2)
        x_conv4 = self.conv4(x_conv3)
        batch_dict["encoded_spconv_tensor"] = self.conv_out(x_conv4)
        batch_dict["encoded_spconv_tensor_stride"] = self.output_stride
        batch_dict["multi_scale_3d_features"] = {
            "x_conv1": x_conv1, "x_conv2": x_conv2, "x_conv3": x_conv3, "x_conv4": x_conv4,
        }  # fmt: skip
        batch_dict["multi_scale_3d_strides"] = {
            "x_conv1": 1, "x_conv2": 2, "x_conv3": 4, "x_conv4": 8,
        }  # fmt: skip
        return batch_dict


def conv_out(in_channels: int, last_pad: int) -> SparseSequential:
    """OpenPCDet's ``conv_out``: the ``(3, 1, 1)`` kernel at stride ``(2, 1, 1)`` down to 128
    channels, BatchNorm, ReLU."""
    return SparseSequential(
        SparseConv3d(
            in_channels,
            128,
            (3, 1, 1),
            stride=(2, 1, 1),
            padding=last_pad,
            bias=False,
            indice_key="spconv_down2",
        ),  # fmt: skip
        norm_fn(128),
        nn.ReLU(),
    )


@MODEL_STAGES.register()
class VoxelBackBone8x(_VoxelBackBone):
    """OpenPCDet's ``VoxelBackBone8x``: submanifold stages at strides 1, 2, 4, 8 and a
    ``(3, 1, 1)`` / ``(2, 1, 1)`` ``conv_out`` to 128 channels."""

    def __init__(
        self,
        *,
        input_channels: int,
        grid_size: Sequence[int],
        last_pad: int = VoxelBackBoneConfig.last_pad,
    ):
        super().__init__(input_channels=input_channels, grid_size=grid_size)
        self.conv_input = SparseSequential(
            SubMConv3d(input_channels, 16, 3, padding=1, bias=False, indice_key="subm1"),
            norm_fn(16),
            nn.ReLU(),
        )
        block = post_act_block
        self.conv1 = SparseSequential(block(16, 16, 3, padding=1, indice_key="subm1"))
        self.conv2 = SparseSequential(
            block(16, 32, 3, stride=2, padding=1, indice_key="spconv2", conv_type="spconv"),
            block(32, 32, 3, padding=1, indice_key="subm2"),
            block(32, 32, 3, padding=1, indice_key="subm2"),
        )
        self.conv3 = SparseSequential(
            block(32, 64, 3, stride=2, padding=1, indice_key="spconv3", conv_type="spconv"),
            block(64, 64, 3, padding=1, indice_key="subm3"),
            block(64, 64, 3, padding=1, indice_key="subm3"),
        )
        self.conv4 = SparseSequential(
            block(64, 64, 3, stride=2, padding=(0, 1, 1), indice_key="spconv4", conv_type="spconv"),
            block(64, 64, 3, padding=1, indice_key="subm4"),
            block(64, 64, 3, padding=1, indice_key="subm4"),
        )
        self.conv_out = conv_out(64, last_pad)
        self.num_point_features = 128


@MODEL_STAGES.register()
class VoxelResBackBone8x(_VoxelBackBone):
    """OpenPCDet's ``VoxelResBackBone8x`` (CenterPoint's): ``SparseBasicBlock`` pairs at strides
    1, 2, 4, 8 (16, 32, 64, 128 channels) and the ``(3, 1, 1)`` / ``(2, 1, 1)`` ``conv_out``."""

    def __init__(
        self,
        *,
        input_channels: int,
        grid_size: Sequence[int],
        last_pad: int = VoxelBackBoneConfig.last_pad,
    ):
        super().__init__(input_channels=input_channels, grid_size=grid_size)
        self.conv_input = SparseSequential(
            SubMConv3d(input_channels, 16, 3, padding=1, bias=False, indice_key="subm1"),
            norm_fn(16),
            nn.ReLU(),
        )
        block = post_act_block
        self.conv1 = SparseSequential(
            SparseBasicBlock(16, 16, indice_key="res1"),
            SparseBasicBlock(16, 16, indice_key="res1"),
        )
        self.conv2 = SparseSequential(
            block(16, 32, 3, stride=2, padding=1, indice_key="spconv2", conv_type="spconv"),
            SparseBasicBlock(32, 32, indice_key="res2"),
            SparseBasicBlock(32, 32, indice_key="res2"),
        )
        self.conv3 = SparseSequential(
            block(32, 64, 3, stride=2, padding=1, indice_key="spconv3", conv_type="spconv"),
            SparseBasicBlock(64, 64, indice_key="res3"),
            SparseBasicBlock(64, 64, indice_key="res3"),
        )
        self.conv4 = SparseSequential(
            block(
                64, 128, 3, stride=2, padding=(0, 1, 1), indice_key="spconv4", conv_type="spconv"
            ),
            SparseBasicBlock(128, 128, indice_key="res4"),
            SparseBasicBlock(128, 128, indice_key="res4"),
        )
        self.conv_out = conv_out(128, last_pad)
        self.num_point_features = 128
