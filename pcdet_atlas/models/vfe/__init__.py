"""Voxel/pillar feature encoders (stage ``vfe``)."""

from pcdet_atlas.models.vfe.dynamic_pillar_vfe import DynamicPillarVFE
from pcdet_atlas.models.vfe.mean_vfe import MeanVFE

__all__ = ["DynamicPillarVFE", "MeanVFE"]
