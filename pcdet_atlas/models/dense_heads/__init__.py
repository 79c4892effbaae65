"""Dense (anchor-free) detection heads (stage ``dense_head``)."""

from pcdet_atlas.models.dense_heads.center_head import CenterHead
from pcdet_atlas.models.dense_heads.centerformer_head import CenterFormerHead

__all__ = ["CenterFormerHead", "CenterHead"]
