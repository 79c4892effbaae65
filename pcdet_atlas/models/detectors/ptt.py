"""PTT (Huang et al., CVPR'24): the current frame's CP-4f proposals refined with the current
frame's points and the proposals of the 31 previous frames
(:class:`~pcdet_atlas.models.roi_heads.ptt_head.PTTHead`; docs/model_zoo.md, "PTT").

Both :meth:`PTT.loss` and :meth:`PTT.predict` read the proposals from the batch: ``roi_boxes``
``(B, R, 11)`` (the current frame's), ``roi_history`` ``(B, N, 12)`` (the previous frames' in
the current vehicle frame, frames back last) and ``roi_history_frames`` ``(B,)`` (how many
previous frames exist). For training they come from the proposal cache of the clean train split
(``WaymoDataset.set_proposals``); at test time from the proposal bank
(:class:`pcdet_atlas.train_utils.proposal_bank.ProposalBank`, which ``tools/test.py`` uses),
which runs the RPN once per frame on that frame's own (attacked) input.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

from pcdet_atlas.models.detectors.two_stage import TwoStageDetector, roi_boxes_to_padded
from pcdet_atlas.models.roi_heads.ptt_head import history_frames
from pcdet_atlas.registry import DETECTORS

__all__ = ["PTT", "PROPOSAL_INPUT_KEYS"]

#: the batch keys PTT reads its proposals from
PROPOSAL_INPUT_KEYS = ("roi_boxes", "roi_history", "roi_history_frames")


@DETECTORS.register()
class PTT(TwoStageDetector):
    """Frozen CP-4f RPN + :class:`PTTHead` (module docstring). Needs ``frame_seed``."""

    required_stages = ("roi_head",)

    @property
    def proposal_history(self) -> int:
        """How many previous frames' proposals the model reads (31)."""
        return self.roi_head.num_history

    def _check_inputs(self, batch_dict: Mapping, caller: str, extra=()) -> None:
        for key in (*PROPOSAL_INPUT_KEYS, *extra):
            if key not in batch_dict:
                raise KeyError(
                    f"PTT.{caller} needs batch_dict[{key!r}]: the proposals of the current and "
                    f"the {self.proposal_history} previous frames (training: the proposal cache, "
                    "attached by tools/train.py; testing: pcdet_atlas.train_utils.proposal_bank."
                    "ProposalBank, used by tools/test.py)"
                )

    def histories(self, batch_dict: Mapping) -> list[list[torch.Tensor | None]]:
        """Per sample, the proposals of frames ``t-1 .. t-H`` (``None`` before the sequence
        start)."""
        return [
            history_frames(rows, int(count), self.proposal_history)
            for rows, count in zip(batch_dict["roi_history"], batch_dict["roi_history_frames"])
        ]

    def loss(self, batch_dict: Mapping) -> dict[str, torch.Tensor]:
        self._check_inputs(batch_dict, "loss", ("gt_boxes",))
        histories = self.histories(batch_dict)
        return self.second_stage_loss(
            batch_dict, "ptt",
            lambda b, chosen: self.roi_head.trajectories(chosen, histories[b]),
        )  # fmt: skip

    @torch.no_grad()
    def predict(self, batch_dict: Mapping) -> list[dict[str, torch.Tensor]]:
        """Per sample ``pred_boxes (K, 7)``, ``pred_scores``, ``pred_labels`` (1-based) and the
        refined proposals as ``rois`` / ``roi_scores`` / ``roi_labels``."""
        self._check_inputs(batch_dict, "predict")
        head = self.roi_head
        rois, scores, labels, valid = roi_boxes_to_padded(batch_dict["roi_boxes"])
        histories = self.histories(batch_dict)
        traj, traj_valid = [], []
        for b in range(rois.shape[0]):
            boxes, ok = head.trajectories(rois[b], histories[b])
            traj.append(boxes)
            traj_valid.append(ok & valid[b][None])
        out = head({
            **batch_dict, "rois": rois, "roi_valid": valid, "trajectories": torch.stack(traj),
            "trajectory_valid": torch.stack(traj_valid),
            "generators": self.sample_generators(batch_dict, "ptt_points"),
        })  # fmt: skip
        boxes, logits = head.decode(out, rois)
        proposals = [
            {"pred_boxes": rois[b][valid[b]], "pred_scores": scores[b][valid[b]],
             "pred_labels": labels[b][valid[b]]}
            for b in range(rois.shape[0])
        ]  # fmt: skip
        # valid rows come first in every sample (roi_boxes are padded at the end)
        return self.detections(proposals, boxes, logits, scores, labels)
