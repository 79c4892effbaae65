"""Ground-truth polar occupancy of LOT (docs/model_zoo.md "PHiM+LOT"): boxes projected onto the
(azimuth, range) grid by their angular and radial extent, downsampled, smoothed by a Gaussian
around every box and combined with the binary map by a per-cell maximum.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from pcdet_atlas.models.model_utils.polar_grid import PolarGrid
from pcdet_atlas.ops.boxes import boxes_to_corners_bev

__all__ = ["box_polar_extent", "occupancy_target"]


def box_polar_extent(boxes: torch.Tensor) -> torch.Tensor:
    """``(M, 7+)`` boxes -> ``(M, 5)`` float64 ``[theta_c, dtheta_lo, dtheta_hi, r_min, r_max]``.

    ``theta_c`` is the centre's azimuth; the box spans ``theta_c + [dtheta_lo, dtheta_hi]``
    (radians, ``-pi <= lo <= 0 <= hi <= pi``, no wrap to handle) and ranges ``[r_min, r_max]``
    (the nearest point of the footprint and its farthest corner). A box over the sensor spans
    every azimuth from range 0.
    """
    b = boxes[:, :7].to(torch.float64)
    corners = boxes_to_corners_bev(b)  # (M, 4, 2)
    theta_c = torch.atan2(b[:, 1], b[:, 0])
    dtheta = (
        torch.remainder(
            torch.atan2(corners[..., 1], corners[..., 0]) - theta_c[:, None] + math.pi, 2 * math.pi
        )
        - math.pi
    )  # (M, 4)
    # the sensor in the box frame: distance from the origin to the footprint
    cos, sin = torch.cos(b[:, 6]), torch.sin(b[:, 6])
    ox = -(b[:, 0] * cos + b[:, 1] * sin)
    oy = -(-b[:, 0] * sin + b[:, 1] * cos)
    gap_x = (ox.abs() - b[:, 3] / 2).clamp(min=0)
    gap_y = (oy.abs() - b[:, 4] / 2).clamp(min=0)
    r_min = torch.hypot(gap_x, gap_y)
    over = r_min == 0
    lo = torch.where(over, -math.pi, dtheta.min(1).values)
    hi = torch.where(over, math.pi, dtheta.max(1).values)
    r_max = torch.linalg.norm(corners, dim=-1).max(1).values
    return torch.stack([theta_c, lo, hi, r_min, r_max], dim=1)


def occupancy_target(
    gt_boxes: torch.Tensor, grid: PolarGrid, pool: tuple[int, int], min_sigma: float = 0.5
) -> torch.Tensor:
    """The occupancy supervision ``(B, num_azimuth / pa, num_range / pr)`` in [0, 1].

    Args:
        gt_boxes: (B, M, 8|10) boxes, class last (0 = padding).
        grid: the polar grid; ``pool`` ``(pa, pr)``: azimuth and range cells per target cell.
        min_sigma: smallest Gaussian sigma, in target cells.

    A fine cell is occupied when its centre lies within a box's angular and radial extent; a
    target cell is occupied when one of its fine cells is (max pooling). Each box adds
    ``exp(-dt^2 / 2 st^2 - dr^2 / 2 sr^2)`` around its centre (``dt`` wrapped across the seam),
    ``st``, ``sr`` half its extent in target cells (at least ``min_sigma``), so the positives
    (value 1) are the binary cells and the Gaussian shapes the negatives around them (0.14 one
    extent beyond the box's edge).
    """
    B = gt_boxes.shape[0]
    nr, na, _ = grid.grid_size
    pa, pr = pool
    dr, da, _ = grid.cell_size
    r0 = grid.range_m[0]
    dev = gt_boxes.device
    theta_fine = -math.pi + (torch.arange(na, device=dev, dtype=torch.float64) + 0.5) * da
    r_fine = r0 + (torch.arange(nr, device=dev, dtype=torch.float64) + 0.5) * dr
    theta_t = -math.pi + (torch.arange(na // pa, device=dev, dtype=torch.float64) + 0.5) * da * pa
    r_t = r0 + (torch.arange(nr // pr, device=dev, dtype=torch.float64) + 0.5) * dr * pr
    out = torch.zeros(B, na // pa, nr // pr, dtype=torch.float32, device=dev)
    for b in range(B):
        boxes = gt_boxes[b][gt_boxes[b, :, -1] > 0].clone()
        if boxes.shape[0] == 0:
            continue
        boxes[:, 0] -= grid.origin_xy[0]  # the grid's polar coordinates are about its origin
        boxes[:, 1] -= grid.origin_xy[1]
        ext = box_polar_extent(boxes)  # (M, 5)
        theta_c, lo, hi, r_min, r_max = ext.unbind(1)
        # binary: angular membership with the seam wrapped, radial membership; (M, na) x (M, nr)
        dt = torch.remainder(theta_fine[None] - theta_c[:, None] + math.pi, 2 * math.pi) - math.pi
        in_t = (dt >= lo[:, None]) & (dt <= hi[:, None])
        in_r = (r_fine[None] >= r_min[:, None]) & (r_fine[None] <= r_max[:, None])
        binary = (in_t.to(torch.float32).T @ in_r.to(torch.float32)) > 0  # (na, nr)
        binary = F.max_pool2d(binary[None, None].float(), (pa, pr))[0, 0]  # (na/pa, nr/pr)
        # Gaussians around the box centres, in target cells
        r_c = torch.hypot(boxes[:, 0].double(), boxes[:, 1].double())
        sig_t = ((hi - lo) / (da * pa) / 2).clamp(min=min_sigma)
        sig_r = ((r_max - r_min) / (dr * pr) / 2).clamp(min=min_sigma)
        gt_dt = (
            torch.remainder(theta_t[None] - theta_c[:, None] + math.pi, 2 * math.pi) - math.pi
        ) / (da * pa)  # (M, na/pa) in cells
        gt_dr = (r_t[None] - r_c[:, None]) / (dr * pr)  # (M, nr/pr)
        gauss = torch.exp(
            -(gt_dt**2 / (2 * sig_t[:, None] ** 2))[:, :, None]
            - (gt_dr**2 / (2 * sig_r[:, None] ** 2))[:, None, :]
        ).amax(0)  # (na/pa, nr/pr)
        out[b] = torch.maximum(binary, gauss.float())
    return out
