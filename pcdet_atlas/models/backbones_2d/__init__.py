"""2D BEV backbones (stage ``backbone_2d``)."""

from pcdet_atlas.models.backbones_2d.base_bev_backbone import BaseBEVBackbone

__all__ = ["BaseBEVBackbone"]
