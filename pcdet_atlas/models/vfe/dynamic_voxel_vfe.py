"""Dynamic voxel feature encoder (OpenPCDet's ``DynamicVoxelVFE``): the dynamic pillar encoder
on a 3D voxel grid.

Every point inside the range (x, y and z) is decorated with its offsets from its voxel's mean
and centre and run through the same PFN layers as :class:`DynamicPillarVFE`, with a max per
voxel; DSVT-V reads its output. Points outside the z range are dropped, as OpenPCDet does here.
"""

from __future__ import annotations

from pcdet_atlas.models.vfe.dynamic_pillar_vfe import (
    DynamicPillarVFE,
    PointNetVFEConfig,
)
from pcdet_atlas.registry import MODEL_STAGES


@MODEL_STAGES.register()
class DynamicVoxelVFE(DynamicPillarVFE):
    """Points -> one feature vector per non-empty voxel.

    Reads ``batch_dict['points']`` (N, 1 + C); writes ``voxel_features`` = ``pillar_features``
    (V, F) and ``voxel_coords`` (V, 4) ``[batch, z, y, x]``.
    """

    pillar_grid = False

    CONFIG = PointNetVFEConfig  # no DROP_OUTSIDE_Z: a voxel grid always drops outside z

    def forward(self, batch_dict: dict) -> dict:
        batch_dict = super().forward(batch_dict)
        batch_dict["voxel_features"] = batch_dict["pillar_features"]  # (V, F)
        return batch_dict
