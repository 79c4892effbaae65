"""Dense (anchor-free) detection heads (stage ``dense_head``)."""

from pcdet_atlas.models.dense_heads.center_head import CenterHead

__all__ = ["CenterHead"]
