"""MeanVFE (OpenPCDet's): hard-voxelize the points, one feature vector per voxel = mean of its
points.

OpenPCDet caps the voxelization in its data processor (``transform_points_to_voxels``); here the
model voxelizes the raw points itself (:func:`hard_voxelize`) with the same caps, the voxel count
cap taken from ``MAX_NUMBER_OF_VOXELS['train']`` in training mode and ``['test']`` in eval mode.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from torch import nn

from pcdet_atlas.config_values import setting
from pcdet_atlas.models.model_utils.hard_voxelize import hard_voxelize
from pcdet_atlas.models.model_utils.voxelize import (
    VoxelGrid,
    check_point_columns,
    check_voxel_size_placeholder,
)
from pcdet_atlas.models.stage_config import StageConfig, read_stage
from pcdet_atlas.registry import MODEL_STAGES


@dataclass(frozen=True, kw_only=True)
class MeanVFEConfig(StageConfig):
    """``MODEL.VFE`` of MeanVFE (hard voxelization)."""

    voxel_size: tuple[float, float, float] = setting(gt=0, doc="voxel size, m")
    max_points_per_voxel: int = setting(ge=1, doc="points kept per voxel")
    max_number_of_voxels: dict[str, int] = setting(
        check=lambda d: all(type(v) is int and v >= 1 for v in d.values()),
        expected="{train: n, test: n} with integers n >= 1",
        doc="voxels kept per sample, per mode",
    )


@MODEL_STAGES.register()
class MeanVFE(nn.Module):
    """Points -> voxel means.

    Reads ``batch_dict['points']`` (N, 1 + C); writes ``voxel_features`` (V, C), ``voxel_coords``
    (V, 4) ``[batch, z, y, x]`` and ``voxel_num_points`` (V,).
    """

    CONFIG = MeanVFEConfig

    def __init__(
        self,
        *,
        num_point_features: int,
        point_cloud_range: Sequence[float],
        voxel_size: Sequence[float],
        max_points_per_voxel: int,
        max_number_of_voxels: Mapping[str, int],
    ):
        """
        Args:
            num_point_features: C, point columns after the batch index (x, y, z first).
            point_cloud_range: (6,) metres. voxel_size: (3,) metres.
            max_points_per_voxel: points kept per voxel (the first ones, in input order).
            max_number_of_voxels: ``{'train': n, 'test': m}`` voxels kept per frame.
        """
        super().__init__()
        self.grid = VoxelGrid(tuple(map(float, point_cloud_range)), tuple(map(float, voxel_size)))
        if num_point_features < 3:
            raise ValueError(f"num_point_features must be >= 3, got {num_point_features}")
        if set(max_number_of_voxels) != {"train", "test"}:
            raise ValueError(
                "MAX_NUMBER_OF_VOXELS must map exactly 'train' and 'test' to counts, got "
                f"{dict(max_number_of_voxels)}"
            )
        self.num_point_features = num_point_features
        self.max_points_per_voxel = int(max_points_per_voxel)
        self.max_number_of_voxels = {k: int(v) for k, v in max_number_of_voxels.items()}
        for name, value in [("MAX_POINTS_PER_VOXEL", self.max_points_per_voxel)] + [
            (f"MAX_NUMBER_OF_VOXELS.{k}", v) for k, v in self.max_number_of_voxels.items()
        ]:
            if value < 1:
                raise ValueError(f"{name} must be >= 1, got {value}")

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> MeanVFE:
        settings = read_stage(cls, cfg, "MODEL.VFE")
        check_voxel_size_placeholder(cfg, settings.voxel_size, model_info)
        return cls(
            num_point_features=model_info["num_point_features"],
            point_cloud_range=model_info["point_cloud_range"],
            voxel_size=settings.voxel_size,
            max_points_per_voxel=settings.max_points_per_voxel,
            max_number_of_voxels=settings.max_number_of_voxels,
        )

    def get_output_feature_dim(self) -> int:
        return self.num_point_features

    def forward(self, batch_dict: dict) -> dict:
        points = batch_dict["points"]  # (N, 1 + C)
        check_point_columns(points, self.num_point_features, "MeanVFE")
        split = "train" if self.training else "test"
        vox = hard_voxelize(
            points, self.grid, self.max_points_per_voxel, self.max_number_of_voxels[split]
        )
        # padded slots are zeros, so the sum over all slots is the sum over the kept points
        normalizer = vox.voxel_num_points.clamp_min(1).to(points.dtype)[:, None]  # (V, 1)
        batch_dict["voxel_features"] = (vox.voxels.sum(dim=1) / normalizer).float()  # (V, C)
        batch_dict["voxel_coords"] = vox.voxel_coords  # (V, 4)
        batch_dict["voxel_num_points"] = vox.voxel_num_points  # (V,)
        return batch_dict
