"""Shapes of the synthetic road users and street furniture as primitive parts.

Each shape is a :class:`PartSet` in the object's own frame (x forward, y left, z up from the
ground), plus the label box OpenPCDet/Waymo would annotate. Vehicles are built from a body, a
cabin (or a cab and a cargo box) and wheels, pedestrians from legs, torso and head, cyclists from a
bicycle and a rider, so LiDAR profiles show the real structure (hood lower than the roof, legs).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "PartSet",
    "SURFACE_SOLID",
    "SURFACE_GLASS",
    "SURFACE_FOLIAGE",
    "SURFACE_RETRO",
    "vehicle_shape",
    "pedestrian_shape",
    "pedestrian_legs",
    "cyclist_shape",
    "VEHICLE_KINDS",
]

#: Surface classes (index into the sensor model's drop/elongation tables).
SURFACE_SOLID, SURFACE_GLASS, SURFACE_FOLIAGE, SURFACE_RETRO = 0, 1, 2, 3
VEHICLE_KINDS = ("car", "van", "truck")


@dataclass
class PartSet:
    """Boxes ``(P, 7)`` ``[x, y, z, dx, dy, dz, yaw]`` and vertical cylinders ``(Q, 5)``
    ``[x, y, z0, z1, r]`` with per-part albedo and surface class, in one frame."""

    boxes: np.ndarray
    box_albedo: np.ndarray
    box_surface: np.ndarray
    cylinders: np.ndarray
    cyl_albedo: np.ndarray
    cyl_surface: np.ndarray

    @staticmethod
    def empty() -> PartSet:
        return PartSet(
            np.zeros((0, 7)),
            np.zeros(0),
            np.zeros(0, dtype=np.int64),
            np.zeros((0, 5)),
            np.zeros(0),
            np.zeros(0, dtype=np.int64),
        )

    @staticmethod
    def build(boxes=(), cylinders=()) -> PartSet:
        """From lists of ``(params, albedo, surface)`` tuples."""
        b = np.array([p for p, _, _ in boxes], dtype=np.float64).reshape(-1, 7)
        c = np.array([p for p, _, _ in cylinders], dtype=np.float64).reshape(-1, 5)
        return PartSet(
            b,
            np.array([a for _, a, _ in boxes], dtype=np.float64),
            np.array([s for _, _, s in boxes], dtype=np.int64),
            c,
            np.array([a for _, a, _ in cylinders], dtype=np.float64),
            np.array([s for _, _, s in cylinders], dtype=np.int64),
        )

    @staticmethod
    def concat(parts: list[PartSet]) -> PartSet:
        if not parts:
            return PartSet.empty()
        return PartSet(
            np.concatenate([p.boxes for p in parts]).reshape(-1, 7),
            np.concatenate([p.box_albedo for p in parts]),
            np.concatenate([p.box_surface for p in parts]).astype(np.int64),
            np.concatenate([p.cylinders for p in parts]).reshape(-1, 5),
            np.concatenate([p.cyl_albedo for p in parts]),
            np.concatenate([p.cyl_surface for p in parts]).astype(np.int64),
        )

    def placed(self, x: float, y: float, yaw: float, z: float = 0.0) -> PartSet:
        """The parts moved by a planar pose (rotation ``yaw`` about z, then translation)."""
        c, s = np.cos(yaw), np.sin(yaw)
        b = self.boxes.copy()
        b[:, 0] = x + c * self.boxes[:, 0] - s * self.boxes[:, 1]
        b[:, 1] = y + s * self.boxes[:, 0] + c * self.boxes[:, 1]
        b[:, 2] += z
        b[:, 6] += yaw
        cy = self.cylinders.copy()
        cy[:, 0] = x + c * self.cylinders[:, 0] - s * self.cylinders[:, 1]
        cy[:, 1] = y + s * self.cylinders[:, 0] + c * self.cylinders[:, 1]
        cy[:, 2:4] += z
        return PartSet(b, self.box_albedo, self.box_surface, cy, self.cyl_albedo, self.cyl_surface)


def _wheels(length, width, radius, overhang, albedo=0.06):
    out = []
    for sx in (1, -1):
        for sy in (1, -1):
            x = sx * (length / 2 - overhang)
            y = sy * (width / 2 - 0.13)
            out.append(([x, y, radius, 2 * radius, 0.24, 2 * radius, 0.0], albedo, SURFACE_SOLID))
    return out


def vehicle_shape(kind: str, rng: np.random.Generator) -> tuple[PartSet, np.ndarray]:
    """A car, van or truck: parts and label dims ``[l, w, h]`` (label box centre at ``h / 2``).

    car: body (hood/trunk line at ~0.55-0.65 h) + a narrower, shorter glass cabin on top;
    van: low nose + tall rear box; truck: cab + separate cargo box on a chassis. All with wheels.
    """
    paint = float(rng.choice([0.08, 0.15, 0.3, 0.45, 0.6]) * rng.uniform(0.85, 1.15))
    glass = float(rng.uniform(0.04, 0.1))
    if kind == "car":
        length, width, height = (
            rng.uniform(3.9, 5.1),
            rng.uniform(1.75, 1.98),
            rng.uniform(1.4, 1.8),
        )
        clearance = rng.uniform(0.22, 0.32)
        belt = height * rng.uniform(0.52, 0.62)
        cab_len = length * rng.uniform(0.42, 0.55)
        cab_x = -length * rng.uniform(0.0, 0.1)
        boxes = [
            ([0, 0, (clearance + belt) / 2, length, width, belt - clearance, 0], paint, 0),
            ([cab_x, 0, (belt + height) / 2, cab_len, width - 0.16, height - belt, 0], glass, 1),
        ]
        boxes += _wheels(length, width, 0.33, length * 0.18)
    elif kind == "van":
        length, width, height = rng.uniform(4.7, 5.9), rng.uniform(1.9, 2.1), rng.uniform(1.9, 2.5)
        clearance = rng.uniform(0.28, 0.38)
        nose = rng.uniform(0.95, 1.15)
        rear_len = length * rng.uniform(0.72, 0.82)
        boxes = [
            ([0, 0, (clearance + nose) / 2, length, width, nose - clearance, 0], paint, 0),
            (
                [
                    -(length - rear_len) / 2,
                    0,
                    (nose + height) / 2,
                    rear_len,
                    width - 0.06,
                    height - nose,
                    0,
                ],
                paint,
                0,
            ),  # fmt: skip
            (
                [
                    -length / 2 + rear_len + 0.04,
                    0,
                    (nose + height) / 2 - 0.1,
                    0.1,
                    width - 0.2,
                    height - nose - 0.2,
                    0,
                ],
                glass,
                1,
            ),  # windscreen  # fmt: skip
        ]
        boxes += _wheels(length, width, 0.36, length * 0.17)
    elif kind == "truck":
        length, width, height = (
            rng.uniform(6.5, 10.0),
            rng.uniform(2.3, 2.55),
            rng.uniform(3.0, 3.7),
        )
        cab_len = rng.uniform(1.9, 2.4)
        cab_h = min(height - 0.2, rng.uniform(2.6, 3.0))
        chassis_top = 1.05
        cargo_len = length - cab_len - 0.3
        cargo_alb = float(rng.uniform(0.35, 0.7))
        boxes = [
            ([length / 2 - cab_len / 2, 0, (0.5 + cab_h) / 2, cab_len, width - 0.1, cab_h - 0.5, 0],
             paint, 0),
            ([-length / 2 + cargo_len / 2, 0, (chassis_top + height) / 2, cargo_len, width,
              height - chassis_top, 0], cargo_alb, 0),
            ([0, 0, 0.8, length - 0.4, width - 0.6, 0.5, 0], 0.05, 0),  # chassis
        ]  # fmt: skip
        boxes += _wheels(length, width, 0.5, 1.2)
    else:
        raise ValueError(f"unknown vehicle kind {kind!r}; expected one of {VEHICLE_KINDS}")
    parts = PartSet.build(boxes=[(list(map(float, p)), a, s) for p, a, s in boxes])
    return parts, np.array([length, width, height], dtype=np.float64)


def pedestrian_shape(rng: np.random.Generator) -> tuple[PartSet, np.ndarray, dict]:
    """Torso and head cylinders (the legs move, see :func:`pedestrian_legs`).

    Returns parts, label dims ``[l, w, h]`` and the gait parameters for the legs.
    """
    height = rng.uniform(1.5, 1.92)
    width = rng.uniform(0.5, 0.8)
    cloth = float(rng.uniform(0.08, 0.5))
    hip = 0.5 * height
    torso_r = rng.uniform(0.15, 0.2)
    cylinders = [
        ([0, 0, hip, 0.84 * height, torso_r], cloth, SURFACE_SOLID),
        ([0, 0, 0.86 * height, height, rng.uniform(0.085, 0.11)], 0.25, SURFACE_SOLID),
        ([0, width / 2 - 0.07, 0.55 * height, 0.82 * height, 0.05], cloth, SURFACE_SOLID),
        ([0, -width / 2 + 0.07, 0.55 * height, 0.82 * height, 0.05], cloth, SURFACE_SOLID),
    ]
    gait = {"hip": hip, "leg_r": rng.uniform(0.065, 0.085), "albedo": float(rng.uniform(0.05, 0.3))}
    length = rng.uniform(0.55, 0.95)
    return PartSet.build(cylinders=cylinders), np.array([length, width, height]), gait


def pedestrian_legs(gait: dict, phase: float, moving: bool) -> PartSet:
    """Two leg cylinders, swung fore/aft by ``0.22 sin(phase)`` m while walking."""
    swing = 0.22 * np.sin(phase) if moving else 0.0
    cyl = [
        ([swing, 0.1, 0.0, gait["hip"], gait["leg_r"]], gait["albedo"], SURFACE_SOLID),
        ([-swing, -0.1, 0.0, gait["hip"], gait["leg_r"]], gait["albedo"], SURFACE_SOLID),
    ]
    return PartSet.build(cylinders=cyl)


def cyclist_shape(rng: np.random.Generator) -> tuple[PartSet, np.ndarray]:
    """A bicycle (two thin wheels, frame) and its rider (legs, torso, head)."""
    length, width, height = rng.uniform(1.7, 1.95), rng.uniform(0.6, 0.85), rng.uniform(1.65, 1.9)
    frame_alb = float(rng.uniform(0.1, 0.5))
    cloth = float(rng.uniform(0.08, 0.5))
    wheel_r = 0.34
    boxes = [
        ([length / 2 - wheel_r, 0, wheel_r, 2 * wheel_r, 0.05, 2 * wheel_r, 0], 0.08, 0),
        ([-length / 2 + wheel_r, 0, wheel_r, 2 * wheel_r, 0.05, 2 * wheel_r, 0], 0.08, 0),
        ([0.0, 0, 0.6, length - 2 * wheel_r + 0.3, 0.06, 0.35, 0], frame_alb, 0),
    ]
    cylinders = [
        ([-0.05, 0.12, 0.3, 0.95, 0.07], cloth, SURFACE_SOLID),
        ([-0.05, -0.12, 0.3, 0.95, 0.07], cloth, SURFACE_SOLID),
        ([0.05, 0, 0.95, 0.84 * height, 0.17], cloth, SURFACE_SOLID),
        ([0.15, 0, 0.86 * height, height, 0.1], 0.25, SURFACE_SOLID),
    ]
    parts = PartSet.build(boxes=boxes, cylinders=cylinders)
    return parts, np.array([length, width, height])
