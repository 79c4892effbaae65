"""Removal-target choice and velocity-guided tracking through a run (docs/attacks.md, "Removal").

Pure functions on ground-truth arrays; no points are touched. Tracking runs in the world frame:
``c_hat_k = c_{k-1} + dt * [vx, vy, 0]`` with the previous box's global speed, then the nearest
same-class box to ``c_hat_k`` within ``d_max`` whose volume ratio to the previous matched box
is in ``[volume_ratio, 1 / volume_ratio]``. If none qualifies the target is *lost* for that frame
(nothing is removed there); the track then coasts on the prediction, with the last matched
velocity and volume, so it can be re-acquired in a later frame.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from pcdet_atlas.config_values import fields_of, read_section, setting
from pcdet_atlas.datasets import waymo_format as wf
from pcdet_atlas.ops.boxes import transform_boxes
from pcdet_atlas.utils.seeding import numpy_generator

__all__ = [
    "FrameLabels",
    "TargetPolicy",
    "Tracker",
    "TrackingConfig",
    "TrackedFrame",
    "choose_target",
]


@dataclass(frozen=True)
class FrameLabels:
    """Ground truth of one frame, as the tracker needs it.

    Attributes:
        boxes: ``(M, 7)`` float64 boxes in the vehicle frame.
        names: ``(M,)`` class names. obj_ids: ``(M,)`` str.
        num_points: ``(M,)`` int64 ``num_points_in_gt``.
        speed_global: ``(M, 2)`` float64 world-frame speed, m/s.
        pose: ``(4, 4)`` float64 vehicle -> world.
    """

    boxes: np.ndarray
    names: np.ndarray
    obj_ids: np.ndarray
    num_points: np.ndarray
    speed_global: np.ndarray
    pose: np.ndarray

    @classmethod
    def from_info(cls, info: Mapping) -> FrameLabels:
        """From an OpenPCDet frame info (a frame without ``annos`` has no boxes)."""
        pose = np.asarray(info["pose"], dtype=np.float64).reshape(4, 4)
        annos = info.get("annos")
        if annos is None or len(annos["name"]) == 0:
            return cls(
                np.zeros((0, 7)),
                np.zeros(0, dtype=str),
                np.zeros(0, dtype=str),
                np.zeros(0, dtype=np.int64),
                np.zeros((0, 2)),
                pose,
            )
        n = len(annos["name"])
        return cls(
            boxes=np.asarray(annos["gt_boxes_lidar"], dtype=np.float64)[:, :7].reshape(n, 7),
            names=np.asarray(annos["name"]).astype(str),
            obj_ids=np.asarray(annos["obj_ids"]).astype(str),
            num_points=np.asarray(annos["num_points_in_gt"], dtype=np.int64).reshape(n),
            speed_global=np.asarray(annos["speed_global"], dtype=np.float64).reshape(n, 2),
            pose=pose,
        )

    def world_boxes(self) -> np.ndarray:
        """``(M, 7)`` boxes in the world frame."""
        return transform_boxes(self.boxes, self.pose) if len(self.boxes) else self.boxes


@dataclass(frozen=True)
class TargetPolicy:
    """How the removal target is chosen at a run's first frame.

    Args:
        policy: ``'nearest'`` (closest eligible box) or ``'random'`` (uniform among eligible,
            seeded by the run).
        class_name: target class.
        min_points: fewest ``num_points_in_gt``.
        range_m: ``(lo, hi)`` band of the box centre's range from the sensor origin, m.
    """

    policy: str = setting(
        "nearest",
        choices=("nearest", "random"),
        expected="'nearest' or 'random'",
        doc="`nearest` or `random`",
    )
    class_name: str = setting(
        "Vehicle",
        key="CLASS",
        choices=wf.WAYMO_CLASSES,
        expected=f"one of {wf.WAYMO_CLASSES}",
        doc="target class",
    )
    min_points: int = setting(
        20, ge=0, expected="a non-negative integer", doc="fewest `num_points_in_gt`"
    )
    range_m: tuple[float, float] = setting(
        (5.0, 50.0), check=lambda r: 0 <= r[0] < r[1],
        expected="[lo, hi] in metres with 0 <= lo < hi",
        doc="range band from the sensor origin, m",
    )  # fmt: skip

    @classmethod
    def from_config(cls, cfg: Mapping | None) -> TargetPolicy:
        """Read a ``TARGET`` section (every key optional)."""
        return read_section(cls, cfg, "TARGET")


def choose_target(
    labels: FrameLabels,
    policy: TargetPolicy,
    sensor_origin: Sequence[float],
    seed_keys: tuple = (),
) -> int | None:
    """Index of the target box in ``labels`` (or ``None`` if no box is eligible).

    ``seed_keys`` key the generator of the ``'random'`` policy (e.g. seed, sequence, run).
    """
    if len(labels.boxes) == 0:
        return None
    rng = np.linalg.norm(labels.boxes[:, :3] - np.asarray(sensor_origin)[None], axis=1)
    lo, hi = policy.range_m
    ok = (
        (labels.names == policy.class_name)
        & (labels.num_points >= policy.min_points)
        & (rng >= lo)
        & (rng <= hi)
    )
    cand = np.flatnonzero(ok)
    if cand.size == 0:
        return None
    if policy.policy == "nearest":
        return int(cand[np.argmin(rng[cand])])  # argmin keeps the first of equal ranges
    gen = numpy_generator(*seed_keys, "target")
    return int(cand[gen.integers(cand.size)])


@dataclass(frozen=True)
class TrackedFrame:
    """The target in one frame: its box (vehicle frame of that frame) and object id, or lost."""

    frame_idx: int
    box: np.ndarray | None
    obj_id: str | None

    @property
    def tracked(self) -> bool:
        return self.box is not None


@dataclass(frozen=True, kw_only=True)
class TrackingConfig:
    """The ``TRACKING`` section of a removal config."""

    dt: float = setting(0.1, gt=0, expected="a positive number", doc="s per frame")
    d_max: float = setting(
        2.0, gt=0, expected="a positive number", doc="prediction-to-box distance bound, m"
    )
    volume_ratio: float = setting(
        0.7, gt=0, le=1, expected="a ratio in (0, 1]", doc="accepted volume ratio `[q, 1/q]`"
    )


class Tracker:
    """Velocity-guided nearest-box association (docs/attacks.md, "Removal").

    Args:
        dt: time between consecutive frames, s.
        d_max: largest distance between the prediction and the matched centre, m.
        volume_ratio: lower bound ``q`` of the volume ratio; accepted ratios are in [q, 1/q].
    """

    def __init__(
        self,
        dt: float = TrackingConfig.dt,
        d_max: float = TrackingConfig.d_max,
        volume_ratio: float = TrackingConfig.volume_ratio,
    ):
        if not dt > 0 or not d_max > 0 or not 0 < volume_ratio <= 1:
            raise ValueError(
                f"need dt > 0, d_max > 0, 0 < volume_ratio <= 1; got {dt}, {d_max}, {volume_ratio}"
            )
        self.dt = float(dt)
        self.d_max = float(d_max)
        self.volume_ratio = float(volume_ratio)

    @classmethod
    def from_config(cls, cfg: Mapping | None) -> Tracker:
        """Build from a ``TRACKING`` section (:class:`TrackingConfig`; every key optional)."""
        return cls(**fields_of(read_section(TrackingConfig, cfg, "TRACKING")))

    def _match(
        self, labels: FrameLabels, class_name: str, center_w: np.ndarray, volume: float
    ) -> int | None:
        if len(labels.boxes) == 0:
            return None
        world = labels.world_boxes()
        dist = np.linalg.norm(world[:, :3] - center_w[None], axis=1)
        vol = np.prod(labels.boxes[:, 3:6], axis=1)
        ratio = vol / volume
        ok = (
            (labels.names == class_name)
            & (dist <= self.d_max)
            & (ratio >= self.volume_ratio)
            & (ratio <= 1.0 / self.volume_ratio)
        )
        cand = np.flatnonzero(ok)
        if cand.size == 0:
            return None
        return int(cand[np.argmin(dist[cand])])

    def track(
        self,
        frames: Mapping[int, FrameLabels],
        start: int,
        target: int,
        class_name: str,
        stop: int,
        first: int | None = None,
    ) -> dict[int, TrackedFrame]:
        """Track box ``target`` of frame ``start`` forward to ``stop`` (inclusive) and, if
        ``first`` (< start) is given, backward to it with the reversed motion model.

        Args:
            frames: frame index -> labels, for every frame in ``[first or start, stop]``.
        Returns:
            frame index -> :class:`TrackedFrame` for every frame in that interval.
        """
        out: dict[int, TrackedFrame] = {}
        lab0 = frames[start]
        box0 = lab0.boxes[target]
        out[start] = TrackedFrame(start, box0.copy(), str(lab0.obj_ids[target]))
        init = (
            lab0.world_boxes()[target, :3],
            lab0.speed_global[target],
            float(np.prod(box0[3:6])),
        )
        for direction, end in ((1, stop), (-1, first if first is not None else start)):
            center_w, vel, volume = init
            k = start
            while k != end:
                k += direction
                center_hat = center_w + direction * self.dt * np.array([vel[0], vel[1], 0.0])
                lab = frames[k]
                m = self._match(lab, class_name, center_hat, volume)
                if m is None:
                    out[k] = TrackedFrame(k, None, None)
                    center_w = center_hat  # coast on the prediction
                    continue
                out[k] = TrackedFrame(k, lab.boxes[m].copy(), str(lab.obj_ids[m]))
                center_w = lab.world_boxes()[m, :3]
                vel = lab.speed_global[m]
                volume = float(np.prod(lab.boxes[m, 3:6]))
        return out
