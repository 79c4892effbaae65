"""What LOT's filter does to the voxels of real frames, and how good its forecast is.

LOT (docs/model_zoo.md "PHiM+LOT") keeps a voxel when its confidence reaches ``FILTER_THRESH``.
These functions measure, on the frames of a loader:

- the confidence of every polar voxel, labelled **in a box** (one of its points lies in a ground
  truth box of its frame), **phantom** (one of its points lies in the frame's injected phantom's
  box, from the attack metadata) or **background** (neither);
- the keep rate of each group at a threshold, and the threshold a stated rule gives: the highest
  one that keeps at least ``recall`` of the in-box voxels (:func:`threshold_for_recall`);
- the forecast's quality: the CenterNet focal loss of the forecast map against LOT's occupancy
  target beside that of a **range prior** (per range cell the constant with the lowest such loss
  over the frames of a fit split, the same for every azimuth): the best a forecast that knows
  only range can do.

``tools/dev/lot_filter.py`` prints them for a config and checkpoint.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np
import torch

from pcdet_atlas.models.batch import load_data_to_device
from pcdet_atlas.models.model_utils.centernet_utils import focal_loss_centernet_prob
from pcdet_atlas.models.model_utils.polar_grid import polar_voxelize
from pcdet_atlas.models.model_utils.scatter import scatter_max
from pcdet_atlas.models.occupancy.occupancy_targets import occupancy_target
from pcdet_atlas.ops.boxes import points_in_boxes_mask

__all__ = [
    "VoxelConfidences",
    "collect_confidences",
    "forecast_quality",
    "keep_rate",
    "range_prior",
    "threshold_for_recall",
    "voxel_confidences",
]

GROUPS = ("in_box", "background", "phantom")


@dataclass
class VoxelConfidences:
    """LOT confidences of voxels by group (``GROUPS``), float64 arrays."""

    groups: dict[str, list[np.ndarray]] = field(default_factory=lambda: {g: [] for g in GROUPS})

    def add(self, group: str, values: torch.Tensor) -> None:
        self.groups[group].append(values.detach().double().cpu().numpy())

    def of(self, group: str) -> np.ndarray:
        parts = self.groups[group]
        return np.concatenate(parts) if parts else np.zeros(0)


def _lot_model(model):
    if getattr(model, "lot", None) is None:
        raise ValueError(f"{type(model).__name__} has no LOT stage (MODEL.LOT)")
    return model


@torch.no_grad()
def voxel_confidences(model, batch: Mapping) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """``({group: (V_g,) confidences}, (B, A', R') forecast probabilities)`` of one batch.

    ``batch`` as the loader collates it (``points``, ``gt_boxes``, ``batch_size``; ``attack``,
    a list of per-sample metadata, for the phantom group). Runs the VFE and LOT's maps, not its
    filter.
    """
    model = _lot_model(model)
    batch = model.split_frames(batch)  # the current frame's points; LOT's history maps
    out = model.lot.occupancy_maps(model.vfe(dict(batch)))
    conf = out["lot_voxel_confidence"]  # (V,)
    points = batch["points"]
    vox = polar_voxelize(points, model.vfe.grid)
    pts = points[vox.point_mask]  # (N_in, 1 + C), the VFE's points in its voxel order
    idx = vox.point_voxel_idx  # (N_in,)
    V = conf.shape[0]
    in_box = torch.zeros(pts.shape[0], dtype=torch.bool, device=pts.device)
    phantom = torch.zeros_like(in_box)
    metas = batch.get("attack")
    for b in range(int(batch["batch_size"])):
        rows = pts[:, 0] == b
        boxes = batch["gt_boxes"][b]
        boxes = boxes[boxes[:, -1] > 0]
        if boxes.shape[0]:
            in_box[rows] = points_in_boxes_mask(pts[rows, 1:4], boxes[:, :7]).any(0)
        meta = metas[b] if metas is not None else None
        box = None if meta is None else meta.get("target_box")
        if box is not None and meta.get("family") == "injection" and meta.get("spoofed"):
            box = torch.as_tensor(np.asarray(box), dtype=pts.dtype, device=pts.device)
            phantom[rows] = points_in_boxes_mask(pts[rows, 1:4], box[None, :7]).any(0)
    voxel_in_box = scatter_max(in_box[:, None].float(), idx, V)[:, 0] > 0
    voxel_phantom = scatter_max(phantom[:, None].float(), idx, V)[:, 0] > 0
    real_box = voxel_in_box & ~voxel_phantom
    groups = {
        "in_box": conf[real_box],
        "background": conf[~voxel_in_box & ~voxel_phantom],
        "phantom": conf[voxel_phantom],
    }
    return groups, torch.sigmoid(out["lot_forecast_logits"])


def collect_confidences(model, batches: Iterable[Mapping], device: str = "cpu"):
    """:class:`VoxelConfidences` over ``batches`` and the list of ``(forecast, target)`` maps
    ``(B, A', R')`` per batch (the target: LOT's occupancy target of the ground truth)."""
    model = _lot_model(model).eval()
    found = VoxelConfidences()
    maps = []
    for batch in batches:
        batch = load_data_to_device(batch, device)
        groups, forecast = voxel_confidences(model, batch)
        for name, values in groups.items():
            found.add(name, values)
        target = occupancy_target(
            batch["gt_boxes"], model.lot.grid, model.lot.pool_size, model.lot.gt_min_sigma
        )
        maps.append((forecast.cpu(), target.cpu()))
    return found, maps


def threshold_for_recall(in_box: np.ndarray, recall: float = 0.95) -> float:
    """The highest threshold ``t`` whose keep rate ``mean(in_box >= t)`` is at least ``recall``:
    the ``ceil(recall * n)``-th largest in-box confidence."""
    if not 0.0 < recall <= 1.0:
        raise ValueError(f"recall must lie in (0, 1], got {recall}")
    if in_box.size == 0:
        raise ValueError("no in-box voxels to set a threshold from")
    ranked = np.sort(in_box)[::-1]
    return float(ranked[int(np.ceil(recall * in_box.size)) - 1])


def keep_rate(values: np.ndarray, thresh: float) -> float | None:
    """Share of ``values`` at or above ``thresh`` (None when there are none)."""
    return float(np.mean(values >= thresh)) if values.size else None


def range_prior(
    maps: Iterable[tuple[torch.Tensor, torch.Tensor]], steps: int = 400
) -> torch.Tensor:
    """``(R',)`` the best forecast that knows only range: per range cell, the constant
    probability with the lowest focal loss over every frame and azimuth of ``maps`` (the loss as
    :func:`forecast_quality` measures it, each frame weighted by one over its positives), found
    on a logit grid of ``steps`` values in [1e-4, 1 - 1e-4]."""
    targets = torch.stack([t for _, tt in maps for t in tt]).double()  # (N, A', R')
    weight = 1.0 / targets.eq(1).sum(dim=(1, 2)).clamp(min=1).double()  # (N,)
    pos = (targets.eq(1).double() * weight[:, None, None]).sum(dim=(0, 1))  # (R',)
    neg = ((1 - targets) ** 4 * targets.ne(1).double() * weight[:, None, None]).sum(dim=(0, 1))
    p = torch.sigmoid(torch.linspace(-9.2, 9.2, steps, dtype=torch.float64))[:, None]  # (P, 1)
    loss = -torch.log(p) * (1 - p) ** 2 * pos - torch.log(1 - p) * p**2 * neg  # (P, R')
    return p[loss.argmin(0), 0].float()


def forecast_quality(
    maps: Iterable[tuple[torch.Tensor, torch.Tensor]], prior: torch.Tensor
) -> dict[str, float]:
    """Mean focal loss per frame of the forecast and of the range prior against the target
    (lower is better), over ``maps``."""
    forecast_loss, prior_loss, frames = 0.0, 0.0, 0
    for forecast, target in maps:
        for f, t in zip(forecast, target):
            forecast_loss += float(focal_loss_centernet_prob(f[None], t[None]))
            flat = prior.to(t.dtype).expand_as(t).clamp(1e-4, 1 - 1e-4)
            prior_loss += float(focal_loss_centernet_prob(flat[None], t[None]))
            frames += 1
    if frames == 0:
        raise ValueError("no frames to measure the forecast on")
    return {"forecast": forecast_loss / frames, "range_prior": prior_loss / frames}
