"""Scatter of pillar features onto the BEV canvas (stage ``map_to_bev_module``)."""

from pcdet_atlas.models.map_to_bev.height_compression import HeightCompression
from pcdet_atlas.models.map_to_bev.pointpillar_scatter import PointPillarScatter
from pcdet_atlas.models.map_to_bev.pointpillar_scatter3d import PointPillarScatter3d
from pcdet_atlas.models.map_to_bev.sector_feature_buffer import SectorFeatureBuffer

__all__ = ["HeightCompression", "PointPillarScatter", "PointPillarScatter3d", "SectorFeatureBuffer"]
