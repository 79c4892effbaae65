"""Voxel/pillar feature encoders (stage ``vfe``)."""

from pcdet_atlas.models.vfe.dynamic_pillar_vfe import DynamicPillarVFE

__all__ = ["DynamicPillarVFE"]
