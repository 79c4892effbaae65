"""The sensor-level raycaster (docs/attacks.md): merge spoofed points into a scan, one echo per ray.

Each (azimuth bin, beam) pair of a :class:`~pcdet_atlas.ops.lidar_model.LidarModel` is one
ray. :func:`raycast_merge` decides, per ray, which spoofed and which scene points a real sensor
would report, and returns keep masks. It is a sparse z-buffer: only the rays hit by the spoof are
built, and only the scene points in the spoof's azimuth sector are binned.

How the work stays proportional to the spoof's sector:

1. The spoof points are binned exactly (float64, :meth:`LidarModel.bin_index`).
2. Their occupied azimuth columns are grouped into a few circular intervals (neighbouring runs
   merged, wide ones split into pieces of at most 90°), each widened by a small angular margin.
3. A scene point is a *candidate* if it lies in one of these wedges, tested with two cross
   products per wedge in the scene's own dtype (no trigonometry over the whole scene; the tests
   compare in place into float 0/1, cheaper on CPU than comparisons into new bool tensors). The
   margins (1e-4 rad, 1 mm at the apex) are far above float32 rounding, so no point whose exact
   column is occupied can be missed. A caller that already holds a sector containing the
   spoof's (the injection: one wedge around the phantom serves its ground estimate too) passes
   its rows.
4. Candidates outside the elevation band of the spoof's beams are dropped (two half-space tests
   in float64 with a 1e-4 rad margin, :func:`_elevation_band_rows`), again a superset.
5. Only the remaining candidates are binned exactly; a lookup table over the spoof's beams gives
   each its ray slot (no sort, no binary search), and per-ray arrays carry one extra slot that
   absorbs invalid spoof points and candidates of other rays, so no mask is compacted. Ties and
   minima use a two-pass ``scatter_reduce('amin')`` (min range per ray, then min index among
   the points achieving it), which is deterministic on CPU and GPU; no ``index_put_`` with
   duplicate indices.

One implementation, in torch, on every device: CPU tensors run the same code as CUDA ones.

Scene points that are never touched: outside the field of view, at range 0 (no direction), or
non-finite. A scene point beyond ``max_range`` *is* a return of its ray (the data is the
measurement; ``max_range`` bounds what the spoofer can inject, not what the scan holds).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from pcdet_atlas.attacks.counters import COUNTERS, AttackCounters
from pcdet_atlas.ops.lidar_model import LidarModel

#: Sources of the dual-return draws (rule 5): a generator, or uniforms drawn beforehand.
Generator = torch.Generator | np.random.Generator | np.ndarray

__all__ = [
    "raycast_merge",
    "azimuth_sector_candidates",
    "disc_wedges",
    "dual_uniforms",
    "wedge_rows",
]

#: Angular margin added to each side of a candidate wedge, radians (>> float32 atan error).
_WEDGE_MARGIN_RAD = 1e-4
#: Absolute slack of the wedge half-plane tests, metres (covers points near the sensor axis).
_WEDGE_SLACK_M = 1e-3
#: At most this many wedges before the closest azimuth intervals are merged.
_MAX_INTERVALS = 8
#: Widest wedge (the half-plane test needs < pi); wider intervals are split.
_MAX_WEDGE_RAD = math.pi / 2
#: Occupied azimuth runs at most this far apart (radians) share one wedge: a wedge costs two
#: passes over the whole scene, the columns of a small gap only a few more candidates.
_MERGE_GAP_RAD = math.radians(5.0)
#: Above this covered fraction of the circle, every scene point is a candidate (cheaper).
_FULL_SCAN_FRACTION = 0.5
#: Elevation band pre-filter: margin beyond the spoof's beams (rad, >> float64 atan2 error),
#: absolute slack of its tests (m, points near the sensor) and the steepest band edge it tests.
_BAND_MARGIN_RAD = 1e-4
_BAND_SLACK_M = 1e-3
_BAND_MAX_ELEVATION_RAD = 1.2


def _as_xyz(points, name: str) -> torch.Tensor:
    pts = torch.as_tensor(points)
    if pts.dim() != 2 or pts.shape[1] < 3:
        raise ValueError(f"{name} must have shape (N, 3+), got {tuple(pts.shape)}")
    if not pts.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got {pts.dtype}")
    pts = pts if pts.shape[1] == 3 else pts[:, :3]
    return pts.detach() if pts.requires_grad else pts  # masks only: no graph


def _azimuth_intervals(
    columns: Sequence[int] | np.ndarray, num_columns: int, max_gap: int = 0
) -> list[tuple[int, int]]:
    """Circular intervals ``(lo, hi)`` (``hi`` may exceed ``num_columns - 1`` when wrapping)
    covering the sorted distinct occupied columns, at most ``_MAX_INTERVALS`` of them; runs
    separated by at most ``max_gap`` empty columns are one interval."""
    runs: list[list[int]] = []
    # a Python loop over the few hundred columns at most: cheaper than vectorised run finding
    # (np.diff & co. are Python-level wrappers, and in a loader their code is cold)
    for c in columns.tolist() if isinstance(columns, np.ndarray) else columns:
        if runs and c <= runs[-1][1] + 1 + max_gap:
            runs[-1][1] = c
        else:
            runs.append([c, c])
    if len(runs) > 1 and runs[0][0] + num_columns - runs[-1][1] - 1 <= max_gap:
        last = runs.pop()  # a run through the +-pi seam: M-1 -> 0
        runs[0] = [last[0], runs[0][1] + num_columns]
    runs.sort()
    while len(runs) > _MAX_INTERVALS:
        # merge the two circular neighbours with the smallest gap
        gaps = [
            (runs[(j + 1) % len(runs)][0] + (num_columns if j == len(runs) - 1 else 0)) - runs[j][1]
            for j in range(len(runs))
        ]
        j = int(np.argmin(gaps))
        if j == len(runs) - 1:
            first = runs.pop(0)
            runs[-1][1] = first[1] + num_columns
        else:
            runs[j][1] = runs[j + 1][1]
            runs.pop(j + 1)
    return [(lo, hi) for lo, hi in runs]


def _sector_wedges(
    columns: Sequence[int] | np.ndarray, num_columns: int
) -> list[tuple[float, float]] | None:
    """The candidate wedges ``(a0, a1)`` (radians, each narrower than pi) covering the sorted
    distinct azimuth ``columns`` with their margins, or ``None`` when they cover so much of the
    circle that testing every point is cheaper."""
    width = 2 * math.pi / num_columns
    max_gap = int(_MERGE_GAP_RAD / width)
    wedges: list[tuple[float, float]] = []
    for lo, hi in _azimuth_intervals(columns, num_columns, max_gap):
        a0 = -math.pi + lo * width - _WEDGE_MARGIN_RAD
        a1 = -math.pi + (hi + 1) * width + _WEDGE_MARGIN_RAD
        pieces = max(1, math.ceil((a1 - a0) / _MAX_WEDGE_RAD))
        step = (a1 - a0) / pieces
        wedges.extend((a0 + p * step, a0 + (p + 1) * step) for p in range(pieces))
    covered = sum(b - a for a, b in wedges)
    return None if covered >= _FULL_SCAN_FRACTION * 2 * math.pi else wedges


def azimuth_sector_candidates(
    scene_xyz: torch.Tensor,
    columns: torch.Tensor,
    lidar: LidarModel,
    rows: torch.Tensor | None = None,
) -> torch.Tensor:
    """Indices of the scene points that may fall in the given azimuth columns.

    A superset, never missing a point whose exact column (:meth:`LidarModel.azimuth_index` of
    its float64 azimuth) is in ``columns``; the extra points are those within a tiny margin of
    the sector or near the sensor axis. Non-finite points are never returned.

    Args:
        scene_xyz: ``(N, 3+)`` float points, vehicle frame, metres.
        columns: ``(K,)`` long, distinct occupied azimuth columns in ``[0, M)``, sorted.
        lidar: the sensor model (origin, ``M = azimuth_bins``).
        rows: ``(R,)`` long ascending indices of the only rows to test (a wider sector the
            caller has already cut out, e.g. with :func:`disc_wedges`); ``None``: every row.

    Returns:
        ``(C,)`` long indices into ``scene_xyz``, ascending (a subset of ``rows``).
    """
    device = scene_xyz.device
    cols = columns.tolist()
    if not cols or scene_xyz.shape[0] == 0:
        return torch.zeros(0, dtype=torch.long, device=device)
    wedges = _sector_wedges(cols, lidar.azimuth_bins)
    if wedges is not None:
        return wedge_rows(scene_xyz, wedges, lidar, rows)
    if rows is None:  # most of the circle: every finite point
        return torch.nonzero(torch.isfinite(scene_xyz[:, :3]).all(dim=1)).squeeze(1)
    return rows[torch.isfinite(scene_xyz[rows, :3]).all(dim=1)]


def wedge_rows(
    scene_xyz: torch.Tensor,
    wedges: Sequence[tuple[float, float]],
    lidar: LidarModel,
    rows: torch.Tensor | None = None,
) -> torch.Tensor:
    """Ascending indices of the scene points inside any of the ``wedges`` ``(a0, a1)`` (radians,
    each narrower than pi, apex at the sensor origin, with the half-plane tests' slack), among
    ``rows`` (ascending indices) or every point.

    Args:
        scene_xyz: ``(N, 3+)`` float points, vehicle frame, metres (a strided view is fine).
    Returns:
        ``(C,)`` long indices into ``scene_xyz``.
    """
    if not wedges or scene_xyz.shape[0] == 0:
        return torch.zeros(0, dtype=torch.long, device=scene_xyz.device)
    dtype = scene_xyz.dtype if scene_xyz.dtype in (torch.float32, torch.float64) else torch.float32
    x, y = scene_xyz[:, 0].detach(), scene_xyz[:, 1].detach()  # (N,)
    if rows is not None:
        x, y = x[rows], y[rows]
    if x.dtype != dtype:
        x, y = x.to(dtype), y.to(dtype)
    ox, oy = lidar.origin_xyz[:2]
    inside = None  # (N,) float 0/1
    for a0, a1 in wedges:
        # inside iff cross(u0, p - o) >= 0 and cross(p - o, u1) >= 0 (wedge narrower than pi)
        flags = _half_plane(x, y, -math.sin(a0), math.cos(a0), ox, oy)
        torch.minimum(flags, _half_plane(x, y, math.sin(a1), -math.cos(a1), ox, oy), out=flags)
        inside = flags if inside is None else torch.maximum(inside, flags, out=inside)
    found = torch.nonzero(inside.bool()).squeeze(1)
    return found if rows is None else rows[found]


def disc_wedges(lidar: LidarModel, center_xy, radius: float) -> list[tuple[float, float]] | None:
    """Wedges (apex at the sensor origin) holding every scene point of every azimuth column
    that meets the disc of ``radius`` (m) around ``center_xy`` (vehicle frame), or ``None``
    when the disc reaches the sensor's axis or the wedges would be most of the circle (no
    pre-filter pays off). Plain float arithmetic: no array work.

    The disc's azimuth interval is widened by one column (a point's column extends at most
    one column width beyond its azimuth) and twice the candidate margin on each side (one for
    :func:`azimuth_sector_candidates`'s margin, one for rounding), so the rows of these
    wedges are a superset of the sector candidates of any points inside the disc.
    """
    dx, dy = (
        float(center_xy[0]) - lidar.origin_xyz[0],
        float(center_xy[1]) - lidar.origin_xyz[1],
    )
    dist = math.hypot(dx, dy)
    if not dist > radius:
        return None
    theta, half = math.atan2(dy, dx), math.asin(radius / dist)
    pad = 2 * math.pi / lidar.azimuth_bins + 2 * _WEDGE_MARGIN_RAD
    a0, a1 = theta - half - pad, theta + half + pad
    if a1 - a0 >= _FULL_SCAN_FRACTION * 2 * math.pi:
        return None
    pieces = max(1, math.ceil((a1 - a0) / _MAX_WEDGE_RAD))
    step = (a1 - a0) / pieces
    return [(a0 + p * step, a0 + (p + 1) * step) for p in range(pieces)]


def _half_plane(
    x: torch.Tensor, y: torch.Tensor, a: float, b: float, ox: float, oy: float
) -> torch.Tensor:
    """``a (x - ox) + b (y - oy) >= -slack`` as a fresh ``(N,)`` float tensor of 0/1 (NaN: 0).

    Divides by the larger of ``|a|``, ``|b|`` so that one fused ``add(.., alpha=..)`` suffices,
    then compares in place (a comparison into a new bool tensor is several times slower on CPU).
    """
    thresh = a * ox + b * oy - _WEDGE_SLACK_M
    if abs(b) >= abs(a):
        w = torch.add(y, x, alpha=a / b)  # (N,)
        return w.ge_(thresh / b) if b > 0 else w.le_(thresh / b)
    w = torch.add(x, y, alpha=b / a)  # (N,)
    return w.ge_(thresh / a) if a > 0 else w.le_(thresh / a)


def raycast_merge(
    scene_xyz: torch.Tensor,
    spoof_xyz: torch.Tensor,
    lidar: LidarModel,
    p_dual: float = 0.01,
    generator: Generator | None = None,
    counters: AttackCounters | None = None,
    candidates: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Merge spoofed points into a scan, one echo per ray (rules 1-6 of docs/attacks.md).

    Per ray (azimuth bin, beam) hit by the spoof:

    1. Only the nearest spoof point survives (ties: the lower index).
    2. Spoof points outside the field of view, at range 0, or beyond ``max_range`` are dropped.
    3. A spoof echo at or behind the farthest scene return of its ray is dropped.
    4. Otherwise it is kept and every scene return of that ray farther than it is removed.
    5. If it is nearer than every scene return of the ray (the primary echo), the nearest scene
       return (ties: lower index) is kept as a second echo with probability ``p_dual``.
    6. Rays without scene returns keep their spoof echo; rays without spoof are untouched.

    Scene points outside the field of view, at range 0 or non-finite are never touched; scene
    points beyond ``max_range`` are returns of their ray like any other.

    Randomness: one uniform per primary ray, in ascending ray id order, drawn from
    ``generator`` on its own device (a numpy generator on the host; so one generator gives the
    same draws for CPU and CUDA inputs). No draw is made when ``p_dual = 0`` or when no ray is
    primary.

    Args:
        scene_xyz: ``(N, 3+)`` float scene points, vehicle frame, metres (extra columns ignored).
        spoof_xyz: ``(M, 3+)`` float spoofed points, same frame and device.
        lidar: the sensor model.
        p_dual: dual-return probability in ``[0, 1]``.
        generator: ``torch.Generator``, numpy ``Generator`` or 1-D array of uniforms,
            required when ``p_dual > 0`` (:func:`dual_uniforms`).
        counters: where to count the work; the per-process ``COUNTERS`` by default.
        candidates: ``(R,)`` long ascending scene rows known to hold every scene point of the
            spoof's azimuth columns (a wider sector); ``None``: the whole scene is tested.

    Returns:
        keep_scene: ``(N,)`` bool, on the scene's device.
        keep_spoof: ``(M,)`` bool.
    """
    scene = _as_xyz(scene_xyz, "scene_xyz")
    spoof = _as_xyz(spoof_xyz, "spoof_xyz")
    if scene.device != spoof.device:
        raise ValueError(f"scene_xyz on {scene.device} but spoof_xyz on {spoof.device}")
    p_dual = _check_dual(p_dual, generator)
    if not bool(torch.isfinite(spoof).all()):
        raise ValueError("spoof_xyz contains non-finite coordinates")
    counters = COUNTERS if counters is None else counters
    device = scene.device
    num_scene, num_spoof = scene.shape[0], spoof.shape[0]
    keep_scene = torch.ones(num_scene, dtype=torch.bool, device=device)
    keep_spoof = torch.zeros(num_spoof, dtype=torch.bool, device=device)
    if num_spoof == 0:
        return keep_scene, keep_spoof

    # ---- spoof rays (rules 1, 2). Per-ray arrays have K + 1 slots: slot K collects the invalid
    # spoof points and the scene candidates that are no return of a spoof ray (never kept).
    spoof_bin, spoof_fov, spoof_rng = lidar.bin_index(spoof)  # (M,) long, bool, float64
    valid = spoof_fov & (spoof_rng > 0) & (spoof_rng <= lidar.max_range)
    sentinel = lidar.num_bins  # after every ray id: the last of the sorted rays
    rays, spoof_ray = torch.unique(
        torch.where(valid, spoof_bin, sentinel), sorted=True, return_inverse=True
    )  # (K or K + 1,) ascending ray ids, (M,) slot of each spoof point
    num_rays = rays.numel() - (int(rays[-1]) == sentinel)  # K
    if num_rays == 0:
        counters.add(raycast_calls=1, points_examined=num_spoof)
        return keep_scene, keep_spoof
    rays = rays[:num_rays]  # (K,)
    echo_r = torch.full((num_rays + 1,), math.inf, dtype=torch.float64, device=device)
    echo_r.scatter_reduce_(0, spoof_ray, spoof_rng, "amin")  # (K+1,) nearest spoof range
    echo_idx = torch.full((num_rays + 1,), num_spoof, dtype=torch.long, device=device)
    spoof_ids = torch.arange(num_spoof, device=device)
    echo_idx.scatter_reduce_(
        0, spoof_ray, torch.where(spoof_rng == echo_r[spoof_ray], spoof_ids, num_spoof), "amin"
    )  # (K+1,) lowest index achieving it

    # ---- scene returns of those rays, from the candidates of the sector only
    columns = torch.unique(rays % lidar.azimuth_bins)  # sorted
    cand = azimuth_sector_candidates(scene, columns, lidar, candidates)  # (C,)
    beam_lo, beam_hi = int(rays[0]) // lidar.azimuth_bins, int(rays[-1]) // lidar.azimuth_bins
    band = _elevation_band_rows(scene, cand, lidar, beam_lo, beam_hi)  # (C',) of the spoof's beams
    cand_bin, cand_fov, cand_rng = lidar.bin_index(scene[band])  # (C',)
    pos = _ray_slots(rays, cand_bin, beam_lo, beam_hi, lidar.azimuth_bins)  # (C',) K: none
    is_ret = cand_fov & (cand_rng > 0) & torch.isfinite(cand_rng)  # returns of some ray
    slot = torch.where(is_ret, pos, num_rays)  # (C',) ray slot of each return, K otherwise
    far_r = torch.full((num_rays + 1,), -math.inf, dtype=torch.float64, device=device)
    far_r.scatter_reduce_(0, slot, cand_rng, "amax")  # (K+1,) farthest scene return
    near_r = torch.full((num_rays + 1,), math.inf, dtype=torch.float64, device=device)
    near_r.scatter_reduce_(0, slot, cand_rng, "amin")  # (K+1,) nearest scene return
    has_scene = far_r > -math.inf

    # ---- rules 3, 4, 6
    ray_keeps = ~has_scene | (echo_r < far_r)  # (K+1,)
    ray_keeps[num_rays] = False
    keep_spoof[echo_idx[:num_rays]] = ray_keeps[:num_rays]  # one distinct echo per ray
    occluded = ray_keeps[slot] & (cand_rng > echo_r[slot])  # (C',)

    # ---- rule 5: dual returns, drawn only in primary rays
    draws = 0
    if p_dual > 0:
        primary = torch.nonzero(ray_keeps & has_scene & (echo_r < near_r)).squeeze(1)  # (P,)
        draws = primary.numel()
        if draws:
            u = dual_uniforms(generator, draws, device)
            dual_rays = primary[u < p_dual]
            if dual_rays.numel():
                near_idx = torch.full((num_rays + 1,), num_scene, dtype=torch.long, device=device)
                near_idx.scatter_reduce_(
                    0, slot, torch.where(cand_rng == near_r[slot], band, num_scene), "amin"
                )
                second = torch.zeros(num_rays + 1, dtype=torch.bool, device=device)
                second[dual_rays] = True
                occluded &= ~(second[slot] & (band == near_idx[slot]))
    keep_scene[band] = ~occluded  # distinct rows; the others stay True
    counters.add(
        raycast_calls=1,
        bins_touched=num_rays,
        points_examined=int(cand.numel()) + num_spoof,
        dual_draws=draws,
    )
    return keep_scene, keep_spoof


def _elevation_band_rows(
    scene: torch.Tensor, rows: torch.Tensor, lidar: LidarModel, beam_lo: int, beam_hi: int
) -> torch.Tensor:
    """The ``rows`` (ascending) whose points may be binned into beams ``beam_lo..beam_hi``.

    A superset, never missing a point whose exact elevation (:meth:`LidarModel.bin_index`) lies
    in those beams: two half-space tests ``dz >= tan(lo) * horiz`` and ``dz <= tan(hi) * horiz``
    in float64 against the band widened by ``_BAND_MARGIN_RAD`` (and ``_BAND_SLACK_M`` near the
    sensor), far above float64 rounding. Non-finite points are dropped (they are no returns).
    Every row is kept for sensors with laser offsets (a beam's elevation depends on the distance)
    and a band edge steeper than ``_BAND_MAX_ELEVATION_RAD`` is not tested.
    """
    if lidar.offsets is not None or rows.numel() == 0:
        return rows
    mids = lidar.midpoints_np
    lo = (float(mids[beam_lo - 1]) if beam_lo > 0 else lidar.fov_min) - _BAND_MARGIN_RAD
    hi = (float(mids[beam_hi]) if beam_hi < mids.size else lidar.fov_max) + _BAND_MARGIN_RAD
    test_lo, test_hi = lo > -_BAND_MAX_ELEVATION_RAD, hi < _BAND_MAX_ELEVATION_RAD
    if not (test_lo or test_hi):
        return rows
    rel = scene.index_select(0, rows).to(torch.float64)  # (C, 3)
    rel -= lidar._constants(rel.device)[0]
    dx, dy, dz = rel.unbind(1)  # (C,) each
    horiz = torch.hypot(dx, dy)
    keep = None
    if test_lo:
        keep = torch.add(dz, horiz, alpha=-math.tan(lo)) >= -_BAND_SLACK_M
    if test_hi:
        below = torch.add(dz, horiz, alpha=-math.tan(hi)) <= _BAND_SLACK_M
        keep = below if keep is None else keep & below
    return rows[keep]


def _ray_slots(
    rays: torch.Tensor, bins: torch.Tensor, beam_lo: int, beam_hi: int, azimuth_bins: int
) -> torch.Tensor:
    """Slot in the ascending ``rays`` (``(K,)`` long ids of beams ``beam_lo..beam_hi``) of each
    of ``bins`` (``(C,)`` long), ``K`` for a bin that is none of them.

    A lookup table over the rays' beams with one "none" cell at each end, where every bin
    outside the beams is clamped: no sort and no binary search.
    """
    num_rays = rays.numel()
    base, size = beam_lo * azimuth_bins - 1, (beam_hi - beam_lo + 1) * azimuth_bins + 2
    table = torch.full((size,), num_rays, dtype=torch.long, device=rays.device)
    table[rays - base] = torch.arange(num_rays, device=rays.device)
    return table[(bins - base).clamp_(0, size - 1)]


def _check_dual(p_dual: float, generator: Generator | None) -> float:
    p_dual = float(p_dual)
    if not 0.0 <= p_dual <= 1.0:
        raise ValueError(f"p_dual must be in [0, 1], got {p_dual}")
    # numpy types first: torch.Generator's isinstance check runs Python code (cold in a loader)
    if p_dual > 0 and not isinstance(generator, (np.ndarray, np.random.Generator, torch.Generator)):
        raise ValueError(
            "raycast_merge: p_dual > 0 needs an explicit torch.Generator, numpy Generator or "
            f"array of uniforms (no global RNG), got {type(generator).__name__}; pass "
            "generator=... or p_dual=0"
        )
    return p_dual


def dual_uniforms(generator: Generator, count: int, device: torch.device | None = None):
    """``count`` float64 uniforms in ``[0, 1)`` for the dual-return draws of rule 5.

    A numpy ``Generator`` draws on the host and a ``torch.Generator`` on its own device, so a
    given generator gives the same uniforms whatever the device of the points; a 1-D numpy array
    holds uniforms drawn beforehand (its first ``count`` are used; an
    :class:`~pcdet_atlas.attacks.injection.InjectionAttack` draws one row per frame of a run
    once). Returns a numpy array when ``device`` is ``None``, else a tensor on ``device``.
    """
    if isinstance(generator, np.ndarray):
        if generator.ndim != 1 or generator.size < count:
            raise ValueError(
                f"dual-return uniforms: need a 1-D array of at least {count}, got shape "
                f"{generator.shape}"
            )
        u = generator[:count]
        return u if device is None else torch.from_numpy(np.ascontiguousarray(u)).to(device)
    if isinstance(generator, np.random.Generator):
        u = generator.random(count)
        return u if device is None else torch.from_numpy(u).to(device)
    u = torch.rand(count, generator=generator, dtype=torch.float64, device=generator.device)
    return u.cpu().numpy() if device is None else u.to(device)
