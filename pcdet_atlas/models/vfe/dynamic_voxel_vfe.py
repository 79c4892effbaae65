"""Dynamic voxel feature encoder (OpenPCDet's ``DynamicVoxelVFE``): the dynamic pillar encoder
on a 3D voxel grid.

Every point inside the range (x, y and z) is decorated with its offsets from its voxel's mean
and centre and run through the same PFN layers as :class:`DynamicPillarVFE`, with a max per
voxel; DSVT-V reads its output. Points outside the z range are dropped, as OpenPCDet does here.
"""

from __future__ import annotations

from collections.abc import Mapping

from pcdet_atlas.config import ConfigError, check_known_keys
from pcdet_atlas.models.model_utils.voxelize import check_voxel_size_placeholder
from pcdet_atlas.models.vfe.dynamic_pillar_vfe import DynamicPillarVFE
from pcdet_atlas.registry import MODEL_STAGES


@MODEL_STAGES.register()
class DynamicVoxelVFE(DynamicPillarVFE):
    """Points -> one feature vector per non-empty voxel.

    Reads ``batch_dict['points']`` (N, 1 + C); writes ``voxel_features`` = ``pillar_features``
    (V, F) and ``voxel_coords`` (V, 4) ``[batch, z, y, x]``.
    """

    pillar_grid = False

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> DynamicVoxelVFE:
        check_known_keys(
            cfg,
            ["NAME", "VOXEL_SIZE", "NUM_FILTERS", "USE_NORM", "WITH_DISTANCE", "USE_ABSLOTE_XYZ"],
            "MODEL.VFE",
        )
        voxel_size = cfg.get("VOXEL_SIZE", model_info.get("voxel_size"))
        if voxel_size is None:
            raise ConfigError(
                "MODEL.VFE needs VOXEL_SIZE, or DATA_CONFIG.DATA_PROCESSOR a "
                "transform_points_to_voxels_placeholder stating it (as OpenPCDet's configs do)"
            )
        check_voxel_size_placeholder(cfg, voxel_size, model_info)
        return cls(
            num_point_features=model_info["num_point_features"],
            point_cloud_range=model_info["point_cloud_range"],
            voxel_size=voxel_size,
            num_filters=cfg.get("NUM_FILTERS", (64, 64)),
            use_norm=cfg.get("USE_NORM", True),
            with_distance=cfg.get("WITH_DISTANCE", False),
            use_absolute_xyz=cfg.get("USE_ABSLOTE_XYZ", True),
            drop_outside_z=True,
        )

    def forward(self, batch_dict: dict) -> dict:
        batch_dict = super().forward(batch_dict)
        batch_dict["voxel_features"] = batch_dict["pillar_features"]  # (V, F)
        return batch_dict
