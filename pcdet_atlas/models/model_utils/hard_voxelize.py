"""Hard voxelization with OpenPCDet's caps, as a torch op inside the model.

OpenPCDet voxelizes each frame with spconv 2.x's ``Point2VoxelCPU3d`` under
``MAX_POINTS_PER_VOXEL`` and ``MAX_NUMBER_OF_VOXELS`` (one value per split). Its rule, applied here
per frame and without a loop over points:

- points are read in their input order; points outside the range belong to no voxel;
- voxels are numbered in the order of their first point; a point that would open a voxel beyond
  ``max_voxels`` is dropped, while later points of already open voxels are still kept;
- a voxel keeps its first ``max_points_per_voxel`` points (input order), the rest are dropped.

The cells come from :func:`voxelize`, in the points' dtype as spconv computes them (float32
points: float32 arithmetic, so a point within rounding of a cell edge lands where spconv puts it).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pcdet_atlas.models.model_utils.voxelize import VoxelGrid, voxelize

__all__ = ["HardVoxelization", "hard_voxelize"]


@dataclass
class HardVoxelization:
    """The result of :func:`hard_voxelize` for a batch.

    Attributes:
        voxels: (V, max_points_per_voxel, C) point features ``[x, y, z, ...]``, zero-padded.
        voxel_coords: (V, 4) int64 ``[batch_idx, z, y, x]``; frames in batch order, each frame's
            voxels in the order of their first point (OpenPCDet's order).
        voxel_num_points: (V,) int64 kept points per voxel (1 .. max_points_per_voxel).
    """

    voxels: torch.Tensor
    voxel_coords: torch.Tensor
    voxel_num_points: torch.Tensor


def hard_voxelize(
    points: torch.Tensor, grid: VoxelGrid, max_points_per_voxel: int, max_voxels: int
) -> HardVoxelization:
    """Group batched points ``(N, 1 + C)`` ``[batch_idx, x, y, z, ...]`` into capped voxels.

    ``max_voxels`` caps each frame (batch index) separately, as OpenPCDet's per-sample processor.
    """
    if max_points_per_voxel < 1 or max_voxels < 1:
        raise ValueError(
            f"hard_voxelize: MAX_POINTS_PER_VOXEL ({max_points_per_voxel}) and "
            f"MAX_NUMBER_OF_VOXELS ({max_voxels}) must be >= 1"
        )
    vox = voxelize(points, grid)  # voxels sorted by (b, z, y, x), every in-range point kept
    device = points.device
    point_ids = torch.nonzero(vox.point_mask, as_tuple=True)[0]  # (N_in,) input positions
    vid = vox.point_voxel_idx  # (N_in,)
    num_cells = vox.voxel_coords.shape[0]
    first = torch.full((num_cells,), points.shape[0], dtype=torch.long, device=device)
    first = first.scatter_reduce(0, vid, point_ids, reduce="amin")  # (V_all,) first point
    batch = vox.voxel_coords[:, 0]
    # rank of each voxel within its frame by first appearance
    order = torch.argsort(batch * (points.shape[0] + 1) + first)  # frames, then first point
    batch_sorted = batch[order]
    frame_start = torch.searchsorted(batch_sorted, batch_sorted, right=False)
    rank = torch.arange(num_cells, device=device) - frame_start  # rank of order[i]
    kept_voxels = order[rank < max_voxels]  # (V,) in output order
    new_id = torch.full((num_cells,), -1, dtype=torch.long, device=device)
    new_id[kept_voxels] = torch.arange(kept_voxels.numel(), device=device)
    pid = new_id[vid]  # (N_in,) output voxel of each point, -1 where its voxel is capped away
    # slot of each point inside its voxel: points sorted stably by voxel keep the input order
    by_voxel = torch.argsort(vid, stable=True)
    vid_sorted = vid[by_voxel]
    slot_sorted = torch.arange(vid.numel(), device=device) - torch.searchsorted(
        vid_sorted, vid_sorted
    )
    slot = torch.empty_like(slot_sorted)
    slot[by_voxel] = slot_sorted
    keep = (pid >= 0) & (slot < max_points_per_voxel)
    feats = points[point_ids[keep], 1:]  # (K, C)
    voxels = points.new_zeros((kept_voxels.numel(), max_points_per_voxel, feats.shape[1]))
    voxels[pid[keep], slot[keep]] = feats
    num_points = torch.bincount(pid[keep], minlength=kept_voxels.numel())
    return HardVoxelization(voxels, vox.voxel_coords[kept_voxels], num_points)
