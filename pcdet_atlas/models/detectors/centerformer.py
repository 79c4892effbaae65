"""CenterFormer (ECCV'22), single frame: MeanVFE -> VoxelResBackBone8x -> HeightCompression ->
CenterFormerBEVBackbone (the BEV pyramid) -> CenterFormerHead (centre heatmap, top-K centre
queries, their transformer, per-query box and IoU heads). docs/model_zoo.md "CenterFormer"
lists how closely it follows the released model."""

from __future__ import annotations

from collections.abc import Mapping

import torch

from pcdet_atlas.models.detectors.detector3d_template import Detector3DTemplate
from pcdet_atlas.registry import DETECTORS

__all__ = ["CenterFormer"]


@DETECTORS.register()
class CenterFormer(Detector3DTemplate):
    """Centre-query transformer detector.

    Input batch (the dataset's collate): ``points`` (N, 1 + C) float ``[batch_idx, x, y, z, ...]``,
    ``batch_size``, and for :meth:`loss` ``gt_boxes`` (B, M, 8|10) with the 1-based class last;
    in training the head puts the ground-truth centres among its queries.
    """

    required_stages = ("vfe", "backbone_3d", "map_to_bev_module", "backbone_2d", "dense_head")
    prediction_inputs = ("points",)

    def features(self, batch_dict: Mapping) -> dict:
        """A shallow copy of ``batch_dict`` through every stage before the head."""
        batch = dict(batch_dict)
        for stage in self.module_list[:-1]:
            batch = stage(batch)
        return batch

    def loss(self, batch_dict: Mapping) -> dict[str, torch.Tensor]:
        """``{'loss': total, 'hm_loss', 'loc_loss', 'iou_loss', 'corner_loss'}`` scalars."""
        if "gt_boxes" not in batch_dict:
            raise KeyError("CenterFormer.loss needs batch_dict['gt_boxes'] (B, M, 8|10)")
        return self.dense_head.loss(self.features(batch_dict), batch_dict["gt_boxes"])

    @torch.no_grad()
    def predict(self, batch_dict: Mapping) -> list[dict[str, torch.Tensor]]:
        """Per sample ``{'pred_boxes': (K, 7), 'pred_scores': (K,), 'pred_labels': (K,)}``,
        labels 1-based into ``class_names``."""
        out = self.run_stages(batch_dict)
        return self.dense_head.predict(out["head_outputs"])
