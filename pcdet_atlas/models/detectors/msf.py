"""MSF (He et al., CVPR'23): CP-4f proposals refined by motion-guided sampling over 4 or 8 frames
of points (:class:`~pcdet_atlas.models.roi_heads.msf_head.MSFHead`; docs/model_zoo.md)."""

from __future__ import annotations

from collections.abc import Mapping

import torch

from pcdet_atlas.models.detectors.two_stage import TwoStageDetector, proposals_to_padded
from pcdet_atlas.models.model_utils.motion_sampler import propagate_boxes
from pcdet_atlas.registry import DETECTORS

__all__ = ["MSF"]


@DETECTORS.register()
class MSF(TwoStageDetector):
    """Frozen CP-4f RPN + :class:`MSFHead`.

    :meth:`loss` trains on the batch's precomputed clean proposals (``roi_boxes`` ``(B, R, 11)``,
    label 0 = padding) and ``gt_boxes``; :meth:`predict` always proposes with the RPN on the
    batch's own (possibly attacked) points. Both need ``frame_seed`` (one per sample).
    """

    required_stages = ("roi_head",)

    def loss(self, batch_dict: Mapping) -> dict[str, torch.Tensor]:
        for key in ("roi_boxes", "gt_boxes"):
            if key not in batch_dict:
                raise KeyError(
                    f"MSF.loss needs batch_dict[{key!r}] (training proposals: "
                    "pcdet_atlas.train_utils.proposals, attached by tools/train.py)"
                )
        return self.second_stage_loss(batch_dict, "msf")

    @torch.no_grad()
    def predict(self, batch_dict: Mapping) -> list[dict[str, torch.Tensor]]:
        """Per sample ``pred_boxes (K, 7)``, ``pred_scores``, ``pred_labels`` (1-based), and
        ``rois`` / ``roi_scores`` / ``roi_labels``: the RPN's proposals it refined."""
        return self.refine(batch_dict, self.propose(batch_dict))

    @torch.no_grad()
    def refine(self, batch_dict: Mapping, proposals: list[Mapping]) -> list[dict]:
        """The second stage alone: :meth:`predict` on given per-sample proposals (the RPN's
        ``pred_boxes (R, 9)``, ``pred_scores``, ``pred_labels``)."""
        device = batch_dict["points"].device
        rois, scores, labels, valid = proposals_to_padded(proposals, device)
        head = self.roi_head
        traj = torch.stack([propagate_boxes(r, head.num_frames) for r in rois])
        out = head({
            **batch_dict, "rois": rois, "roi_valid": valid, "trajectories": traj,
            "generators": self.sample_generators(batch_dict, "msf_points"),
        })  # fmt: skip
        boxes, logits = head.decode(out, rois)
        return self.detections(proposals, boxes, logits, scores, labels)
