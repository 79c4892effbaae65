"""2D BEV backbones (stage ``backbone_2d``)."""

from pcdet_atlas.models.backbones_2d.base_bev_backbone import BaseBEVBackbone
from pcdet_atlas.models.backbones_2d.base_bev_res_backbone import BaseBEVResBackbone
from pcdet_atlas.models.backbones_2d.centerformer_bev_backbone import CenterFormerBEVBackbone

__all__ = ["BaseBEVBackbone", "BaseBEVResBackbone", "CenterFormerBEVBackbone"]
