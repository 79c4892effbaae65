"""The procedural world of one synthetic sequence: roads, street furniture, road users, ego motion.

A :class:`SyntheticScene` is fully determined by ``(seed, split, sequence_index, num_frames)``:
every random draw comes from :func:`pcdet_atlas.utils.seeding.numpy_generator` keyed by those and
by what it is for. The ego drives a route of straight roads, gentle curves and 4-way junctions
(it may stop at a stop line and turns left/right/straight); side arms of the junctions carry
cross traffic that waits at stop lines. Sidewalks (raised curbs), buildings, walls and hedges,
street lights, trees and signs line every road; cars, vans and trucks park and drive in lanes,
pedestrians walk or stand on sidewalks and cross at junctions, cyclists ride bike lanes.

Everything is built in global coordinates; :meth:`SyntheticScene.primitives` and
:meth:`SyntheticScene.labels` express frame ``f`` in the ego vehicle frame.
"""

from __future__ import annotations

import base64
import math
from dataclasses import dataclass

import numpy as np
import torch

from pcdet_atlas.datasets.synthetic.actors import (
    SURFACE_FOLIAGE,
    SURFACE_RETRO,
    SURFACE_SOLID,
    PartSet,
    cyclist_shape,
    pedestrian_legs,
    pedestrian_shape,
    vehicle_shape,
)
from pcdet_atlas.datasets.synthetic.raycast import Primitives
from pcdet_atlas.datasets.synthetic.roads import CrossSection, Path, Road, RoadMap, simulate_motion
from pcdet_atlas.ops.boxes import boxes_bev_overlap, boxes_to_corners_bev
from pcdet_atlas.utils.common import limit_period
from pcdet_atlas.utils.seeding import derive_seed, numpy_generator

__all__ = ["SyntheticScene", "Actor", "FRAME_DT", "EGO_BOX_LOCAL"]

FRAME_DT = 0.1  # s, 10 Hz
#: Ego body in its own frame (x, y, dx, dy): rear-axle origin, ~5 m x 2.1 m.
EGO_BOX_LOCAL = (1.4, 0.0, 5.0, 2.15)
_ARM_LENGTH = 80.0  # m, side arms of a junction
_BACK = 80.0  # m of route behind the ego start
_CULL = 95.0  # m, objects never coming closer to the ego than this are not built


@dataclass
class Actor:
    """One labelled object: its shape and its global trajectory at the frame times.

    ``xy`` ``(F, 2)``, ``yaw`` ``(F,)`` heading of the object frame, ``speed``/``accel``
    ``(F, 2)`` global m/s and m/s^2. The label box is ``dims`` ``[l, w, h]`` centred at
    ``label_offset`` ``(3,)`` in the object frame.
    """

    name: str
    kind: str
    obj_id: str
    dims: np.ndarray
    label_offset: np.ndarray
    parts: PartSet
    xy: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    accel: np.ndarray
    gait: dict | None = None
    gait_phase: np.ndarray | None = None

    def parts_at(self, f: int) -> PartSet:
        local = self.parts
        if self.gait is not None:
            moving = bool(np.hypot(*self.speed[f]) > 0.05)
            legs = pedestrian_legs(self.gait, float(self.gait_phase[f]), moving)
            local = PartSet.concat([local, legs])
        return local.placed(float(self.xy[f, 0]), float(self.xy[f, 1]), float(self.yaw[f]))

    def footprint(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Label-box footprint over time: centres ``(F, 2)``, yaw ``(F,)``, half sizes ``(2,)``."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        ox, oy = self.label_offset[0], self.label_offset[1]
        centre = self.xy + np.stack([c * ox - s * oy, s * ox + c * oy], axis=1)
        return centre, self.yaw, self.dims[:2] / 2


# ---------------------------------------------------------------------------------- helpers
def _obj_id(*keys) -> str:
    """A 22-character id like Waymo's label ids, derived from keys."""
    raw = derive_seed(*keys, "a").to_bytes(8, "little") + derive_seed(*keys, "b").to_bytes(
        8, "little"
    )
    return base64.urlsafe_b64encode(raw).decode()[:22]


def _rect_boxes(cx, cy, yaw, hx, hy) -> np.ndarray:
    """``(K, 7)`` float64 boxes of rectangles given by centre, yaw and half extents (broadcast;
    z and height 0): the BEV footprints :mod:`pcdet_atlas.ops.boxes` works on."""
    cx, cy, yaw, hx, hy = np.broadcast_arrays(
        *(np.asarray(v, np.float64) for v in (cx, cy, yaw, hx, hy))
    )
    zero = np.zeros(cx.shape)
    return np.stack([cx, cy, zero, 2 * hx, 2 * hy, zero, yaw], axis=-1).reshape(-1, 7)


def _sample_rect(cx, cy, yaw, hx, hy) -> np.ndarray:
    """Corners, edge midpoints and centre of a rectangle: ``(9, 2)``."""
    c = boxes_to_corners_bev(_rect_boxes(cx, cy, yaw, hx, hy))[0]
    mids = (c + np.roll(c, -1, axis=0)) / 2
    return np.concatenate([c, mids, [[cx, cy]]])


def _track(path: Path, offset: float, t: np.ndarray, s: np.ndarray, times: np.ndarray, direction):
    """Pose, speed and acceleration at ``times`` of a motion ``s(t)`` along lane ``offset``."""

    def pos(tt):
        x, y, h = path.offset_pose(np.interp(tt, t, s), offset)
        return np.stack([x, y], axis=1), h

    xy, h = pos(times)
    h_step = 0.05
    ahead, _ = pos(times + h_step)
    behind, _ = pos(np.maximum(times - h_step, 0.0))
    dt = times + h_step - np.maximum(times - h_step, 0.0)
    speed = (ahead - behind) / dt[:, None]
    h2 = 0.1
    a2, _ = pos(times + h2)
    b2, _ = pos(np.maximum(times - h2, 0.0))
    accel = (a2 - 2 * xy + b2) / h2**2
    accel[times < h2] = 0.0  # one-sided start: undefined, as for the first frame of a log
    yaw = h if direction > 0 else h + math.pi
    return xy, limit_period(yaw), speed, accel


# ---------------------------------------------------------------------------------- the scene
class SyntheticScene:
    """World, road users and ego trajectory of one synthetic sequence.

    Args:
        seed: dataset seed.
        split: ``'train'`` or ``'val'`` (part of every random key).
        index: sequence index within the split.
        num_frames: frames at 10 Hz.
    """

    def __init__(self, seed: int, split: str, index: int, num_frames: int):
        if num_frames < 1:
            raise ValueError(f"num_frames must be >= 1, got {num_frames}")
        self.seed, self.split, self.index, self.num_frames = (
            int(seed),
            split,
            int(index),
            num_frames,
        )
        self.times = np.arange(num_frames) * FRAME_DT
        self._keys = (self.seed, "synthetic_waymo", split, self.index)
        rng = self.random_generator("layout")
        self.cross = CrossSection(lanes_per_direction=int(rng.choice([1, 2], p=[0.4, 0.6])))
        self._build_route(rng)
        self._build_ego()
        self.road_map = RoadMap(self.roads, self.cross, self.junction_centres)
        self._build_static()
        self._build_actors()

    def random_generator(self, *purpose) -> np.random.Generator:
        """The numpy generator of this sequence for ``purpose`` (keys: seed, split, index, ...)."""
        return numpy_generator(*self._keys, *purpose)

    # ------------------------------------------------------------------ route and roads
    def _build_route(self, rng):
        cross = self.cross
        hw = cross.half_width
        turn_r = hw + 2.0
        duration = self.num_frames * FRAME_DT
        self.ego_cruise = float(rng.uniform(7.0, 12.5))
        needed = _BACK + self.ego_cruise * duration + 120.0
        pieces = [(_BACK + rng.uniform(15.0, 45.0), 0.0)]  # a junction soon after the start
        length, heading_quarter, curve_acc = pieces[0][0], 0, 0.0
        junctions = []  # (s_enter, s_exit, turn)
        while length < needed:
            if rng.uniform() < 0.65 or len(junctions) == 0:
                options = [t for t in (-1, 0, 1) if abs(heading_quarter + t) <= 1]
                weights = np.array([0.4 if t else (0.2 if not junctions else 0.3) for t in options])
                turn = int(rng.choice(options, p=weights / weights.sum()))
                if turn == 0:
                    pieces.append((2 * turn_r, 0.0))
                else:
                    pieces.append((turn_r * math.pi / 2, turn / turn_r))
                junctions.append((length, length + pieces[-1][0], turn))
                heading_quarter += turn
            else:
                radius = rng.uniform(60.0, 180.0)
                angle = math.radians(rng.uniform(12.0, 35.0))
                sign = -np.sign(curve_acc) if abs(curve_acc) > 0.3 else rng.choice([-1.0, 1.0])
                pieces.append((radius * angle, sign / radius))
                curve_acc += sign * angle
            length += pieces[-1][0]
            pieces.append((rng.uniform(45.0, 100.0), 0.0))
            length += pieces[-1][0]
        start = rng.uniform(-3000.0, 3000.0, size=2)
        yaw0 = rng.uniform(-math.pi, math.pi)
        self.route = Path(start, yaw0, pieces)
        self.roads = [Road(self.route, 0.0, self.route.length, "route")]
        centres, self.junctions = [], []
        for s_in, s_out, turn in junctions:
            x, y, h_in = self.route.pose(s_in)
            centre = np.array([x + turn_r * math.cos(h_in), y + turn_r * math.sin(h_in)])
            h_out = h_in + turn * math.pi / 2
            used = {round((h_in + math.pi) % (2 * math.pi), 3), round(h_out % (2 * math.pi), 3)}
            for k in range(4):
                h = h_in + k * math.pi / 2
                if round(h % (2 * math.pi), 3) in used:
                    continue
                arm = Path(centre, h, [(_ARM_LENGTH, 0.0)])
                self.roads.append(Road(arm, 0.0, _ARM_LENGTH, "arm"))
            if turn != 0:  # the straight corner pieces under the turning arc
                for h in (h_in + math.pi, h_out):
                    fill = Path(centre, h, [(turn_r, 0.0)])
                    self.roads.append(Road(fill, 0.0, turn_r, "fill"))
            centres.append(centre)
            self.junctions.append(
                {"centre": centre, "s_enter": s_in, "s_exit": s_out, "turn": turn, "h_in": h_in}
            )
        self.junction_centres = np.array(centres).reshape(-1, 2)

    def _build_ego(self):
        rng = self.random_generator("ego")
        duration = self.num_frames * FRAME_DT
        stops = []
        for j, junc in enumerate(self.junctions):
            if junc["s_enter"] > _BACK + 8.0 and rng.uniform() < (0.7 if j == 0 else 0.4):
                stops.append((junc["s_enter"] - 1.0, float(rng.uniform(1.0, 4.0))))
        v0 = 0.0 if rng.uniform() < 0.25 else self.ego_cruise
        self.ego_offset = self.cross.lane_offset(self.cross.lanes_per_direction - 1)
        t, s = simulate_motion(
            self.route, self.ego_offset, _BACK, duration + 1.0, self.ego_cruise, v0=v0, stops=stops
        )
        xy, yaw, _, _ = _track(self.route, self.ego_offset, t, s, self.times, 1)
        self.ego_xy, self.ego_yaw = xy, yaw
        self.ego_stops = stops

    def pose(self, f: int) -> np.ndarray:
        """Vehicle -> global 4x4 (float64) of frame ``f``; the ground is the plane z = 0."""
        c, s = math.cos(self.ego_yaw[f]), math.sin(self.ego_yaw[f])
        pose = np.eye(4)
        pose[:2, :2] = [[c, -s], [s, c]]
        pose[:2, 3] = self.ego_xy[f]
        return pose

    def _near_ego(self, xy: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Whether ``(N, 2)`` points come within ``_CULL + margin`` of the ego path."""
        xy = np.asarray(xy).reshape(-1, 2)
        path = self.ego_xy[:: max(1, len(self.ego_xy) // 40)]
        d = np.linalg.norm(xy[:, None, :] - path[None, :, :], axis=2).min(axis=1)
        return d < _CULL + margin

    def _clear_of_roads(self, pts: np.ndarray, clearance: float) -> bool:
        return bool(self.road_map.distance(pts).min() >= clearance)

    # ------------------------------------------------------------------ static world
    def _build_static(self):
        rng = self.random_generator("static")
        cross = self.cross
        hw = cross.half_width
        box_list, cyl_list = [], []  # (params, albedo, surface)
        footprints = []  # placed building / wall footprints, (1, 7) boxes
        self.sign_specs = []  # (x, y, yaw, width, height, z_centre)
        for road in self.roads:
            if road.kind == "fill":
                continue
            length = road.s_end - road.s_start
            for side in (-1.0, 1.0):
                # sidewalk slabs (the raised curb), 4 m pieces
                n = int(math.ceil(length / 4.0))
                s_mid = road.s_start + (np.arange(n) + 0.5) * length / n
                off = side * (hw + cross.sidewalk_width / 2)
                x, y, h = road.path.offset_pose(s_mid, off)
                keep = self._near_ego(np.stack([x, y], 1), 10.0)
                for i in np.nonzero(keep)[0]:
                    pts = _sample_rect(
                        x[i], y[i], h[i], length / n / 2 + 0.02, cross.sidewalk_width / 2
                    )
                    if self._clear_of_roads(pts, hw - 0.25):
                        box_list.append(
                            (
                                [x[i], y[i], cross.curb_height / 2, length / n + 0.04,
                                 cross.sidewalk_width, cross.curb_height, h[i]],
                                0.3 * (1 + 0.1 * rng.standard_normal()),
                                SURFACE_SOLID,
                            )
                        )  # fmt: skip
                self._place_buildings(rng, road, side, box_list, footprints)
                self._place_furniture(rng, road, side, box_list, cyl_list)
        self.static = PartSet.build(boxes=box_list, cylinders=cyl_list)
        self._build_no_label_zones()

    def _build_no_label_zones(self):
        """0-2 off-road rectangles (e.g. a parking lot behind the sidewalk) flagged as Waymo
        no-label zones: their points get NLZ = 1 and nothing inside them is labelled."""
        rng = self.random_generator("nlz")
        cross = self.cross
        zones = []
        roads = [r for r in self.roads if r.kind != "fill"]
        wanted = int(rng.choice([0, 1, 2], p=[0.4, 0.4, 0.2]))
        for _ in range(8 * wanted):  # a few tries per zone
            if len(zones) == wanted:
                break
            road = roads[int(rng.integers(len(roads)))]
            side = float(rng.choice([-1.0, 1.0]))
            length, depth = rng.uniform(20.0, 60.0), rng.uniform(15.0, 35.0)
            s_mid = rng.uniform(road.s_start + length / 2, max(road.s_end - length / 2, 1.0))
            off = side * (cross.sidewalk_outer + 1.0 + depth / 2)
            x, y, h = (float(v) for v in road.path.offset_pose(s_mid, off))
            pts = _sample_rect(x, y, h, length / 2, depth / 2)
            if self._near_ego(np.array([[x, y]]))[0] and self._clear_of_roads(
                pts, cross.sidewalk_outer + 0.5
            ):
                zones.append([x, y, h, length / 2, depth / 2])
        self.no_label_zones = np.asarray(zones, dtype=np.float64).reshape(-1, 5)

    def in_no_label_zone(self, xy: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: ``(N, 2)`` global points inside a no-label zone."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        inside = np.zeros(len(xy), dtype=bool)
        for cx, cy, yaw, hx, hy in self.no_label_zones:
            rx, ry = xy[:, 0] - cx, xy[:, 1] - cy
            c, s = math.cos(yaw), math.sin(yaw)
            inside |= (np.abs(rx * c + ry * s) <= hx) & (np.abs(-rx * s + ry * c) <= hy)
        return inside

    def _place_buildings(self, rng, road, side, box_list, footprints):
        cross = self.cross
        cursor = road.s_start + rng.uniform(0.0, 8.0)
        while cursor < road.s_end:
            cursor += rng.uniform(1.0, 9.0) if rng.uniform() < 0.85 else rng.uniform(15.0, 35.0)
            kind = rng.choice(["building", "wall", "hedge"], p=[0.78, 0.12, 0.1])
            length = rng.uniform(8.0, 34.0)
            for _attempt in range(2):
                s_mid = cursor + length / 2
                if s_mid > road.s_end:
                    break
                if kind == "building":
                    depth = rng.uniform(8.0, 22.0)
                    setback = rng.uniform(0.4, 5.0)
                else:
                    depth = 0.35 if kind == "wall" else rng.uniform(0.8, 1.4)
                    setback = rng.uniform(0.3, 1.5)
                off = side * (cross.sidewalk_outer + setback + depth / 2)
                x, y, h = road.path.offset_pose(s_mid, off)
                x, y, h = float(x), float(y), float(h)
                if not self._near_ego(np.array([[x, y]]), length / 2 + depth)[0]:
                    break
                pts = _sample_rect(x, y, h, length / 2, depth / 2)
                rect = _rect_boxes(x, y, h, length / 2, depth / 2)
                clear = self._clear_of_roads(pts, cross.sidewalk_outer + 0.25)
                if clear and footprints:
                    clear = not boxes_bev_overlap(rect, np.concatenate(footprints)).any()
                if clear:
                    if kind == "building":
                        u = rng.uniform()
                        height = rng.uniform(4, 10) if u < 0.6 else rng.uniform(10, 28)
                        albedo, surface = rng.uniform(0.12, 0.5), SURFACE_SOLID
                    elif kind == "wall":
                        height, albedo, surface = rng.uniform(1.0, 2.6), rng.uniform(0.2, 0.45), 0
                    else:
                        height, albedo = rng.uniform(0.8, 2.0), rng.uniform(0.08, 0.2)
                        surface = SURFACE_FOLIAGE
                    box_list.append(([x, y, height / 2, length, depth, height, h], albedo, surface))
                    footprints.append(rect)
                    break
                length /= 2
            cursor += length

    def _place_furniture(self, rng, road, side, box_list, cyl_list):
        """Street lights, trees and signs along the curb (clear of every carriageway)."""
        cross = self.cross
        hw = cross.half_width
        cursor = road.s_start + rng.uniform(3.0, 15.0)
        while cursor < road.s_end:
            x, y, h = (float(v) for v in road.path.offset_pose(cursor, side * (hw + 0.5)))
            if self._near_ego(np.array([[x, y]]))[0] and self._clear_of_roads(
                np.array([[x, y]]), hw + 0.3
            ):
                u = rng.uniform()
                inward = h + (math.pi / 2 if side < 0 else -math.pi / 2)  # towards the road
                if u < 0.45:  # street light with an arm over the road
                    height = rng.uniform(6.5, 9.0)
                    cyl_list.append(([x, y, 0.0, height, rng.uniform(0.09, 0.14)], 0.35, 0))
                    arm = rng.uniform(1.2, 2.4)
                    ax, ay = x + math.cos(inward) * arm / 2, y + math.sin(inward) * arm / 2
                    box_list.append(([ax, ay, height - 0.1, arm, 0.18, 0.16, inward], 0.4, 0))
                elif u < 0.85:  # tree: trunk and foliage crown
                    trunk = rng.uniform(3.8, 4.6)
                    cyl_list.append(([x, y, 0.0, trunk, rng.uniform(0.14, 0.25)], 0.2, 0))
                    crown = rng.uniform(1.3, 2.2)
                    top = trunk + rng.uniform(2.5, 4.5)
                    cyl_list.append(
                        ([x, y, trunk, top, crown], rng.uniform(0.1, 0.25), SURFACE_FOLIAGE)
                    )
                else:  # sign on a post facing the oncoming traffic of this side
                    plate_w, plate_h = rng.uniform(0.6, 0.9), rng.uniform(0.6, 0.9)
                    z_c = rng.uniform(2.0, 2.6) + plate_h / 2
                    cyl_list.append(([x, y, 0.0, z_c - plate_h / 2, 0.04], 0.4, 0))
                    facing = h if side < 0 else h + math.pi
                    self.sign_specs.append((x, y, facing, plate_w, plate_h, z_c))
            cursor += rng.uniform(12.0, 30.0)

    # ------------------------------------------------------------------ road users
    def _build_actors(self):
        candidates: list[Actor] = []  # in priority order for the collision filter
        candidates += self._signs()
        candidates += self._parked()
        candidates += self._cross_traffic()
        candidates += self._route_traffic()
        candidates += self._cyclists()
        candidates += self._pedestrians()
        self.actors = self._collision_filter(candidates)

    def _make_actor(self, name, kind, key, dims, offset, parts, xy, yaw, speed, accel, **kw):
        return Actor(
            name=name,
            kind=kind,
            obj_id=_obj_id(*self._keys, "actor", *key),
            dims=np.asarray(dims, dtype=np.float64),
            label_offset=np.asarray(offset, dtype=np.float64),
            parts=parts,
            xy=xy,
            yaw=yaw,
            speed=speed,
            accel=accel,
            **kw,
        )

    def _static_track(self, x, y, yaw):
        f = self.num_frames
        return (
            np.tile([x, y], (f, 1)).astype(np.float64),
            np.full(f, limit_period(yaw)),
            np.zeros((f, 2)),
            np.zeros((f, 2)),
        )

    def _signs(self):
        out = []
        for i, (x, y, yaw, w, h, z_c) in enumerate(self.sign_specs):
            parts = PartSet.build(
                boxes=[([0.0, 0.0, z_c, 0.05, w, h, 0.0], 0.8, SURFACE_RETRO)],
            )
            xy, yw, sp, ac = self._static_track(x, y, yaw)
            out.append(
                self._make_actor(
                    "Sign", "sign", ("sign", i), [0.1, w, h], [0.0, 0.0, z_c], parts, xy, yw, sp, ac
                )
            )
        return out

    def _vehicle(self, rng):
        kind = str(rng.choice(["car", "van", "truck"], p=[0.72, 0.18, 0.10]))
        parts, dims = vehicle_shape(kind, rng)
        return kind, parts, dims

    def _parked(self):
        rng = self.random_generator("parked")
        cross = self.cross
        out = []
        for r_i, road in enumerate(self.roads):
            if road.kind == "fill":
                continue
            for side in (-1.0, 1.0):
                occupancy = rng.uniform(0.2, 0.85)
                cursor = road.s_start + rng.uniform(0.0, 10.0)
                k = 0
                while cursor < road.s_end:
                    kind, parts, dims = self._vehicle(rng)
                    s_mid = cursor + dims[0] / 2
                    x, y, h = (
                        float(v) for v in road.path.offset_pose(s_mid, -side * cross.parking_offset)
                    )
                    park = rng.uniform() < occupancy
                    if park and self._near_ego(np.array([[x, y]]))[0]:
                        yaw = h if side < 0 else h + math.pi
                        pts = _sample_rect(x, y, yaw, dims[0] / 2, dims[1] / 2)
                        in_junction = self.road_map.near_junction(np.array([[x, y]]), 6.0)[0]
                        if not in_junction and self._clear_of_roads(
                            pts, cross.carriageway + cross.bike_lane_width - 0.05
                        ):
                            xy, yw, sp, ac = self._static_track(x, y, yaw)
                            out.append(
                                self._make_actor(
                                    "Vehicle", kind, ("parked", r_i, side, k), dims,
                                    [0, 0, dims[2] / 2], parts, xy, yw, sp, ac,
                                )
                            )  # fmt: skip
                    k += 1
                    cursor += dims[0] + rng.uniform(0.8, 5.0) + (0 if park else rng.uniform(0, 6))
        return out

    def _moving_vehicle(self, rng, key, path, offset, s0, direction, v_cruise, stops=()):
        kind, parts, dims = self._vehicle(rng)
        duration = self.num_frames * FRAME_DT + 1.0
        t, s = simulate_motion(
            path, offset, s0, duration, v_cruise, direction=direction, stops=list(stops)
        )
        xy, yaw, speed, accel = _track(path, offset, t, s, self.times, direction)
        if not self._near_ego(xy[:: max(1, len(xy) // 20)]).any():
            return None
        return self._make_actor(
            "Vehicle", kind, key, dims, [0, 0, dims[2] / 2], parts, xy, yaw, speed, accel
        )

    def _route_traffic(self):
        rng = self.random_generator("route_traffic")
        cross = self.cross
        out = []
        for direction in (1, -1):
            for lane in range(cross.lanes_per_direction):
                offset = direction * cross.lane_offset(lane)
                lane_speed = rng.uniform(6.0, 13.5)
                is_ego_lane = direction == 1 and lane == cross.lanes_per_direction - 1
                if is_ego_lane:
                    lane_speed = max(lane_speed, self.ego_cruise + 1.0)
                    s = _BACK + rng.uniform(18.0, 35.0)
                else:
                    s = rng.uniform(0.0, 30.0)
                k = 0
                while s < self.route.length:
                    v = lane_speed + rng.uniform(-0.4, 0.4)
                    actor = self._moving_vehicle(
                        rng, ("route", direction, lane, k), self.route, offset, s, direction, v
                    )
                    if actor is not None:
                        out.append(actor)
                    k += 1
                    s += rng.uniform(14.0, 60.0)
        return out

    def _cross_traffic(self):
        rng = self.random_generator("cross_traffic")
        cross = self.cross
        hw = cross.half_width
        out = []
        for r_i, road in enumerate(self.roads):
            if road.kind != "arm":
                continue
            for lane in range(cross.lanes_per_direction):
                # inbound: queue at the stop line (arm s decreasing towards the junction)
                stop = hw + 4.5
                s = stop + rng.uniform(0.0, 25.0)
                k = 0
                while s < road.s_end and rng.uniform() < 0.75:
                    actor = self._moving_vehicle(
                        rng, ("in", r_i, lane, k), road.path, -cross.lane_offset(lane), s, -1,
                        rng.uniform(6.0, 11.0), stops=[(stop, 1e9)],
                    )  # fmt: skip
                    if actor is not None:
                        out.append(actor)
                        stop += actor.dims[0] + rng.uniform(1.5, 3.5)
                    k += 1
                    s = max(s, stop) + rng.uniform(8.0, 40.0)
                # outbound: leaving the junction
                s = hw + rng.uniform(4.0, 20.0)
                k = 0
                while s < road.s_end and rng.uniform() < 0.6:
                    actor = self._moving_vehicle(
                        rng, ("out", r_i, lane, k), road.path, cross.lane_offset(lane), s, 1,
                        rng.uniform(6.0, 12.0),
                    )  # fmt: skip
                    if actor is not None:
                        out.append(actor)
                    k += 1
                    s += rng.uniform(15.0, 40.0)
        return out

    def _cyclists(self):
        rng = self.random_generator("cyclists")
        cross = self.cross
        out = []
        for k in range(int(rng.integers(3, 10))):
            road = (
                self.roads[0] if rng.uniform() < 0.7 else self.roads[rng.integers(len(self.roads))]
            )
            if road.kind == "fill":
                continue
            direction = int(rng.choice([-1, 1]))
            offset = direction * cross.bike_offset
            s0 = rng.uniform(road.s_start, road.s_end)
            parts, dims = cyclist_shape(rng)
            v = rng.uniform(3.0, 7.0)
            duration = self.num_frames * FRAME_DT + 1.0
            t, s = simulate_motion(
                road.path, offset, s0, duration, v, direction=direction, accel=1.0, decel=2.0
            )
            xy, yaw, speed, accel = _track(road.path, offset, t, s, self.times, direction)
            if self._near_ego(xy[:: max(1, len(xy) // 20)]).any():
                out.append(
                    self._make_actor(
                        "Cyclist", "cyclist", ("cyclist", k), dims, [0, 0, dims[2] / 2], parts,
                        xy, yaw, speed, accel,
                    )
                )  # fmt: skip
        return out

    def _pedestrians(self):
        rng = self.random_generator("pedestrians")
        cross = self.cross
        hw = cross.half_width
        out = []
        duration = self.num_frames * FRAME_DT
        k = 0
        for road in self.roads:
            if road.kind == "fill":
                continue
            length = road.s_end - road.s_start
            for side in (-1.0, 1.0):
                for _ in range(int(rng.poisson(length / 22.0))):
                    k += 1
                    lateral = side * (hw + rng.uniform(1.2, cross.sidewalk_width - 0.5))
                    s0 = rng.uniform(road.s_start, road.s_end)
                    x0, y0, _ = road.path.offset_pose(s0, lateral)
                    if not self._near_ego(np.array([[x0, y0]]))[0]:
                        continue
                    walkable = self._walkable_stretch(road, lateral, s0)
                    if walkable is None:
                        continue
                    direction = int(rng.choice([-1, 1]))
                    v = 0.0 if rng.uniform() < 0.25 else rng.uniform(0.8, 1.7)
                    end = walkable[1] if direction > 0 else walkable[0]
                    t, s = self._walk(road.path, lateral, s0, v, direction, [(end, 1e9)])
                    out.append(
                        self._pedestrian(rng, ("ped", k), road.path, lateral, t, s, direction)
                    )
        for j, road in enumerate(self.roads):  # crossing at the crosswalks of the arms
            if road.kind != "arm" or rng.uniform() > 0.7:
                continue
            x, y, h = (float(v) for v in road.path.pose(hw + 2.0))
            side = float(rng.choice([-1.0, 1.0]))
            across = h + side * math.pi / 2
            start = np.array([x, y]) - (hw + 1.5) * np.array([math.cos(across), math.sin(across)])
            cross_path = Path(start, across, [(2 * (hw + 1.5), 0.0)])
            for i in range(int(rng.integers(1, 4))):
                v = rng.uniform(1.0, 1.6)
                t0 = rng.uniform(-0.5, 0.7) * duration  # when it steps off the curb
                stops = [(cross_path.length, 1e9)]
                if t0 > 0:  # waits at the curb first
                    s0, v0, stops = 0.0, 0.0, [(0.0, t0), *stops]
                else:
                    s0, v0 = min(-t0 * v, cross_path.length), v
                t, s = self._walk(cross_path, 0.0, s0, v, 1, stops, v0=v0)
                lat = rng.uniform(-1.2, 1.2)
                out.append(self._pedestrian(rng, ("crossing", j, i), cross_path, lat, t, s, 1))
        return out

    def _walk(self, path, lateral, s0, v, direction, stops, v0=None):
        """Walking motion (accelerate 0.8 m/s^2, stop at 1.2 m/s^2) along a lane of ``path``."""
        duration = self.num_frames * FRAME_DT + 1.0
        if v <= 0:
            return np.array([0.0, duration]), np.array([s0, s0])
        return simulate_motion(
            path, lateral, s0, duration, v, v0=v0, direction=direction, stops=stops,
            accel=0.8, decel=1.2, lateral_accel=50.0,
        )  # fmt: skip

    def _walkable_stretch(self, road, lateral, s0):
        ss = np.arange(road.s_start, road.s_end, 1.0)
        x, y, _ = road.path.offset_pose(ss, lateral)
        ok = self.road_map.distance(np.stack([x, y], 1)) >= self.cross.half_width + 0.5
        i0 = int(np.clip(np.searchsorted(ss, s0), 0, len(ss) - 1))
        if not ok[i0]:
            return None
        lo = i0
        while lo > 0 and ok[lo - 1]:
            lo -= 1
        hi = i0
        while hi < len(ss) - 1 and ok[hi + 1]:
            hi += 1
        return float(ss[lo]), float(ss[hi])

    def _pedestrian(self, rng, key, path, lateral, t, s, direction):
        parts, dims, gait = pedestrian_shape(rng)
        xy, yaw, speed, accel = _track(path, lateral, t, s, self.times, direction)
        walked = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
        phase = walked / 0.75 * math.pi + rng.uniform(0, 2 * math.pi)
        # a standing pedestrian keeps the heading it would walk with
        return self._make_actor(
            "Pedestrian", "pedestrian", key, dims, [0, 0, dims[2] / 2], parts, xy, yaw, speed,
            accel, gait=gait, gait_phase=phase,
        )  # fmt: skip

    def _collision_filter(self, candidates: list[Actor]) -> list[Actor]:
        """Keep candidates in order unless their label box overlaps the ego or a kept actor at
        any frame (0.25 m margin)."""
        f = self.num_frames
        ex, ey, edx, edy = EGO_BOX_LOCAL
        c, s = np.cos(self.ego_yaw), np.sin(self.ego_yaw)
        ego_c = self.ego_xy + np.stack([c * ex - s * ey, s * ex + c * ey], 1)
        kept_c = [ego_c]
        kept_yaw = [self.ego_yaw]
        kept_half = [np.array([edx / 2, edy / 2])]
        kept = []
        margin = 0.25
        for actor in candidates:
            centre, yaw, half = actor.footprint()
            half = half + margin
            all_c = np.stack(kept_c)  # (K, F, 2)
            all_half = np.stack(kept_half)  # (K, 2)
            radius = np.linalg.norm(half) + np.linalg.norm(all_half, axis=1)  # (K,)
            dist = np.linalg.norm(all_c - centre[None], axis=2)  # (K, F)
            near = dist < radius[:, None]
            hit = False
            if near.any():
                ki, fi = np.nonzero(near)
                a = _rect_boxes(centre[fi, 0], centre[fi, 1], yaw[fi], half[0], half[1])
                kyaw = np.stack(kept_yaw)[ki, fi]
                b = _rect_boxes(
                    all_c[ki, fi, 0], all_c[ki, fi, 1], kyaw, all_half[ki, 0], all_half[ki, 1]
                )
                hit = bool(np.diagonal(boxes_bev_overlap(a, b)).any())
            if not hit:
                kept.append(actor)
                kept_c.append(centre)
                kept_yaw.append(yaw)
                kept_half.append(half)
        assert all(len(a.xy) == f for a in kept)
        return kept

    # ------------------------------------------------------------------ per frame
    def _to_vehicle(self, f: int, parts: PartSet) -> PartSet:
        c, s = math.cos(-self.ego_yaw[f]), math.sin(-self.ego_yaw[f])
        ex, ey = self.ego_xy[f]
        b = parts.boxes.copy()
        rx, ry = b[:, 0] - ex, b[:, 1] - ey
        b[:, 0], b[:, 1] = c * rx - s * ry, s * rx + c * ry
        b[:, 6] = limit_period(b[:, 6] - self.ego_yaw[f])
        cy = parts.cylinders.copy()
        rx, ry = cy[:, 0] - ex, cy[:, 1] - ey
        cy[:, 0], cy[:, 1] = c * rx - s * ry, s * rx + c * ry
        return PartSet(
            b, parts.box_albedo, parts.box_surface, cy, parts.cyl_albedo, parts.cyl_surface
        )

    def primitives(
        self,
        f: int,
        sensor_xy=(1.43, 0.0),
        max_range: float = 75.0,
        device: str | torch.device = "cpu",
        dtype: torch.dtype = torch.float32,
    ) -> Primitives:
        """All primitives of frame ``f`` in the vehicle frame, those beyond range dropped."""
        moving = [a.parts_at(f) for a in self.actors]
        world = self._to_vehicle(f, PartSet.concat([self.static, *moving]))
        sx, sy = sensor_xy
        b_reach = np.hypot(world.boxes[:, 3], world.boxes[:, 4]) / 2
        b_keep = np.hypot(world.boxes[:, 0] - sx, world.boxes[:, 1] - sy) - b_reach <= max_range
        c_keep = (
            np.hypot(world.cylinders[:, 0] - sx, world.cylinders[:, 1] - sy) - world.cylinders[:, 4]
            <= max_range
        )
        return Primitives(
            boxes=torch.as_tensor(world.boxes[b_keep]),
            box_albedo=torch.as_tensor(world.box_albedo[b_keep]),
            box_surface=torch.as_tensor(world.box_surface[b_keep]),
            cylinders=torch.as_tensor(world.cylinders[c_keep]),
            cyl_albedo=torch.as_tensor(world.cyl_albedo[c_keep]),
            cyl_surface=torch.as_tensor(world.cyl_surface[c_keep]),
        ).to(device, dtype)

    def labels(self, f: int, sensor_xy=(1.43, 0.0), max_range: float = 75.0) -> dict:
        """Objects of frame ``f`` whose box centre lies within ``max_range`` (horizontally) of
        the sensor and outside the no-label zones: ``name``, ``obj_ids``, ``boxes`` ``(N, 7)``
        in the vehicle frame (float64), ``speed_global`` and ``accel_global`` ``(N, 2)``."""
        names, ids, boxes, speed, accel = [], [], [], [], []
        c, s = math.cos(-self.ego_yaw[f]), math.sin(-self.ego_yaw[f])
        ex, ey = self.ego_xy[f]
        for a in self.actors:
            ca, sa = math.cos(a.yaw[f]), math.sin(a.yaw[f])
            ox, oy, oz = a.label_offset
            gx = a.xy[f, 0] + ca * ox - sa * oy - ex
            gy = a.xy[f, 1] + sa * ox + ca * oy - ey
            x, y = c * gx - s * gy, s * gx + c * gy
            if math.hypot(x - sensor_xy[0], y - sensor_xy[1]) > max_range:
                continue
            if self.in_no_label_zone(np.array([[gx + ex, gy + ey]]))[0]:
                continue
            heading = float(limit_period(a.yaw[f] - self.ego_yaw[f]))
            names.append(a.name)
            ids.append(a.obj_id)
            boxes.append([x, y, oz, *a.dims, heading])
            speed.append(a.speed[f])
            accel.append(a.accel[f])
        return {
            "name": names,
            "obj_ids": ids,
            "boxes": np.asarray(boxes, dtype=np.float64).reshape(-1, 7),
            "speed_global": np.asarray(speed, dtype=np.float64).reshape(-1, 2),
            "accel_global": np.asarray(accel, dtype=np.float64).reshape(-1, 2),
        }
