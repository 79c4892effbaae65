"""Road geometry of the synthetic world: piecewise line/arc centerlines, the road map, kinematics.

A :class:`Path` is an arc-length parameterised centerline made of straight pieces and circular
arcs; lanes, sidewalks and building rows are offsets of it (``+`` to the left of the direction of
travel). :class:`RoadMap` answers "which road surface lies under this ground point" (asphalt,
lane marking, sidewalk, verge) for intensity. :func:`simulate_motion` integrates a simple
longitudinal driver model (acceleration, comfortable braking, curve speed limit, stop lines).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["Path", "Road", "RoadMap", "simulate_motion", "CrossSection"]


class Path:
    """Centerline of straight pieces and circular arcs, starting at ``start`` heading ``yaw0``.

    Args:
        start: ``(2,)`` global xy of ``s = 0``, m.
        yaw0: heading at ``s = 0``, rad.
        pieces: ``[(length_m, curvature_1_per_m), ...]``; curvature 0 is a straight piece.
    Beyond either end the path continues straight along the end tangent.
    """

    def __init__(self, start, yaw0: float, pieces: list[tuple[float, float]]):
        if not pieces:
            raise ValueError("Path needs at least one piece")
        self.pieces = [(float(length), float(k)) for length, k in pieces]
        s0, x0, y0, yaw = [0.0], [float(start[0])], [float(start[1])], [float(yaw0)]
        for length, k in self.pieces:
            x, y, h = _advance(x0[-1], y0[-1], yaw[-1], length, k)
            s0.append(s0[-1] + length)
            x0.append(x)
            y0.append(y)
            yaw.append(h)
        self._s0 = np.asarray(s0)
        self._x0 = np.asarray(x0)
        self._y0 = np.asarray(y0)
        self._yaw0 = np.asarray(yaw)
        self._k = np.asarray([k for _, k in self.pieces] + [0.0])
        self.length = float(self._s0[-1])

    def _piece(self, s: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self._s0, s, side="right") - 1, 0, len(self.pieces))

    def curvature(self, s) -> np.ndarray:
        """Signed curvature (1/m, + = turning left) at arc length ``s``; 0 beyond the ends."""
        s = np.asarray(s, dtype=np.float64)
        i = self._piece(s)
        k = self._k[i]
        return np.where((s < 0) | (s > self.length), 0.0, k)

    def pose(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Global ``x, y, heading`` at arc length(s) ``s`` (arrays of the shape of ``s``)."""
        s = np.asarray(s, dtype=np.float64)
        i = self._piece(s)
        i = np.where(s < 0, 0, i)
        ds = s - self._s0[i]
        k = np.where(s < 0, 0.0, self._k[i])
        x, y, h = _advance(self._x0[i], self._y0[i], self._yaw0[i], ds, k)
        return x, y, h

    def project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Nearest point of the path (within ``[0, length]``) to ``(N, 2)`` global points.

        Returns ``(N,)`` distance, signed lateral offset (+ = left) and arc length ``s`` there.
        Exact per piece: a segment projection, or the radial distance to an arc's circle.
        """
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        best_d = np.full(len(xy), np.inf)
        best_lat = np.zeros(len(xy))
        best_s = np.zeros(len(xy))
        for i, (length, k) in enumerate(self.pieces):
            x0, y0, h0 = self._x0[i], self._y0[i], self._yaw0[i]
            c, s = math.cos(h0), math.sin(h0)
            if abs(k) < 1e-12:
                rx, ry = xy[:, 0] - x0, xy[:, 1] - y0
                along = rx * c + ry * s
                lat = -rx * s + ry * c
            else:
                radius = 1.0 / abs(k)
                cx, cy = x0 - s / k, y0 + c / k  # centre of the circle
                rx, ry = xy[:, 0] - cx, xy[:, 1] - cy
                rho = np.sqrt(rx * rx + ry * ry)
                lat = np.sign(k) * (radius - rho)
                start = math.atan2(y0 - cy, x0 - cx)
                turn = (np.arctan2(ry, rx) - start) * np.sign(k)
                turn = np.mod(turn + math.pi, 2 * math.pi) - math.pi
                along = turn * radius
            over = along - np.clip(along, 0.0, length)
            d = np.sqrt(over * over + lat * lat)
            better = d < best_d
            best_d = np.where(better, d, best_d)
            best_lat = np.where(better, lat, best_lat)
            best_s = np.where(better, self._s0[i] + np.clip(along, 0.0, length), best_s)
        return best_d, best_lat, best_s

    def offset_pose(self, s, offset) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pose of the parallel curve ``offset`` m to the left (heading unchanged)."""
        x, y, h = self.pose(s)
        return x - offset * np.sin(h), y + offset * np.cos(h), h


def _advance(x, y, yaw, length, k):
    """Pose after driving ``length`` m from ``(x, y, yaw)`` with constant curvature ``k``."""
    length = np.asarray(length, dtype=np.float64)
    k = np.asarray(k, dtype=np.float64)
    straight = np.abs(k) < 1e-12
    ksafe = np.where(straight, 1.0, k)
    h = yaw + k * length
    xa = x + (np.sin(h) - np.sin(yaw)) / ksafe
    ya = y - (np.cos(h) - np.cos(yaw)) / ksafe
    xs = x + length * np.cos(yaw)
    ys = y + length * np.sin(yaw)
    out = (np.where(straight, xs, xa), np.where(straight, ys, ya), h)
    if out[0].ndim == 0:
        return float(out[0]), float(out[1]), float(out[2])
    return out


@dataclass(frozen=True)
class CrossSection:
    """Lateral layout of every road of a scene (metres from the centerline, symmetric)."""

    lanes_per_direction: int = 2
    lane_width: float = 3.5
    bike_lane_width: float = 1.5
    parking_width: float = 2.3
    sidewalk_width: float = 3.5
    curb_height: float = 0.15

    @property
    def carriageway(self) -> float:
        """Half width of the driving lanes."""
        return self.lanes_per_direction * self.lane_width

    @property
    def half_width(self) -> float:
        """Half width from centerline to curb."""
        return self.carriageway + self.bike_lane_width + self.parking_width

    @property
    def sidewalk_outer(self) -> float:
        return self.half_width + self.sidewalk_width

    def lane_offset(self, lane: int) -> float:
        """Offset of driving lane ``lane`` (0 = innermost) on the right of the travel direction."""
        return -(lane + 0.5) * self.lane_width

    @property
    def bike_offset(self) -> float:
        return -(self.carriageway + self.bike_lane_width / 2)

    @property
    def parking_offset(self) -> float:
        return -(self.carriageway + self.bike_lane_width + self.parking_width / 2)


@dataclass
class Road:
    path: Path
    s_start: float
    s_end: float
    kind: str  # 'route', 'arm', 'fill'


@dataclass
class RoadMap:
    """Road lookups over all roads of a scene: distance to the nearest centerline (KD-tree of
    0.5 m samples, for placing objects) and exact lateral offsets (for the ground material)."""

    roads: list[Road]
    cross: CrossSection
    junctions: np.ndarray  # (J, 2) junction centres, global xy
    spacing: float = 0.5
    _tree: cKDTree = field(init=False, repr=False)

    def __post_init__(self):
        xy = []
        for road in self.roads:
            n = max(2, int(np.ceil((road.s_end - road.s_start) / self.spacing)) + 1)
            x, y, _ = road.path.pose(np.linspace(road.s_start, road.s_end, n))
            xy.append(np.stack([x, y], 1))
        self.sample_xy = np.concatenate(xy)
        self._tree = cKDTree(self.sample_xy)
        self._bounds = []
        for road in self.roads:
            ss = np.linspace(road.s_start, road.s_end, 64)
            x, y, _ = road.path.pose(ss)
            pts = np.stack([x, y], 1)
            self._bounds.append((pts.min(axis=0), pts.max(axis=0)))

    def distance(self, xy: np.ndarray) -> np.ndarray:
        """``(N,)`` distance of ``(N, 2)`` global points to the nearest road centerline, m."""
        if len(xy) == 0:
            return np.zeros(0)
        d, _ = self._tree.query(np.asarray(xy, dtype=np.float64).reshape(-1, 2))
        return d

    def lateral(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed lateral offset from the nearest centerline and the arc length there (exact)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        best_d = np.full(len(xy), np.inf)
        best_lat, best_s = np.zeros(len(xy)), np.zeros(len(xy))
        if len(xy) == 0:
            return best_lat, best_s
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        for road, (blo, bhi) in zip(self.roads, self._bounds):
            if (blo > hi + 50.0).any() or (bhi < lo - 50.0).any():
                continue  # the road is far from every point; another road is nearer
            d, lat, s = road.path.project(xy)
            better = d < best_d
            best_d = np.where(better, d, best_d)
            best_lat = np.where(better, lat, best_lat)
            best_s = np.where(better, s, best_s)
        return best_lat, best_s

    def near_junction(self, xy: np.ndarray, margin: float) -> np.ndarray:
        """Whether points lie within ``half_width + margin`` of a junction centre."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if len(self.junctions) == 0:
            return np.zeros(len(xy), dtype=bool)
        diff = xy[:, None, :] - self.junctions[None, :, :]
        d2 = (diff**2).sum(axis=2).min(axis=1)
        return d2 < (self.cross.half_width + margin) ** 2

    def ground_albedo(self, xy: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Diffuse albedo and retro-reflective flag of the ground at ``(N, 2)`` global points.

        Asphalt inside the curbs, painted lines (centre, lane dividers dashed 3 m / 6 m gap, bike
        and parking lines; none inside junctions), and a darker or lighter verge beyond the
        sidewalks. ``noise`` is ``(N,)`` standard normal, for texture.
        """
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        lat, s = self.lateral(xy)
        a = np.abs(lat)
        c = self.cross
        albedo = np.where(a <= c.half_width, 0.09, 0.2) * (1 + 0.12 * noise)
        line_w = 0.075
        marks = np.abs(a - 0.2) < line_w  # double centre line at +-0.2 m
        for lane in range(1, c.lanes_per_direction):
            dashed = np.mod(s, 9.0) < 3.0
            marks |= (np.abs(a - lane * c.lane_width) < line_w) & dashed
        marks |= np.abs(a - c.carriageway) < line_w
        marks |= np.abs(a - c.carriageway - c.bike_lane_width) < line_w
        idx = np.nonzero(marks)[0]
        marks[idx[self.near_junction(xy[idx], 1.0)]] = False
        albedo = np.where(marks, 0.55 * (1 + 0.05 * noise), albedo)
        return np.clip(albedo, 0.01, 1.0), marks


def simulate_motion(
    path: Path,
    offset: float,
    s0: float,
    duration: float,
    v_cruise: float,
    v0: float | None = None,
    direction: int = 1,
    stops: list[tuple[float, float]] | None = None,
    accel: float = 1.6,
    decel: float = 2.5,
    lateral_accel: float = 2.2,
    dt: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """Centerline arc length over time of a vehicle following lane ``offset`` of ``path``.

    A longitudinal driver starting at ``v0`` (default: the cruise speed, or less where a curve
    demands it) accelerates at ``accel`` toward ``v_cruise``, keeps the curve speed
    ``sqrt(lateral_accel / |kappa|)`` (looking 40 m ahead), brakes at ``decel`` to stop at each
    ``(s_stop, wait_s)`` line (in the travel direction) and waits there ``wait_s`` seconds.

    Returns:
        ``t`` ``(T,)`` seconds from 0 to ``duration`` and ``s`` ``(T,)`` centerline arc length.
    """
    stops = sorted(stops or [], key=lambda st: direction * st[0])
    n = int(np.ceil(duration / dt)) + 1
    t = np.arange(n) * dt
    s_out = np.empty(n)
    # Lane arc length u is piecewise linear in the centerline arc length s (constant curvature
    # per piece), so the vehicle integrates u exactly and s follows from the breakpoints.
    far = 1e6
    s_break = [-far, *path._s0.tolist(), path.length + far]
    scales = [1.0] + [max(1.0 - offset * k, 0.2) for _, k in path.pieces] + [1.0]
    u_break = [0.0]
    for i, scale in enumerate(scales):
        u_break.append(u_break[-1] + (s_break[i + 1] - s_break[i]) * scale)

    def s_of_u(u: float) -> float:
        i = min(max(bisect.bisect_right(u_break, u) - 1, 0), len(scales) - 1)
        return s_break[i] + (u - u_break[i]) / scales[i]

    def u_of_s(s: float) -> float:
        i = min(max(bisect.bisect_right(s_break, s) - 1, 0), len(scales) - 1)
        return u_break[i] + (s - s_break[i]) * scales[i]

    # allowed speed over centerline arc length (curves ahead, braking at ``decel``)
    reach = (v_cruise + 1.0) * duration + 60.0
    step = 0.5
    grid = np.arange(s0 - reach - 1.0, s0 + reach + 1.0, step)
    look = np.arange(0.0, 40.0, 1.0)
    kap = path.curvature(grid[:, None] + direction * look[None, :])  # (G, 40)
    lane_scale = np.maximum(1.0 - offset * kap, 0.2)  # lane length per centerline metre
    v_curve = np.sqrt(lateral_accel / np.maximum(np.abs(kap) / lane_scale, 1e-6))
    v_allow_tab = np.min(np.sqrt(v_curve**2 + 2 * decel * look[None, :]), axis=1).tolist()
    g0, last = float(grid[0]), len(grid) - 1

    def allowed(s: float) -> float:
        return v_allow_tab[min(max(int(round((s - g0) / step)), 0), last)]

    s = float(s0)
    u = u_of_s(s)
    # default start speed: the cruise speed, unless a curve here or just ahead forbids it
    v = float(min(v_cruise, allowed(s)) if v0 is None else v0)
    stop_i, wait_left = 0, 0.0
    for i in range(n):
        s_out[i] = s
        v_allow = allowed(s)
        if stop_i < len(stops):
            s_stop, wait = stops[stop_i]
            dist = direction * (s_stop - s)
            if wait_left > 0:
                wait_left -= dt
                v = 0.0
                if wait_left <= 0:
                    stop_i += 1
                continue
            if dist <= 0.3 and v < 0.5:
                v = 0.0
                wait_left = max(wait, dt)
                continue
            v_allow = min(v_allow, math.sqrt(2 * decel * max(dist, 0.0)))
        target = min(v_cruise, v_allow)
        v = max(min(max(target, v - 1.5 * decel * dt), v + accel * dt), 0.0)
        u += direction * v * dt
        s = s_of_u(u)
    return t, s_out
