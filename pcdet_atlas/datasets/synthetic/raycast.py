"""Batched torch ray casting of a spinning LiDAR against ground, boxes and vertical cylinders.

The scene is a set of primitives in the vehicle frame:

- a ground plane ``z = ground_z``;
- yaw-oriented boxes ``(K, 7)`` ``[x, y, z, dx, dy, dz, yaw]`` (docs/conventions.md);
- vertical cylinders ``(L, 5)`` ``[x, y, z_min, z_max, radius]``.

One ray leaves the sensor origin per (beam, azimuth column); the nearest hit wins, so occlusion is
exact. To stay fast, each primitive is only tested against the rays of its bounding
(beam x column) window: a conservative azimuth interval from its footprint and a conservative
elevation interval from its nearest/farthest horizontal distance and its z extent. The
(primitive, ray) pairs of all windows are tested in one vectorised pass and reduced per ray with
``scatter_reduce('amin')``. Works on any torch device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

__all__ = [
    "Primitives",
    "RayHits",
    "ray_box_distance",
    "ray_cylinder_distance",
    "ray_directions",
    "column_azimuths",
    "raycast_scan",
    "GROUND_ID",
    "NO_HIT_ID",
]

#: ``RayHits.prim_id`` of a ray that hit the ground plane.
GROUND_ID = -2
#: ``RayHits.prim_id`` of a ray without a return.
NO_HIT_ID = -1
_EPS_T = 1e-3  # hits closer than 1 mm to the origin are ignored (origin inside a primitive)


@dataclass
class Primitives:
    """Scene primitives in the vehicle frame with per-primitive surface attributes.

    ``*_albedo`` is the diffuse reflectivity in [0, 1]; ``*_surface`` a surface class id of
    :mod:`pcdet_atlas.datasets.synthetic.sensor` (solid, glass, foliage, retro-reflective).
    """

    boxes: torch.Tensor  # (K, 7) [x, y, z, dx, dy, dz, yaw], m / rad
    box_albedo: torch.Tensor  # (K,)
    box_surface: torch.Tensor  # (K,) long
    cylinders: torch.Tensor  # (L, 5) [x, y, z_min, z_max, radius], m
    cyl_albedo: torch.Tensor  # (L,)
    cyl_surface: torch.Tensor  # (L,) long

    @property
    def num_boxes(self) -> int:
        return int(self.boxes.shape[0])

    @property
    def num_cylinders(self) -> int:
        return int(self.cylinders.shape[0])

    def to(self, device: str | torch.device, dtype: torch.dtype = torch.float32) -> Primitives:
        return Primitives(
            boxes=self.boxes.to(device, dtype),
            box_albedo=self.box_albedo.to(device, dtype),
            box_surface=self.box_surface.to(device, torch.long),
            cylinders=self.cylinders.to(device, dtype),
            cyl_albedo=self.cyl_albedo.to(device, dtype),
            cyl_surface=self.cyl_surface.to(device, torch.long),
        )


@dataclass
class RayHits:
    """Result of a scan, one entry per ray in ``beam * num_columns + column`` order.

    ``range_m`` is ``inf`` where nothing was hit within ``max_range``; ``prim_id`` is a box index
    ``k``, ``num_boxes + l`` for cylinder ``l``, :data:`GROUND_ID` or :data:`NO_HIT_ID`;
    ``normal`` is the unit surface normal at the hit (zeros where no hit).
    """

    range_m: torch.Tensor  # (R,)
    prim_id: torch.Tensor  # (R,) long
    normal: torch.Tensor  # (R, 3)


# ---------------------------------------------------------------------------------- rays
def column_azimuths(num_columns: int, device=None, dtype=torch.float64) -> torch.Tensor:
    """Azimuth of each column centre, ``-pi + (c + 0.5) * 2 pi / M``: ``(M,)`` radians.

    These are the centres of :class:`~pcdet_atlas.ops.lidar_model.LidarModel`'s azimuth bins,
    so every ray falls in its own (beam, azimuth) bin.
    """
    width = 2 * math.pi / num_columns
    return -math.pi + (torch.arange(num_columns, device=device, dtype=dtype) + 0.5) * width


def ray_directions(inclinations: torch.Tensor, azimuths: torch.Tensor) -> torch.Tensor:
    """Unit directions ``(B * M, 3)`` of the ray grid of ``(B,)`` elevations, ``(M,)`` azimuths."""
    el = inclinations[:, None]
    az = azimuths[None, :]
    d = torch.stack(
        [
            torch.cos(el) * torch.cos(az),
            torch.cos(el) * torch.sin(az),
            torch.sin(el).expand(-1, az.shape[1]),
        ],
        dim=-1,
    )  # (B, M, 3)
    return d.reshape(-1, 3)


# ---------------------------------------------------------------------------------- kernels
def _safe_inv(v: torch.Tensor) -> torch.Tensor:
    tiny = torch.full_like(v, 1e-12)
    v = torch.where(v.abs() < 1e-12, torch.where(v < 0, -tiny, tiny), v)
    return 1.0 / v


def ray_box_distance(origin: torch.Tensor, dirs: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """Distance along each ray to its box (slab test), ``inf`` on a miss.

    Args:
        origin: ``(3,)`` ray origin.
        dirs: ``(P, 3)`` unit directions.
        boxes: ``(P, 7)`` one box per ray.
    Returns:
        ``(P,)`` metres; a ray starting inside its box gives ``inf`` (no self-hit).
    """
    cos, sin = torch.cos(boxes[:, 6]), torch.sin(boxes[:, 6])
    rel = origin[None, :] - boxes[:, 0:3]  # (P, 3)
    ox = rel[:, 0] * cos + rel[:, 1] * sin
    oy = -rel[:, 0] * sin + rel[:, 1] * cos
    dx = dirs[:, 0] * cos + dirs[:, 1] * sin
    dy = -dirs[:, 0] * sin + dirs[:, 1] * cos
    half = boxes[:, 3:6] / 2
    o_loc = torch.stack([ox, oy, rel[:, 2]], dim=1)  # (P, 3)
    inv = _safe_inv(torch.stack([dx, dy, dirs[:, 2]], dim=1))  # (P, 3)
    t1 = (-half - o_loc) * inv
    t2 = (half - o_loc) * inv
    t_near = torch.minimum(t1, t2).amax(dim=1)
    t_far = torch.maximum(t1, t2).amin(dim=1)
    hit = (t_near <= t_far) & (t_near > _EPS_T)
    return torch.where(hit, t_near, torch.full_like(t_near, math.inf))


def ray_cylinder_distance(
    origin: torch.Tensor, dirs: torch.Tensor, cylinders: torch.Tensor
) -> torch.Tensor:
    """Distance along each ray to its vertical capped cylinder, ``inf`` on a miss.

    Args:
        origin: ``(3,)``; dirs: ``(P, 3)`` unit; cylinders: ``(P, 5)`` ``[x, y, z0, z1, r]``.
    Returns:
        ``(P,)`` metres.
    """
    inf = math.inf
    ox = origin[0] - cylinders[:, 0]
    oy = origin[1] - cylinders[:, 1]
    z0, z1, r = cylinders[:, 2], cylinders[:, 3], cylinders[:, 4]
    dx, dy, dz = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    a = dx * dx + dy * dy
    b = 2 * (ox * dx + oy * dy)
    c = ox * ox + oy * oy - r * r
    disc = b * b - 4 * a * c
    ok = (disc >= 0) & (a > 1e-12)
    sq = torch.sqrt(torch.clamp(disc, min=0))
    t_side = (-b - sq) / (2 * torch.clamp(a, min=1e-12))
    z_side = origin[2] + t_side * dz
    side_ok = ok & (t_side > _EPS_T) & (z_side >= z0) & (z_side <= z1)
    t = torch.where(side_ok, t_side, torch.full_like(t_side, inf))
    inv_dz = _safe_inv(dz)
    for zc in (z0, z1):
        t_cap = (zc - origin[2]) * inv_dz
        px = ox + t_cap * dx
        py = oy + t_cap * dy
        cap_ok = (t_cap > _EPS_T) & (px * px + py * py <= r * r) & (dz.abs() > 1e-12)
        t = torch.where(cap_ok & (t_cap < t), t_cap, t)
    return t


def _box_normals(origin, dirs, boxes, t):
    """Outward unit normals ``(P, 3)`` of boxes at the hit ``origin + t * dirs``."""
    cos, sin = torch.cos(boxes[:, 6]), torch.sin(boxes[:, 6])
    p = origin[None, :] + t[:, None] * dirs - boxes[:, 0:3]
    lx = p[:, 0] * cos + p[:, 1] * sin
    ly = -p[:, 0] * sin + p[:, 1] * cos
    loc = torch.stack([lx, ly, p[:, 2]], dim=1)
    ratio = loc.abs() / (boxes[:, 3:6] / 2).clamp(min=1e-6)
    axis = ratio.argmax(dim=1)
    n_loc = torch.zeros_like(loc)
    n_loc.scatter_(1, axis[:, None], torch.sign(loc.gather(1, axis[:, None])))
    nx = n_loc[:, 0] * cos - n_loc[:, 1] * sin
    ny = n_loc[:, 0] * sin + n_loc[:, 1] * cos
    return torch.stack([nx, ny, n_loc[:, 2]], dim=1)


def _cylinder_normals(origin, dirs, cylinders, t):
    p = origin[None, :] + t[:, None] * dirs
    rx = p[:, 0] - cylinders[:, 0]
    ry = p[:, 1] - cylinders[:, 1]
    radial = torch.sqrt(rx * rx + ry * ry)
    on_side = (radial >= cylinders[:, 4] * (1 - 1e-3)) & (p[:, 2] > cylinders[:, 2] + 1e-4)
    on_side &= p[:, 2] < cylinders[:, 3] - 1e-4
    up = torch.where(p[:, 2] >= (cylinders[:, 2] + cylinders[:, 3]) / 2, 1.0, -1.0).to(p.dtype)
    scale = radial.clamp(min=1e-9)
    n = torch.stack(
        [
            torch.where(on_side, rx / scale, torch.zeros_like(rx)),
            torch.where(on_side, ry / scale, torch.zeros_like(ry)),
            torch.where(on_side, torch.zeros_like(rx), up),
        ],
        dim=1,
    )
    return n


# ---------------------------------------------------------------------------------- culling
def _windows(az_center, az_half, el_lo, el_hi, inclinations, num_columns):
    """Per primitive: first beam, beam count, first column, column count of its ray window."""
    width = 2 * math.pi / num_columns
    full = az_half >= math.pi - 1e-9
    lo = az_center - az_half
    hi = az_center + az_half
    # one extra column each side: float32 bounds of grazing rays must never cull a hit
    c_lo = torch.ceil((lo + math.pi) / width - 0.5).long() - 1
    c_hi = torch.floor((hi + math.pi) / width - 0.5).long() + 1
    n_col = c_hi - c_lo + 1
    full = full | (n_col >= num_columns)
    c_lo = torch.where(full, torch.zeros_like(c_lo), c_lo)
    n_col = torch.where(full, torch.full_like(n_col, num_columns), n_col).clamp(min=0)
    b_lo = torch.searchsorted(inclinations, el_lo.contiguous())
    b_hi = torch.searchsorted(inclinations, el_hi.contiguous(), right=True) - 1
    n_beam = (b_hi - b_lo + 1).clamp(min=0)
    return b_lo, n_beam, c_lo, n_col


def _elevation_bounds(z_lo, z_hi, d_min, d_max, oz):
    """Conservative elevation interval of a z-slab at horizontal distance in [d_min, d_max]."""
    top = z_hi - oz
    bot = z_lo - oz
    el_hi = torch.where(top > 0, torch.atan2(top, d_min), torch.atan2(top, d_max))
    el_lo = torch.where(bot < 0, torch.atan2(bot, d_min), torch.atan2(bot, d_max))
    margin = 1e-4  # rad, far above float32 rounding of the bounds
    return el_lo - margin, el_hi + margin


def _box_windows(origin, boxes, inclinations, num_columns):
    cos, sin = torch.cos(boxes[:, 6]), torch.sin(boxes[:, 6])
    rel = boxes[:, 0:2] - origin[None, 0:2]  # (K, 2) box centre relative to the sensor
    hx, hy = boxes[:, 3] / 2, boxes[:, 4] / 2
    # sensor position in the box frame -> distance to the footprint rectangle
    sx = -(rel[:, 0] * cos + rel[:, 1] * sin)
    sy = -(-rel[:, 0] * sin + rel[:, 1] * cos)
    ex = (sx.abs() - hx).clamp(min=0)
    ey = (sy.abs() - hy).clamp(min=0)
    d_min = torch.sqrt(ex * ex + ey * ey)
    sgn = boxes.new_tensor([[1, 1], [1, -1], [-1, -1], [-1, 1]])  # (4, 2)
    cx = sgn[None, :, 0] * hx[:, None]
    cy = sgn[None, :, 1] * hy[:, None]
    corner_x = rel[:, 0:1] + cx * cos[:, None] - cy * sin[:, None]  # (K, 4)
    corner_y = rel[:, 1:2] + cx * sin[:, None] + cy * cos[:, None]
    d_max = torch.sqrt(corner_x**2 + corner_y**2).amax(dim=1)
    az_c = torch.atan2(rel[:, 1], rel[:, 0])
    corner_az = torch.atan2(corner_y, corner_x) - az_c[:, None]
    corner_az = torch.remainder(corner_az + math.pi, 2 * math.pi) - math.pi
    a_lo, a_hi = corner_az.amin(dim=1), corner_az.amax(dim=1)
    center = az_c + (a_lo + a_hi) / 2
    half = (a_hi - a_lo) / 2 + 1e-6
    inside = d_min <= 1e-6
    half = torch.where(inside, torch.full_like(half, math.pi), half)
    el_lo, el_hi = _elevation_bounds(
        boxes[:, 2] - boxes[:, 5] / 2, boxes[:, 2] + boxes[:, 5] / 2, d_min, d_max, origin[2]
    )
    return _windows(center, half, el_lo, el_hi, inclinations, num_columns)


def _cylinder_windows(origin, cylinders, inclinations, num_columns):
    rel = cylinders[:, 0:2] - origin[None, 0:2]
    d = torch.sqrt((rel**2).sum(dim=1))
    r = cylinders[:, 4]
    az_c = torch.atan2(rel[:, 1], rel[:, 0])
    half = torch.where(
        d > r, torch.asin((r / d.clamp(min=1e-9)).clamp(max=1.0)), torch.full_like(d, math.pi)
    )
    half = half + 1e-6
    el_lo, el_hi = _elevation_bounds(
        cylinders[:, 2], cylinders[:, 3], (d - r).clamp(min=0), d + r, origin[2]
    )
    return _windows(az_c, half, el_lo, el_hi, inclinations, num_columns)


def _window_pairs(b_lo, n_beam, c_lo, n_col, num_columns):
    """Expand windows into (primitive index, ray id) pairs, both ``(P,)`` long."""
    counts = n_beam * n_col
    total = int(counts.sum())
    if total == 0:
        empty = torch.zeros(0, dtype=torch.long, device=counts.device)
        return empty, empty
    prim = torch.repeat_interleave(torch.arange(counts.numel(), device=counts.device), counts)
    start = torch.cumsum(counts, 0) - counts
    local = torch.arange(total, device=counts.device) - start[prim]
    nc = n_col[prim]
    beam = b_lo[prim] + torch.div(local, nc, rounding_mode="floor")
    col = torch.remainder(c_lo[prim] + torch.remainder(local, nc), num_columns)
    return prim, beam * num_columns + col


# ---------------------------------------------------------------------------------- scan
@torch.no_grad()
def raycast_scan(
    origin: torch.Tensor,
    inclinations: torch.Tensor,
    num_columns: int,
    prims: Primitives,
    ground_z: float | None = 0.0,
    max_range: float = 75.0,
    chunk_pairs: int = 4_000_000,
    dirs: torch.Tensor | None = None,
) -> RayHits:
    """Cast the full ``(B, M)`` ray grid of a spinning LiDAR; the nearest hit wins.

    Args:
        origin: ``(3,)`` sensor position in the vehicle frame, m.
        inclinations: ``(B,)`` ascending beam elevations, rad.
        num_columns: azimuth columns ``M`` (ray azimuths at :func:`column_azimuths`).
        prims: scene primitives on the same device and dtype as ``origin``.
        ground_z: height of the ground plane, or ``None`` for no ground.
        max_range: hits farther than this give no return, m.
        chunk_pairs: bound on (primitive, ray) pairs tested at once (memory).
        dirs: the grid's ``(B * M, 3)`` directions if already computed (must match).
    Returns:
        :class:`RayHits` over ``B * M`` rays (ray id ``beam * M + column``).
    """
    device, dtype = origin.device, origin.dtype
    incl = inclinations.to(device, dtype)
    if dirs is None:
        dirs = ray_directions(incl, column_azimuths(num_columns, device, dtype))  # (R, 3)
    num_rays = dirs.shape[0]
    best = torch.full((num_rays,), math.inf, device=device, dtype=dtype)
    prim_id = torch.full((num_rays,), NO_HIT_ID, device=device, dtype=torch.long)

    kinds = []
    if prims.num_boxes:
        w = _box_windows(origin, prims.boxes, incl, num_columns)
        kinds.append((prims.boxes, ray_box_distance, w, 0))
    if prims.num_cylinders:
        w = _cylinder_windows(origin, prims.cylinders, incl, num_columns)
        kinds.append((prims.cylinders, ray_cylinder_distance, w, prims.num_boxes))
    pair_results = []
    for params, kernel, (b_lo, n_beam, c_lo, n_col), id_offset in kinds:
        counts = n_beam * n_col
        # split primitives into groups of bounded pair count (memory), in order
        csum = torch.cumsum(counts, 0)
        group = torch.div(csum - 1, chunk_pairs, rounding_mode="floor")
        for g in torch.unique(group).tolist():
            sel = torch.nonzero(group == g).flatten()
            p_loc, ray = _window_pairs(b_lo[sel], n_beam[sel], c_lo[sel], n_col[sel], num_columns)
            if ray.numel() == 0:
                continue
            p = sel[p_loc]
            t = kernel(origin, dirs[ray], params[p])
            hit = torch.isfinite(t)
            ray, p, t = ray[hit], p[hit], t[hit]
            best.scatter_reduce_(0, ray, t, reduce="amin")
            pair_results.append((ray, p + id_offset, t))
    for ray, pid, t in pair_results:
        win = t == best[ray]
        prim_id.scatter_reduce_(0, ray[win], pid[win], reduce="amax")

    normal = torch.zeros((num_rays, 3), device=device, dtype=dtype)
    if ground_z is not None:
        dz = dirs[:, 2]
        t_g = torch.where(
            dz < -1e-9, (ground_z - origin[2]) / torch.where(dz < -1e-9, dz, -1.0), math.inf
        )
        ground = (t_g < best) & (t_g > _EPS_T)
        best = torch.where(ground, t_g, best)
        prim_id = torch.where(ground, torch.full_like(prim_id, GROUND_ID), prim_id)
        normal[ground, 2] = 1.0
    too_far = best > max_range
    best = torch.where(too_far, torch.full_like(best, math.inf), best)
    prim_id = torch.where(too_far, torch.full_like(prim_id, NO_HIT_ID), prim_id)

    is_box = (prim_id >= 0) & (prim_id < prims.num_boxes)
    if is_box.any():
        idx = torch.nonzero(is_box).flatten()
        normal[idx] = _box_normals(origin, dirs[idx], prims.boxes[prim_id[idx]], best[idx])
    is_cyl = prim_id >= prims.num_boxes
    if is_cyl.any():
        idx = torch.nonzero(is_cyl).flatten()
        cyl = prims.cylinders[prim_id[idx] - prims.num_boxes]
        normal[idx] = _cylinder_normals(origin, dirs[idx], cyl, best[idx])
    return RayHits(range_m=best, prim_id=prim_id, normal=normal)
