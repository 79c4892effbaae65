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
   products per wedge in the scene's own dtype (no trigonometry over the whole scene). The
   margins (1e-4 rad, 1 mm at the apex) are far above float32 rounding, so no point whose exact
   column is occupied can be missed.
4. Only candidates are binned exactly and merged. Ties and minima use a two-pass
   ``scatter_reduce('amin')`` (min range per ray, then min index among the points achieving it),
   which is deterministic on CPU and GPU; no ``index_put_`` with duplicate indices.

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
from pcdet_atlas.ops.lidar_model import LidarModel, spherical_offsets

#: Sources of the dual-return draws (rule 5): a generator, or uniforms drawn beforehand.
Generator = torch.Generator | np.random.Generator | np.ndarray

__all__ = [
    "raycast_merge",
    "raycast_merge_numpy",
    "azimuth_sector_candidates",
    "azimuth_sector_candidates_numpy",
    "disc_wedges",
    "wedge_rows_numpy",
    "scene_columns",
]

#: ``raycast_merge(..., backend=)`` values: ``'auto'`` runs CPU tensors through the numpy
#: implementation and every other device through the torch one.
BACKENDS = ("auto", "torch", "numpy")
_NUMPY_DTYPES = (torch.float16, torch.float32, torch.float64)

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


def _as_xyz(points, name: str) -> torch.Tensor:
    pts = torch.as_tensor(points)
    if pts.dim() != 2 or pts.shape[1] < 3:
        raise ValueError(f"{name} must have shape (N, 3+), got {tuple(pts.shape)}")
    if not pts.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got {pts.dtype}")
    return pts[:, :3]


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
    scene_xyz: torch.Tensor, columns: torch.Tensor, lidar: LidarModel
) -> torch.Tensor:
    """Indices of the scene points that may fall in the given azimuth columns.

    A superset, never missing a point whose exact column (:meth:`LidarModel.azimuth_index` of
    its float64 azimuth) is in ``columns``; the extra points are those within a tiny margin of
    the sector or near the sensor axis. Non-finite points are never returned.

    Args:
        scene_xyz: ``(N, 3)`` float points, vehicle frame, metres.
        columns: ``(K,)`` long, distinct occupied azimuth columns in ``[0, M)``, sorted.
        lidar: the sensor model (origin, ``M = azimuth_bins``).

    Returns:
        ``(C,)`` long indices into ``scene_xyz``, ascending.
    """
    device = scene_xyz.device
    cols = columns.tolist()
    if not cols or scene_xyz.shape[0] == 0:
        return torch.zeros(0, dtype=torch.long, device=device)
    wedges = _sector_wedges(cols, lidar.azimuth_bins)
    if wedges is None:
        ok = torch.isfinite(scene_xyz).all(dim=1)
        return torch.nonzero(ok).squeeze(1)
    dtype = scene_xyz.dtype if scene_xyz.dtype in (torch.float32, torch.float64) else torch.float32
    x = scene_xyz[:, 0].to(dtype)  # (N,)
    y = scene_xyz[:, 1].to(dtype)  # (N,)
    ox, oy = lidar.origin_xyz[:2]
    mask = None
    for a0, a1 in wedges:
        # inside iff cross(u0, p - o) >= 0 and cross(p - o, u1) >= 0 (wedge narrower than pi)
        inside = _half_plane(x, y, -math.sin(a0), math.cos(a0), ox, oy)
        inside &= _half_plane(x, y, math.sin(a1), -math.cos(a1), ox, oy)
        mask = inside if mask is None else mask | inside
    return torch.nonzero(mask).squeeze(1)


class ColumnScratch:
    """Reusable storage of the per-frame column copies of :func:`scene_columns`.

    The full-scene pre-filters need ``x``, ``y`` and one work array per frame: ~1.7 MB for a
    140k-point frame, which a fresh allocation pays again in page faults on every spoofed frame.
    One instance per attack object; not for concurrent use from several threads (each
    DataLoader worker process has its own copy; it pickles empty).
    """

    def __init__(self):
        self._store: np.ndarray | None = None

    def rows(self, n: int, dtype: np.dtype) -> np.ndarray:
        """A ``(3, n)`` array of ``dtype`` (uninitialised; valid until the next call)."""
        store = self._store
        if store is None or store.dtype != dtype or store.shape[1] < n:
            store = self._store = np.empty((3, max(n, 1) + max(n, 1) // 4), dtype=dtype)
        return store[:, :n]

    def __getstate__(self) -> dict:
        return {"_store": None}


def scene_columns(
    scene_xyz: np.ndarray, scratch: ColumnScratch | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Contiguous copies of the ``x`` and ``y`` columns of ``(N, 3+)`` points (float32 unless
    float64) and a work array of the same shape: the layout of every full-scene pre-filter on
    CPU, made once per frame and shared (:func:`raycast_merge_numpy`,
    :class:`~pcdet_atlas.attacks.ground.GroundEstimator`, the removal sector). With ``scratch``
    they are views into its reusable storage."""
    dtype = scene_xyz.dtype if scene_xyz.dtype in (np.float32, np.float64) else np.float32
    n = scene_xyz.shape[0]
    rows = np.empty((3, n), dtype=dtype) if scratch is None else scratch.rows(n, np.dtype(dtype))
    np.copyto(rows[0], scene_xyz[:, 0], casting="same_kind")
    np.copyto(rows[1], scene_xyz[:, 1], casting="same_kind")
    return rows[0], rows[1], rows[2]


def azimuth_sector_candidates_numpy(
    scene_xyz: np.ndarray,
    columns: np.ndarray,
    lidar: LidarModel,
    scene_xy: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    rows: np.ndarray | None = None,
) -> np.ndarray:
    """:func:`azimuth_sector_candidates` on numpy arrays (the same wedges and margins; each
    half-plane test is a multiply, an add and a compare over contiguous columns).

    Args:
        scene_xyz: ``(N, 3+)`` float points, vehicle frame, metres.
        columns: ``(K,)`` distinct occupied azimuth columns, sorted.
        scene_xy: :func:`scene_columns` of ``scene_xyz`` when the caller already has them.
        rows: ascending indices of the only rows to test (a wider sector the caller has already
            cut out, e.g. with :func:`disc_wedges`); ``None``: every row.
    Returns:
        ``(C,)`` int64 indices into ``scene_xyz``, ascending (a subset of ``rows``).
    """
    if len(columns) == 0 or scene_xyz.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    wedges = _sector_wedges(columns, lidar.azimuth_bins)
    if wedges is not None:
        return wedge_rows_numpy(scene_xyz, wedges, lidar, scene_xy, rows)
    if rows is None:  # most of the circle: every finite point
        return np.isfinite(scene_xyz[:, :3]).all(axis=1).nonzero()[0]
    return rows[np.isfinite(scene_xyz[rows, :3]).all(axis=1)]


def wedge_rows_numpy(
    scene_xyz: np.ndarray,
    wedges: Sequence[tuple[float, float]],
    lidar: LidarModel,
    scene_xy: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    rows: np.ndarray | None = None,
) -> np.ndarray:
    """Ascending indices of the scene points inside any of the ``wedges`` ``(a0, a1)`` (radians,
    each narrower than pi, apex at the sensor origin, with the half-plane tests' slack), among
    ``rows`` (ascending indices) or every point.

    Args:
        scene_xyz: ``(N, 3+)`` float points, vehicle frame, metres.
        scene_xy: :func:`scene_columns` of ``scene_xyz`` when the caller already has them.
    """
    if not wedges or scene_xyz.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    if rows is None:
        x, y, buf = scene_columns(scene_xyz) if scene_xy is None else scene_xy
    else:
        x, y = (scene_xyz[:, 0], scene_xyz[:, 1]) if scene_xy is None else scene_xy[:2]
        x, y = x[rows], y[rows]
        if x.dtype not in (np.float32, np.float64):  # the dtype of scene_columns
            x, y = x.astype(np.float32), y.astype(np.float32)
        buf = np.empty_like(x)
    ox, oy = lidar.origin_xyz[:2]
    mask = None
    for a0, a1 in wedges:
        inside = _half_plane_numpy(x, y, -math.sin(a0), math.cos(a0), ox, oy, buf)
        inside &= _half_plane_numpy(x, y, math.sin(a1), -math.cos(a1), ox, oy, buf)
        mask = inside if mask is None else mask | inside
    return mask.nonzero()[0] if rows is None else rows[mask]


def disc_wedges(lidar: LidarModel, center_xy, radius: float) -> list[tuple[float, float]] | None:
    """Wedges (apex at the sensor origin) holding every scene point of every azimuth column
    that meets the disc of ``radius`` (m) around ``center_xy`` (vehicle frame), or ``None``
    when the disc reaches the sensor's axis or the wedges would be most of the circle (no
    pre-filter pays off). Plain float arithmetic: no array work.

    The disc's azimuth interval is widened by one column (a point's column extends at most
    one column width beyond its azimuth) and twice the candidate margin on each side (one for
    :func:`azimuth_sector_candidates_numpy`'s margin, one for rounding), so the rows of these
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


def _half_plane_numpy(
    x: np.ndarray, y: np.ndarray, a: float, b: float, ox: float, oy: float, buf: np.ndarray
) -> np.ndarray:
    """:func:`_half_plane` in numpy, in the columns' dtype (``buf``: scratch of that shape)."""
    thresh = a * ox + b * oy - _WEDGE_SLACK_M
    if abs(b) < abs(a):
        x, y, a, b = y, x, b, a
    np.multiply(x, x.dtype.type(a / b), out=buf)
    np.add(buf, y, out=buf)
    bound = x.dtype.type(thresh / b)
    return np.greater_equal(buf, bound) if b > 0 else np.less_equal(buf, bound)


def _half_plane(
    x: torch.Tensor, y: torch.Tensor, a: float, b: float, ox: float, oy: float
) -> torch.Tensor:
    """``a (x - ox) + b (y - oy) >= -slack`` in two passes over the points (``(N,)`` bool).

    Divides by the larger of ``|a|``, ``|b|`` so that one fused ``add(.., alpha=..)`` and one
    comparison suffice; NaN compares False.
    """
    thresh = a * ox + b * oy - _WEDGE_SLACK_M
    if abs(b) >= abs(a):
        w = torch.add(y, x, alpha=a / b)  # (N,)
        return w >= thresh / b if b > 0 else w <= thresh / b
    w = torch.add(x, y, alpha=b / a)  # (N,)
    return w >= thresh / a if a > 0 else w <= thresh / a


def raycast_merge(
    scene_xyz: torch.Tensor,
    spoof_xyz: torch.Tensor,
    lidar: LidarModel,
    p_dual: float = 0.01,
    generator: Generator | None = None,
    counters: AttackCounters | None = None,
    backend: str = "auto",
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
        backend: ``'auto'`` (numpy for CPU tensors, torch otherwise), ``'torch'`` or
            ``'numpy'`` (CPU tensors only). On CPU both give identical masks, counters and
            draws: both bin through :func:`~pcdet_atlas.ops.lidar_model.spherical_offsets`
            (numpy ``sqrt`` / ``arctan2``), everything else is IEEE-exact arithmetic or
            integer/comparison logic. The numpy
            one avoids ~60 small torch ops, whose fixed cost dominates a few thousand candidate
            points on CPU.

    Returns:
        keep_scene: ``(N,)`` bool, on the scene's device.
        keep_spoof: ``(M,)`` bool.
    """
    scene = _as_xyz(scene_xyz, "scene_xyz")
    spoof = _as_xyz(spoof_xyz, "spoof_xyz")
    if scene.device != spoof.device:
        raise ValueError(f"scene_xyz on {scene.device} but spoof_xyz on {spoof.device}")
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    p_dual = _check_dual(p_dual, generator)
    if not bool(torch.isfinite(spoof).all()):
        raise ValueError("spoof_xyz contains non-finite coordinates")
    counters = COUNTERS if counters is None else counters
    numpy_ok = (
        scene.device.type == "cpu"
        and scene.dtype in _NUMPY_DTYPES
        and not (scene.requires_grad or spoof.requires_grad)
    )
    if backend == "numpy" and not numpy_ok:
        raise ValueError(
            f"backend 'numpy' needs CPU float16/32/64 tensors without grad, got {scene.dtype}"
        )
    if backend == "numpy" or (backend == "auto" and numpy_ok and spoof.dtype in _NUMPY_DTYPES):
        occluded, keep_spoof = _raycast_numpy(
            scene.numpy(), spoof.numpy(), lidar, p_dual, generator, counters
        )
        keep_scene = torch.ones(scene.shape[0], dtype=torch.bool)
        keep_scene[torch.from_numpy(occluded)] = False
        return keep_scene, torch.from_numpy(keep_spoof)
    device = scene.device
    num_scene, num_spoof = scene.shape[0], spoof.shape[0]
    keep_scene = torch.ones(num_scene, dtype=torch.bool, device=device)
    keep_spoof = torch.zeros(num_spoof, dtype=torch.bool, device=device)
    if num_spoof == 0:
        return keep_scene, keep_spoof

    # ---- spoof rays (rules 1, 2)
    spoof_bin, spoof_fov, spoof_rng = lidar.bin_index(spoof)  # (M,) long, bool, float64
    valid = spoof_fov & (spoof_rng > 0) & (spoof_rng <= lidar.max_range)
    spoof_idx = torch.nonzero(valid).squeeze(1)  # (V,)
    if spoof_idx.numel() == 0:
        counters.add(raycast_calls=1, points_examined=num_spoof)
        return keep_scene, keep_spoof
    rays, spoof_ray = torch.unique(spoof_bin[spoof_idx], sorted=True, return_inverse=True)
    num_rays = rays.numel()  # K rays, ascending ray id
    spoof_r = spoof_rng[spoof_idx]  # (V,)
    echo_r = torch.full((num_rays,), math.inf, dtype=torch.float64, device=device)
    echo_r.scatter_reduce_(0, spoof_ray, spoof_r, "amin")  # (K,) nearest spoof range
    echo_idx = torch.full((num_rays,), num_spoof, dtype=torch.long, device=device)
    echo_idx.scatter_reduce_(
        0, spoof_ray, torch.where(spoof_r == echo_r[spoof_ray], spoof_idx, num_spoof), "amin"
    )  # (K,) lowest index achieving it

    # ---- scene returns of those rays, from the candidates of the sector only
    columns = torch.unique(rays % lidar.azimuth_bins)  # sorted
    cand = azimuth_sector_candidates(scene, columns, lidar)  # (C,)
    cand_bin, cand_fov, cand_rng = lidar.bin_index(scene[cand])
    pos = torch.searchsorted(rays, cand_bin).clamp_(max=num_rays - 1)
    is_ret = cand_fov & (cand_rng > 0) & torch.isfinite(cand_rng) & (rays[pos] == cand_bin)  # (C,)
    ret_idx = cand[is_ret]  # (R,) scene indices
    ret_ray = pos[is_ret]  # (R,)
    ret_r = cand_rng[is_ret]  # (R,)
    far_r = torch.full((num_rays,), -math.inf, dtype=torch.float64, device=device)
    far_r.scatter_reduce_(0, ret_ray, ret_r, "amax")  # (K,) farthest scene return
    near_r = torch.full((num_rays,), math.inf, dtype=torch.float64, device=device)
    near_r.scatter_reduce_(0, ret_ray, ret_r, "amin")  # (K,) nearest scene return
    has_scene = far_r > -math.inf

    # ---- rules 3, 4, 6
    ray_keeps = ~has_scene | (echo_r < far_r)  # (K,)
    keep_spoof[echo_idx[ray_keeps]] = True
    occluded = ray_keeps[ret_ray] & (ret_r > echo_r[ret_ray])  # (R,)

    # ---- rule 5: dual returns, drawn only in primary rays
    draws = 0
    if p_dual > 0:
        primary = torch.nonzero(ray_keeps & has_scene & (echo_r < near_r)).squeeze(1)  # (P,)
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


def raycast_merge_numpy(
    scene_xyz: np.ndarray,
    spoof_xyz: np.ndarray,
    lidar: LidarModel,
    p_dual: float = 0.01,
    generator: Generator | None = None,
    counters: AttackCounters | None = None,
    scene_xy: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`raycast_merge` on numpy arrays (CPU), with identical results.

    Args:
        scene_xyz: ``(N, 3+)`` float scene points (a strided view is fine: never copied whole).
        spoof_xyz: ``(M, 3+)`` float spoofed points.
        lidar, p_dual, generator, counters: as :func:`raycast_merge` (the uniforms of rule 5
            come from :func:`dual_uniforms`, so the draws are the same).
        scene_xy: :func:`scene_columns` of ``scene_xyz`` if the caller has them already.

    Returns:
        keep_scene ``(N,)`` and keep_spoof ``(M,)`` bool arrays.
    """
    occluded, keep_spoof = raycast_numpy_indices(
        scene_xyz, spoof_xyz, lidar, p_dual, generator, counters, scene_xy
    )
    keep_scene = np.ones(np.shape(scene_xyz)[0], dtype=bool)
    keep_scene[occluded] = False
    return keep_scene, keep_spoof


def raycast_numpy_indices(
    scene_xyz: np.ndarray,
    spoof_xyz: np.ndarray,
    lidar: LidarModel,
    p_dual: float = 0.01,
    generator: Generator | None = None,
    counters: AttackCounters | None = None,
    scene_xy: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    candidates: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`raycast_merge_numpy` returning the **ascending int64 indices** of the occluded
    scene points (instead of an ``(N,)`` mask) and the ``(M,)`` bool keep mask of the spoof.

    ``candidates``: ascending indices of scene rows that include every point of the spoof's
    azimuth sector (a wider sector the caller cut out for its own use, e.g. with
    :func:`disc_wedges`); the sector test then looks at those rows only.
    The result is the same as without them."""
    scene = _as_xyz_numpy(scene_xyz, "scene_xyz")
    spoof = _as_xyz_numpy(spoof_xyz, "spoof_xyz")
    p_dual = _check_dual(p_dual, generator)
    if not np.isfinite(spoof).all():
        raise ValueError("spoof_xyz contains non-finite coordinates")
    counters = COUNTERS if counters is None else counters
    return _raycast_numpy(scene, spoof, lidar, p_dual, generator, counters, scene_xy, candidates)


def _as_xyz_numpy(points, name: str) -> np.ndarray:
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"{name} must have shape (N, 3+), got {pts.shape}")
    if not np.issubdtype(pts.dtype, np.floating):
        raise TypeError(f"{name} must be a floating-point array, got {pts.dtype}")
    return pts[:, :3]


def _bin_index_numpy(lidar: LidarModel, xyz: np.ndarray) -> tuple[np.ndarray, ...]:
    """:meth:`LidarModel.bin_index` of ``(N, 3)`` numpy points, bit for bit (the same
    :func:`~pcdet_atlas.ops.lidar_model.spherical_offsets` arithmetic)."""
    rel = xyz[:, :3].astype(np.float64) - lidar.origin_np
    return _bin_offsets(lidar, rel[:, 0], rel[:, 1], rel[:, 2])


def _bin_offsets(
    lidar: LidarModel, dx: np.ndarray, dy: np.ndarray, dz: np.ndarray
) -> tuple[np.ndarray, ...]:
    """:func:`_bin_index_numpy` of points given as ``(N,)`` float64 offsets from the sensor
    origin (``float64(xyz) - origin``, the first step of the binning)."""
    azimuth, elevation, rng = spherical_offsets(dx, dy, dz)
    beam = np.searchsorted(lidar.midpoints_np, elevation, side="left")
    fov = (elevation >= lidar.fov_min) & (elevation <= lidar.fov_max)
    return beam * lidar.azimuth_bins + _azimuth_column(lidar, azimuth), fov, rng


def _azimuth_column(lidar: LidarModel, azimuth: np.ndarray) -> np.ndarray:
    """``(N,)`` int64 column of float64 azimuths in ``(-pi, pi]`` (non-finite: any column)."""
    width = 2 * math.pi / lidar.azimuth_bins
    with np.errstate(invalid="ignore"):  # non-finite points: any bin, never in the FOV
        col = np.floor((azimuth + math.pi) / width)  # >= 0: azimuth > -pi
        np.minimum(col, lidar.azimuth_bins - 1, out=col)  # azimuth pi: the last column
        return col.astype(np.int64)


def _raycast_numpy(
    scene: np.ndarray,
    spoof: np.ndarray,
    lidar: LidarModel,
    p_dual: float,
    generator: Generator | None,
    counters: AttackCounters,
    scene_xy: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    candidates: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The merge of :func:`raycast_merge` in numpy; returns (occluded scene indices ascending,
    keep_spoof). Per-ray minima by one stable sort instead of two-pass scatters."""
    num_scene, num_spoof = scene.shape[0], spoof.shape[0]
    keep_spoof = np.zeros(num_spoof, dtype=bool)
    no_index = np.zeros(0, dtype=np.int64)
    if num_spoof == 0:
        return no_index, keep_spoof

    # ---- spoof rays (rules 1, 2): nearest per ray, ties to the lower index
    origin = lidar.origin_np
    spoof_rel = spoof.astype(np.float64) - origin  # (M, 3) offsets from the sensor
    spoof_bin, spoof_fov, spoof_rng = _bin_offsets(
        lidar, spoof_rel[:, 0], spoof_rel[:, 1], spoof_rel[:, 2]
    )
    valid = spoof_fov & (spoof_rng > 0) & (spoof_rng <= lidar.max_range)
    spoof_idx = valid.nonzero()[0]  # (V,)
    if spoof_idx.size == 0:
        counters.add(raycast_calls=1, points_examined=num_spoof)
        return no_index, keep_spoof
    spoof_ray_bin = spoof_bin[spoof_idx]
    spoof_r = spoof_rng[spoof_idx]
    # by ray, then range; lexsort is stable and spoof_idx ascending, so ties keep the lower index
    order = np.lexsort((spoof_r, spoof_ray_bin))
    sorted_bin = spoof_ray_bin[order]
    # (C-level calls only here and below: np.ones / np.full / np.flatnonzero are Python
    # wrappers, each a few more microseconds with the cold caches of a loader)
    head = np.empty(order.size, dtype=bool)
    head[0] = True
    np.not_equal(sorted_bin[1:], sorted_bin[:-1], out=head[1:])
    first = order[head]  # (K,) the echo of each ray, ascending ray id
    rays = spoof_ray_bin[first]
    echo_r = spoof_r[first]
    echo_idx = spoof_idx[first]
    num_rays = rays.size

    # ---- the scene points that can be returns of those rays: the sector of the rays' columns
    # (wedge pre-filter), then the band of their beams (rays are sorted by beam first), and
    # only those are binned -- each point's bin is a function of its own coordinates alone
    num_columns = lidar.azimuth_bins
    columns = np.bincount(rays % num_columns, minlength=num_columns).nonzero()[0]
    cand = azimuth_sector_candidates_numpy(scene, columns, lidar, scene_xy, candidates)  # (C,)
    num_cand = cand.size
    cand_rel = _gather_rel(scene, cand, scene_xy, origin)  # 3 x (C,)
    sub = _elevation_band(
        cand_rel, int(rays[0]) // num_columns, int(rays[-1]) // num_columns, lidar
    )
    if sub is not None:  # only the candidates in the rays' beams get trigonometry
        cand, cand_rel = cand[sub], [v[sub] for v in cand_rel]
    cand_bin, cand_fov, cand_rng = _bin_offsets(lidar, *cand_rel)

    # ---- scene returns of those rays
    pos = np.minimum(np.searchsorted(rays, cand_bin), num_rays - 1)
    is_ret = cand_fov & (cand_rng > 0) & np.isfinite(cand_rng) & (rays[pos] == cand_bin)
    ret_idx = cand[is_ret]  # (R,) ascending scene indices
    ret_ray = pos[is_ret]
    ret_r = cand_rng[is_ret]
    far_r = np.empty(num_rays)
    far_r.fill(-math.inf)
    np.maximum.at(far_r, ret_ray, ret_r)
    near_r = np.empty(num_rays)
    near_r.fill(math.inf)
    np.minimum.at(near_r, ret_ray, ret_r)
    has_scene = far_r > -math.inf

    # ---- rules 3, 4, 6
    ray_keeps = ~has_scene | (echo_r < far_r)
    keep_spoof[echo_idx[ray_keeps]] = True
    occluded = ray_keeps[ret_ray] & (ret_r > echo_r[ret_ray])

    # ---- rule 5: dual returns, drawn only in primary rays (same uniforms as the torch path)
    draws = 0
    if p_dual > 0:
        primary = (ray_keeps & has_scene & (echo_r < near_r)).nonzero()[0]
        draws = primary.size
        if draws:
            dual_rays = primary[dual_uniforms(generator, draws) < p_dual]
            if dual_rays.size:
                nearest = ret_r == near_r[ret_ray]
                near_idx = np.empty(num_rays, dtype=np.int64)
                near_idx.fill(num_scene)
                np.minimum.at(near_idx, ret_ray[nearest], ret_idx[nearest])
                second = np.zeros(num_rays, dtype=bool)
                second[dual_rays] = True
                occluded &= ~(second[ret_ray] & (ret_idx == near_idx[ret_ray]))
    counters.add(
        raycast_calls=1,
        bins_touched=num_rays,
        points_examined=num_cand + num_spoof,
        dual_draws=draws,
    )
    return ret_idx[occluded], keep_spoof


def _gather_rel(
    scene: np.ndarray,
    idx: np.ndarray,
    scene_xy: tuple[np.ndarray, ...] | None,
    origin: np.ndarray,
) -> list[np.ndarray]:
    """``float64(scene[idx, d]) - origin[d]`` for ``d = 0, 1, 2``, three ``(C,)`` arrays; ``x``
    and ``y`` are gathered from the contiguous :func:`scene_columns` when given (1-D gathers
    instead of a row gather from a strided view; the values are the same floats)."""
    if scene_xy is None:
        rel = scene[idx].astype(np.float64) - origin
        return [rel[:, 0], rel[:, 1], rel[:, 2]]
    cols = (scene_xy[0], scene_xy[1], scene[:, 2])
    return [np.subtract(col[idx], origin[d], dtype=np.float64) for d, col in enumerate(cols)]


def _elevation_band(
    rel: list[np.ndarray], b_lo: int, b_hi: int, lidar: LidarModel
) -> np.ndarray | None:
    """Indices of the points (their float64 offsets from the sensor origin, three ``(C,)``
    arrays) whose elevation may fall in the beams ``[b_lo, b_hi]``
    (a superset: the beam boundaries are widened by ``_WEDGE_MARGIN_RAD``), by
    ``z >= h tan(lo)`` and ``z <= h tan(hi)`` in float64 -- no trigonometry per point. ``None``
    when the beams span the whole fan (every point passes)."""
    if b_lo == 0 and b_hi == lidar.num_beams - 1:
        return None
    mids = lidar.midpoints_np
    horiz = np.sqrt(rel[0] ** 2 + rel[1] ** 2)
    ok = None
    if b_lo > 0:
        ok = rel[2] >= horiz * math.tan(float(mids[b_lo - 1]) - _WEDGE_MARGIN_RAD)
    if b_hi < lidar.num_beams - 1:
        below = rel[2] <= horiz * math.tan(float(mids[b_hi]) + _WEDGE_MARGIN_RAD)
        ok = below if ok is None else ok & below
    return ok.nonzero()[0]
