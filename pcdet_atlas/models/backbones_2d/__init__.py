"""2D BEV backbones (stage ``backbone_2d``)."""

from pcdet_atlas.models.backbones_2d.base_bev_backbone import BaseBEVBackbone
from pcdet_atlas.models.backbones_2d.base_bev_res_backbone import BaseBEVResBackbone

__all__ = ["BaseBEVBackbone", "BaseBEVResBackbone"]
