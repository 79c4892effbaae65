"""The raycaster as it was before its elevation-band pre-filter, ray lookup table and sentinel
slot (slow test reference): a sort of the candidates' bins, compaction of the returns, and the
wedge test as bool comparisons. ``test_raycast.py`` checks the library against it bitwise,
masks and work counters alike."""

from __future__ import annotations

import math

import torch

from pcdet_atlas.attacks.counters import AttackCounters
from pcdet_atlas.attacks.raycast import _as_xyz, _sector_wedges, dual_uniforms
from pcdet_atlas.ops.lidar_model import LidarModel

_WEDGE_SLACK_M = 1e-3


def reference_wedge_rows(scene_xyz, wedges, lidar: LidarModel, rows=None) -> torch.Tensor:
    """Ascending indices of the points inside any wedge: two bool half-plane tests each."""
    if not wedges or scene_xyz.shape[0] == 0:
        return torch.zeros(0, dtype=torch.long, device=scene_xyz.device)
    dtype = scene_xyz.dtype if scene_xyz.dtype in (torch.float32, torch.float64) else torch.float32
    x, y = scene_xyz[:, 0].detach(), scene_xyz[:, 1].detach()
    if rows is not None:
        x, y = x[rows], y[rows]
    x, y = x.to(dtype), y.to(dtype)
    ox, oy = lidar.origin_xyz[:2]
    mask = None
    for a0, a1 in wedges:
        inside = _half_plane(x, y, -math.sin(a0), math.cos(a0), ox, oy)
        inside &= _half_plane(x, y, math.sin(a1), -math.cos(a1), ox, oy)
        mask = inside if mask is None else mask | inside
    found = torch.nonzero(mask).squeeze(1)
    return found if rows is None else rows[found]


def _half_plane(x, y, a: float, b: float, ox: float, oy: float) -> torch.Tensor:
    thresh = a * ox + b * oy - _WEDGE_SLACK_M
    if abs(b) >= abs(a):
        w = torch.add(y, x, alpha=a / b)
        return w >= thresh / b if b > 0 else w <= thresh / b
    w = torch.add(x, y, alpha=b / a)
    return w >= thresh / a if a > 0 else w <= thresh / a


def _sector_candidates(scene, columns, lidar, rows):
    cols = columns.tolist()
    if not cols or scene.shape[0] == 0:
        return torch.zeros(0, dtype=torch.long, device=scene.device)
    wedges = _sector_wedges(cols, lidar.azimuth_bins)
    if wedges is not None:
        return reference_wedge_rows(scene, wedges, lidar, rows)
    if rows is None:
        return torch.nonzero(torch.isfinite(scene[:, :3]).all(dim=1)).squeeze(1)
    return rows[torch.isfinite(scene[rows, :3]).all(dim=1)]


def reference_raycast_merge(
    scene_xyz, spoof_xyz, lidar: LidarModel, p_dual=0.01, generator=None, counters=None,
    candidates=None,
):  # fmt: skip
    """``raycast_merge``'s rules, the way they were computed before (returns the same)."""
    scene, spoof = _as_xyz(scene_xyz, "scene_xyz"), _as_xyz(spoof_xyz, "spoof_xyz")
    counters = AttackCounters() if counters is None else counters
    device = scene.device
    num_scene, num_spoof = scene.shape[0], spoof.shape[0]
    keep_scene = torch.ones(num_scene, dtype=torch.bool, device=device)
    keep_spoof = torch.zeros(num_spoof, dtype=torch.bool, device=device)
    if num_spoof == 0:
        return keep_scene, keep_spoof
    spoof_bin, spoof_fov, spoof_rng = lidar.bin_index(spoof)
    valid = spoof_fov & (spoof_rng > 0) & (spoof_rng <= lidar.max_range)
    spoof_idx = torch.nonzero(valid).squeeze(1)
    if spoof_idx.numel() == 0:
        counters.add(raycast_calls=1, points_examined=num_spoof)
        return keep_scene, keep_spoof
    rays, spoof_ray = torch.unique(spoof_bin[spoof_idx], sorted=True, return_inverse=True)
    num_rays = rays.numel()
    spoof_r = spoof_rng[spoof_idx]
    echo_r = torch.full((num_rays,), math.inf, dtype=torch.float64, device=device)
    echo_r.scatter_reduce_(0, spoof_ray, spoof_r, "amin")
    echo_idx = torch.full((num_rays,), num_spoof, dtype=torch.long, device=device)
    echo_idx.scatter_reduce_(
        0, spoof_ray, torch.where(spoof_r == echo_r[spoof_ray], spoof_idx, num_spoof), "amin"
    )
    columns = torch.unique(rays % lidar.azimuth_bins)
    cand = _sector_candidates(scene, columns, lidar, candidates)
    cand_bin, cand_fov, cand_rng = lidar.bin_index(scene[cand])
    pos = torch.searchsorted(rays, cand_bin).clamp_(max=num_rays - 1)
    is_ret = cand_fov & (cand_rng > 0) & torch.isfinite(cand_rng) & (rays[pos] == cand_bin)
    ret_idx, ret_ray, ret_r = cand[is_ret], pos[is_ret], cand_rng[is_ret]
    far_r = torch.full((num_rays,), -math.inf, dtype=torch.float64, device=device)
    far_r.scatter_reduce_(0, ret_ray, ret_r, "amax")
    near_r = torch.full((num_rays,), math.inf, dtype=torch.float64, device=device)
    near_r.scatter_reduce_(0, ret_ray, ret_r, "amin")
    has_scene = far_r > -math.inf
    ray_keeps = ~has_scene | (echo_r < far_r)
    keep_spoof[echo_idx[ray_keeps]] = True
    occluded = ray_keeps[ret_ray] & (ret_r > echo_r[ret_ray])
    draws = 0
    if p_dual > 0:
        primary = torch.nonzero(ray_keeps & has_scene & (echo_r < near_r)).squeeze(1)
        draws = primary.numel()
        if draws:
            u = dual_uniforms(generator, draws, device)
            dual_rays = primary[u < p_dual]
            if dual_rays.numel():
                near_idx = torch.full((num_rays,), num_scene, dtype=torch.long, device=device)
                near_idx.scatter_reduce_(
                    0, ret_ray, torch.where(ret_r == near_r[ret_ray], ret_idx, num_scene), "amin"
                )
                second = torch.zeros(num_rays, dtype=torch.bool, device=device)
                second[dual_rays] = True
                occluded &= ~(second[ret_ray] & (ret_idx == near_idx[ret_ray]))
    keep_scene[ret_idx[occluded]] = False
    counters.add(
        raycast_calls=1,
        bins_touched=num_rays,
        points_examined=int(cand.numel()) + num_spoof,
        dual_draws=draws,
    )
    return keep_scene, keep_spoof
