"""``PointCountOracle``: not an OpenPCDet model; the stand-in's "any architecture".

It detects each ground-truth box of the batch that holds at least ``MODEL.MIN_POINTS`` of the
current frame's points, with score ``min(1, points / MODEL.SCORE_POINTS) * scale`` (``scale``:
its one weight, from the checkpoint), so an attack changes its output through the points alone:
a removal that thins a box out hides it. It has OpenPCDet's detector interface: ``forward`` in
eval mode returns ``(pred_dicts, recall_dict)``; ``load_params_from_file``, which unpickles
the file as OpenPCDet's does on a torch that does not default to ``weights_only`` (so it runs
code a file names: the integration must not call it), and ``_load_state_dict``.
"""

import torch
from torch import nn

from pcdet_atlas.ops.boxes import points_in_boxes_mask


class PointCountOracle(nn.Module):
    def __init__(self, model_cfg, num_class, dataset):
        super().__init__()
        self.model_cfg = model_cfg
        self.num_class = num_class
        self.scale = nn.Parameter(torch.ones(()))

    def load_params_from_file(self, filename, logger, to_cpu=False, pre_trained_path=None):
        checkpoint = torch.load(filename, map_location="cpu", weights_only=False)
        self._load_state_dict(checkpoint["model_state"], strict=False)
        logger.info(f"loaded {filename}")

    def _load_state_dict(self, model_state_disk, *, strict=True):
        state_dict = self.state_dict()
        update_model_state = {
            key: val for key, val in model_state_disk.items()
            if key in state_dict and state_dict[key].shape == val.shape
        }  # fmt: skip
        if strict:
            self.load_state_dict(update_model_state)
        else:
            state_dict.update(update_model_state)
            self.load_state_dict(state_dict)
        return state_dict, update_model_state

    def forward(self, batch_dict):
        if self.training:
            raise NotImplementedError("the stand-in detector only predicts")
        points, boxes = batch_dict["points"], batch_dict["gt_boxes"]  # (N, 1 + C), (B, M, 8)
        if points.shape[1] > 6:  # a sequence input: the current frame's points (time lag 0)
            points = points[points[:, -1] == 0]
        pred_dicts = []
        for b in range(batch_dict["batch_size"]):
            gt = boxes[b][boxes[b, :, 3] > 0]  # padding rows have no size
            inside = points_in_boxes_mask(points[points[:, 0] == b, 1:4].double(), gt[:, :7])
            count = inside.sum(dim=1)
            keep = count >= self.model_cfg.MIN_POINTS
            score = torch.clamp(count[keep].float() / self.model_cfg.SCORE_POINTS, max=1.0)
            pred_dicts.append({
                "pred_boxes": gt[keep, :7], "pred_scores": score * self.scale.detach(),
                "pred_labels": gt[keep, 7].long(),
            })  # fmt: skip
        return pred_dicts, {}
