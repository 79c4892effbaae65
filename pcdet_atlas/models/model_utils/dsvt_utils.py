"""DSVT's index ops in plain torch: windows, ranks inside a window, equal-size sets, pooling.

DSVT (Wang et al., CVPR 2023) attends inside sets of a fixed number of voxels. A window of ``n``
non-empty voxels is cut into ``ceil(n / set_size)`` sets; its voxels, ordered along y (``y, x,
z``) or along x (``x, y, z``), are spread over the sets' slots evenly (Eq. 3 of the paper: slot
``j`` of the window's ``S * set_size`` slots holds voxel ``floor(j * n / (S * set_size))``), so
every voxel is in a set and a set repeats a voxel only when the window is not full. The rank of a
voxel inside its window (a custom CUDA op in the released code) is a stable sort plus a
cumulative count here.

Coordinates are OpenPCDet's ``(batch, z, y, x)`` voxel rows; shapes ``(x, y, z)`` as DSVT's
config writes them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

__all__ = [
    "PositionEmbeddingLearned",
    "continuous_inds",
    "pooling_index",
    "rank_in_group",
    "set_key_mask",
    "set_partition",
    "window_coords",
]


class PositionEmbeddingLearned(nn.Module):
    """Learned absolute position embedding: Linear -> BN -> ReLU -> Linear of a voxel's
    position in its window (2 or 3 values)."""

    def __init__(self, input_channel: int, num_pos_feats: int):
        super().__init__()
        self.position_embedding_head = nn.Sequential(
            nn.Linear(input_channel, num_pos_feats),
            nn.BatchNorm1d(num_pos_feats),
            nn.ReLU(inplace=True),
            nn.Linear(num_pos_feats, num_pos_feats),
        )

    def forward(self, xyz: torch.Tensor) -> torch.Tensor:
        """(N, 2|3) -> (N, num_pos_feats)."""
        return self.position_embedding_head(xyz)


@torch.no_grad()
def window_coords(
    coords: torch.Tensor,
    sparse_shape: Sequence[int],
    window_shape: Sequence[int],
    shift: Sequence[int],
) -> tuple[torch.Tensor, torch.Tensor]:
    """The window of each voxel after shifting the grid by ``shift`` voxels.

    Args:
        coords: (N, 4) int ``[batch, z, y, x]``.
        sparse_shape: ``(nx, ny, nz)`` of the grid. window_shape: ``(wx, wy, wz)``.
        shift: ``(sx, sy, sz)`` voxels added before dividing (z is not shifted when a window
            spans the whole height).
    Returns:
        ``batch_win_inds`` (N,) int64, a window id unique over the batch, and ``coors_in_win``
        (N, 3) int64 ``[z, y, x]`` inside the window.
    """
    wx, wy, wz = (int(v) for v in window_shape)
    nx, ny, nz = (int(v) for v in sparse_shape)
    sx, sy, sz = (int(v) for v in shift)
    if nz == wz:
        sz = 0
    # one extra window per axis so that a shifted grid still fits
    win_x, win_y, win_z = math.ceil(nx / wx) + 1, math.ceil(ny / wy) + 1, math.ceil(nz / wz) + 1
    c = coords.long()
    x, y, z = c[:, 3] + sx, c[:, 2] + sy, c[:, 1] + sz
    batch_win_inds = (
        c[:, 0] * (win_x * win_y * win_z)
        + torch.div(x, wx, rounding_mode="floor") * (win_y * win_z)
        + torch.div(y, wy, rounding_mode="floor") * win_z
        + torch.div(z, wz, rounding_mode="floor")
    )
    coors_in_win = torch.stack([z % wz, y % wy, x % wx], dim=-1)
    return batch_win_inds, coors_in_win


def rank_in_group(group: torch.Tensor, key: torch.Tensor) -> torch.Tensor:
    """Rank of each element among the elements of its group, ordered by ``key``.

    A stable sort by ``key`` then by ``group`` lists every group contiguously in key order; an
    element's rank is its position minus its group's start (the cumulative count of the groups
    before it). Ties in ``key`` keep input order.

    Args:
        group: (N,) int64 group ids >= 0 (any values). key: (N,) int64 order inside a group.
    Returns:
        (N,) int64 ranks ``0 .. size(group) - 1``.
    """
    if group.numel() == 0:
        return group.new_zeros(0)
    by_key = torch.sort(key, stable=True).indices
    order = by_key[torch.sort(group[by_key], stable=True).indices]  # group-major, then key
    _, dense = torch.unique(group, return_inverse=True)
    counts = torch.bincount(dense)
    starts = torch.cumsum(counts, 0) - counts  # (G,) first position of each group
    rank = torch.empty_like(group)
    rank[order] = torch.arange(group.numel(), device=group.device) - starts[dense[order]]
    return rank


def continuous_inds(setnum_per_win: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For ``S_w`` sets in window ``w``: each set's window and its index in the window.

    ``[1, 2, 1, 3]`` -> windows ``[0, 1, 1, 2, 3, 3, 3]``, indices ``[0, 0, 1, 0, 0, 1, 2]``.
    """
    win = torch.repeat_interleave(torch.arange(len(setnum_per_win), device=setnum_per_win.device),
                                  setnum_per_win)  # fmt: skip
    starts = torch.cumsum(setnum_per_win, 0) - setnum_per_win
    return win, torch.arange(win.numel(), device=win.device) - starts[win]


@torch.no_grad()
def set_partition(
    batch_win_inds: torch.Tensor,
    coors_in_win: torch.Tensor,
    window_shape: Sequence[int],
    set_size: int,
) -> torch.Tensor:
    """DSVT's dynamic set partition of the voxels of each window, in two orders.

    Args:
        batch_win_inds: (N,) window of each voxel. coors_in_win: (N, 3) ``[z, y, x]`` in it.
        window_shape: ``(wx, wy, wz)``. set_size: voxels per set.
    Returns:
        (2, num_sets, set_size) int64 voxel indices: ``[0]`` the y-major partition (voxels of a
        window ordered by y, then x, then z), ``[1]`` the x-major one (x, y, z). Both have the
        same sets per window; every voxel appears in each, a set repeats a voxel only in
        consecutive slots.
    """
    wx, wy, wz = (int(v) for v in window_shape)
    device = batch_win_inds.device
    if batch_win_inds.numel() == 0:
        return torch.zeros(2, 0, set_size, dtype=torch.long, device=device)
    _, win = torch.unique(batch_win_inds, return_inverse=True)  # (N,) windows 0..W-1
    n_per_win = torch.bincount(win)  # (W,)
    sets_per_win = torch.div(n_per_win + set_size - 1, set_size, rounding_mode="floor")
    set_win, set_in_win = continuous_inds(sets_per_win)  # (S,)
    # Eq. 3: slot j of a window's S_w * set_size slots takes its floor(j * n / (S_w * set_size))-th
    # voxel (integer arithmetic: exact where the released code divides in float64)
    slot = set_in_win[:, None] * set_size + torch.arange(set_size, device=device)  # (S, T)
    pick = torch.div(
        slot * n_per_win[set_win][:, None],
        (sets_per_win[set_win] * set_size)[:, None],
        rounding_mode="floor",
    )  # (S, T) rank inside the window
    starts = torch.cumsum(n_per_win, 0) - n_per_win
    z, y, x = coors_in_win[:, 0].long(), coors_in_win[:, 1].long(), coors_in_win[:, 2].long()
    out = []
    for key in (y * (wx * wz) + x * wz + z, x * (wy * wz) + y * wz + z):
        rank = rank_in_group(win, key)
        by_rank = torch.empty_like(rank)
        by_rank[starts[win] + rank] = torch.arange(len(rank), device=device)  # window-major
        out.append(by_rank[starts[set_win][:, None] + pick])
    return torch.stack(out)


def set_key_mask(set_voxel_inds: torch.Tensor) -> torch.Tensor:
    """True at a slot that repeats the voxel of the slot before it (ignored as a key)."""
    prev = torch.roll(set_voxel_inds, shifts=1, dims=-1)
    prev[..., 0] = -1
    return set_voxel_inds == prev


@torch.no_grad()
def pooling_index(
    coords: torch.Tensor, sparse_shape: Sequence[int], stride: Sequence[int]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Voxels grouped into pooling cells of ``stride`` = ``(sx, sy, sz)`` voxels.

    Returns:
        ``cell`` (N,) pooled voxel of each voxel (0 .. M-1, ordered by pooled id),
        ``index_in_cell`` (N,) ``x * sy * sz + y * sz + z`` inside the cell, and ``pooled``
        (M, 4) int64 ``[batch, z, y, x]`` coordinates of the pooled voxels.
    """
    sx, sy, sz = (int(v) for v in stride)
    nx, ny, nz = (int(v) for v in sparse_shape)
    px, py, pz = math.ceil(nx / sx), math.ceil(ny / sy), math.ceil(nz / sz)
    c = coords.long()
    cx, cy, cz = c[:, 3] // sx, c[:, 2] // sy, c[:, 1] // sz
    ids = c[:, 0] * (px * py * pz) + cx * (py * pz) + cy * pz + cz
    unique, cell = torch.unique(ids, return_inverse=True)
    index_in_cell = (c[:, 3] % sx) * (sy * sz) + (c[:, 2] % sy) * sz + (c[:, 1] % sz)
    pooled = torch.stack(
        [
            torch.div(unique, px * py * pz, rounding_mode="floor"),
            unique % pz,
            torch.div(unique, pz, rounding_mode="floor") % py,
            torch.div(unique, py * pz, rounding_mode="floor") % px,
        ],
        dim=1,
    )
    return cell, index_in_cell, pooled
