"""Voxel/pillar feature encoders (stage ``vfe``)."""

from pcdet_atlas.models.vfe.dynamic_pillar_vfe import DynamicPillarVFE
from pcdet_atlas.models.vfe.dynamic_voxel_vfe import DynamicVoxelVFE
from pcdet_atlas.models.vfe.mean_vfe import MeanVFE
from pcdet_atlas.models.vfe.polar_vfe import PolarVFE

__all__ = ["DynamicPillarVFE", "DynamicVoxelVFE", "MeanVFE", "PolarVFE"]
