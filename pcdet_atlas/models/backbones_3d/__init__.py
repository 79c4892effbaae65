"""3D sparse voxel backbones (stage ``backbone_3d``)."""

from pcdet_atlas.models.backbones_3d.dsvt import DSVT
from pcdet_atlas.models.backbones_3d.polar_sector_mamba import PolarSectorMamba
from pcdet_atlas.models.backbones_3d.spconv_backbone import VoxelBackBone8x, VoxelResBackBone8x

__all__ = ["DSVT", "PolarSectorMamba", "VoxelBackBone8x", "VoxelResBackBone8x"]
