"""CenterPoint: pillars (DynamicPillarVFE -> PointPillarScatter) or voxels (MeanVFE ->
VoxelResBackBone8x -> HeightCompression), then BaseBEVBackbone -> CenterHead. With multi-frame
input (a time-lag point column) and the ``vel`` head it is CP4F."""

from __future__ import annotations

from collections.abc import Mapping

import torch

from pcdet_atlas.models.detectors.detector3d_template import Detector3DTemplate
from pcdet_atlas.registry import DETECTORS


@DETECTORS.register()
class CenterPoint(Detector3DTemplate):
    """Single-stage centre-based detector.

    Input batch (the dataset's collate): ``points`` (N, 1 + C) float ``[batch_idx, x, y, z, ...]``,
    ``batch_size``, and for :meth:`loss` ``gt_boxes`` (B, M, 8|10) with the 1-based class last.
    """

    required_stages = ("vfe", "map_to_bev_module", "backbone_2d", "dense_head")
    prediction_inputs = ("points",)

    def loss(self, batch_dict: Mapping) -> dict[str, torch.Tensor]:
        """``{'loss': total, 'hm_loss', 'loc_loss'}`` scalars."""
        if "gt_boxes" not in batch_dict:
            raise KeyError("CenterPoint.loss needs batch_dict['gt_boxes'] (B, M, 8|10)")
        out = self.run_stages(batch_dict)
        return self.dense_head.loss(out["head_outputs"], batch_dict["gt_boxes"])

    @torch.no_grad()
    def predict(self, batch_dict: Mapping) -> list[dict[str, torch.Tensor]]:
        """Per sample ``{'pred_boxes': (K, 7|9), 'pred_scores': (K,), 'pred_labels': (K,)}``,
        labels 1-based into ``class_names``."""
        out = self.run_stages(batch_dict)
        return self.dense_head.predict(out["head_outputs"])
