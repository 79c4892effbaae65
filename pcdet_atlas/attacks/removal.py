"""Point removal, A-HFR (docs/attacks.md): hide a tracked vehicle by deleting an angular sector.

Per run: the target is chosen at the run's first frame (:class:`TargetPolicy`) and tracked through
the run and its lifecycle frames in the world frame (:class:`Tracker`). Per spoofed frame:

1. lost target -> nothing removed;
2. firing gate ``a_k ~ Bernoulli(p_dist(r_k))``, ``r_k`` the range from the sensor origin to the
   target centre. The uniform behind it is keyed without the sector width, so every ``rem_*``
   variant fires on the same frames (common random numbers);
3. if fired, every point with ``|wrap(theta - theta*)| <= alpha/2`` and
   ``|phi - phi*| <= beta/2`` (angles relative to the sensor origin, aimed at the target centre)
   is removed with probability ``p_remove``; points outside the sector are kept.

The shipped ``p_dist`` table is an **assumed placeholder** (the paper's source table, Sato et al.
2025 Table XI, is not reproduced in the paper); replace it with measured values in the YAML.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pcdet_atlas.attacks.base import (
    AttackConfig,
    BaseAttack,
    FrameAttack,
    ScheduleState,
    SequenceData,
)
from pcdet_atlas.attacks.counters import COUNTERS
from pcdet_atlas.attacks.raycast import wedge_rows
from pcdet_atlas.attacks.tracking import (
    TargetPolicy,
    TrackedFrame,
    Tracker,
    TrackingConfig,
    choose_target,
)
from pcdet_atlas.config import ConfigError
from pcdet_atlas.config_values import config_files, fields_of, read_section, section, setting
from pcdet_atlas.ops.lidar_model import LidarModel, spherical_offsets
from pcdet_atlas.registry import ATTACKS
from pcdet_atlas.utils.common import limit_period
from pcdet_atlas.utils.seeding import numpy_generator

__all__ = ["PDistConfig", "PDistTable", "RemovalAttack", "RemovalConfig", "sector_mask"]

_EMPTY = np.zeros((0, 5), dtype=np.float32)


@dataclass(frozen=True, kw_only=True)
class PDistConfig:
    """The ``P_DIST`` section of a removal config (checked as a table by :class:`PDistTable`)."""

    edges_m: tuple[float, ...] = setting(
        doc="lower edges of the range bins, m; the last bin is open"
    )
    prob: tuple[float, ...] = setting(
        ge=0, le=1, expected="a list of probabilities in [0, 1]", doc="firing probability per bin"
    )
    note: str = setting("", doc="provenance of the values (free text)")


class PDistTable:
    """Firing probability by target range: bin ``i`` is ``[edges[i], edges[i+1])``, the last bin
    extends to infinity.

    Args:
        edges_m: ascending lower bin edges, metres, starting at 0.
        prob: one probability in [0, 1] per bin.
    """

    def __init__(self, edges_m, prob):
        self.edges = np.asarray(edges_m, dtype=np.float64).reshape(-1)
        self.prob = np.asarray(prob, dtype=np.float64).reshape(-1)
        if self.edges.size == 0 or self.edges[0] != 0 or (np.diff(self.edges) <= 0).any():
            raise ValueError(
                f"P_DIST.EDGES_M must ascend strictly from 0, got {self.edges.tolist()}"
            )
        if self.prob.shape != self.edges.shape:
            raise ValueError(
                f"P_DIST.PROB needs one value per bin ({self.edges.size}), got {self.prob.size}"
            )
        if ((self.prob < 0) | (self.prob > 1)).any():
            raise ValueError(f"P_DIST.PROB values must be in [0, 1], got {self.prob.tolist()}")

    @classmethod
    def from_config(cls, cfg: Mapping) -> PDistTable:
        """Build from a ``P_DIST`` section (:class:`PDistConfig`)."""
        settings = read_section(PDistConfig, cfg, "P_DIST")
        try:
            return cls(settings.edges_m, settings.prob)
        except ValueError as err:
            raise ConfigError(f"{err} (from {config_files(cfg)})") from err

    def __call__(self, range_m: float) -> float:
        if not range_m >= 0:
            raise ValueError(f"range must be >= 0, got {range_m}")
        return float(self.prob[np.searchsorted(self.edges, range_m, side="right") - 1])


def _azimuth_elevation(xyz: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth and elevation (float64, rad) relative to ``origin``: the CPU arithmetic of
    :meth:`LidarModel.spherical` (:func:`~pcdet_atlas.ops.lidar_model.spherical_offsets`)."""
    rel = xyz.astype(np.float64) - origin[None]
    azimuth, elevation, _ = spherical_offsets(rel[:, 0], rel[:, 1], rel[:, 2], with_range=False)
    return azimuth, elevation


def sector_mask(
    scene_xyz: np.ndarray,
    center_xyz: np.ndarray,
    lidar: LidarModel,
    alpha: float,
    beta: float,
) -> tuple[np.ndarray, int]:
    """Indices of the points of the A-HFR sector aimed at ``center_xyz``.

    ``|wrap(theta_i - theta*)| <= alpha / 2`` and ``|phi_i - phi*| <= beta / 2``, angles relative
    to the sensor origin (:meth:`LidarModel.spherical`, float64). Only the points of a cheap
    wedge pre-filter (a dot-product test in the scene's dtype, with a margin) get trigonometry.

    Args:
        scene_xyz: ``(N, 3+)`` points, vehicle frame, m.
        center_xyz: ``(3,)`` sector aim point, vehicle frame, m.
        alpha, beta: full azimuth and elevation widths, radians (``alpha < pi``).
    Returns:
        ``(S,)`` int64 ascending indices of the sector points, and the number of points the
        exact test examined.
    """
    if not 0 < alpha < math.pi or not 0 < beta < math.pi:
        raise ValueError(f"sector widths must be in (0, pi), got alpha={alpha}, beta={beta}")
    origin = lidar.origin_np
    theta_c, phi_c = (
        float(v[0]) for v in _azimuth_elevation(np.reshape(center_xyz, (1, 3)), origin)
    )
    xyz = np.asarray(scene_xyz)
    half = alpha / 2 + _PREFILTER_MARGIN_RAD
    if half >= math.pi / 2:  # wide sectors: every point gets exact angles
        cand = np.arange(xyz.shape[0])
    else:
        # pre-filter: the wedge [theta* - half, theta* + half] as two half-planes through the
        # sensor origin (the raycaster's sector test, with its 1 mm slack at the apex)
        wedge = [(theta_c - half, theta_c + half)]
        cand = wedge_rows(torch.from_numpy(xyz[:, :3]), wedge, lidar).numpy()
    if cand.size == 0:
        return cand.astype(np.int64), 0
    theta, phi = _azimuth_elevation(xyz[cand, :3], origin)
    dtheta = np.abs(limit_period(theta - theta_c))  # wrapped into [-pi, pi)
    inside = (dtheta <= alpha / 2) & (np.abs(phi - phi_c) <= beta / 2)
    return cand[inside].astype(np.int64), int(cand.size)


#: Angular margin of the sector pre-filter on each side, radians (>> float32 rounding).
_PREFILTER_MARGIN_RAD = 1e-3


@dataclass(frozen=True)
class RemovalRun:
    """A run's target and its track over the lifecycle frames (frame index -> tracked frame)."""

    run_id: int
    start: int
    end: int
    target_obj_id: str | None
    track: dict[int, TrackedFrame]


_SECTOR_WIDTH = {"gt": 0, "lt": 180, "expected": "an angle in (0, 180) degrees"}


@dataclass(frozen=True, kw_only=True)
class RemovalConfig(AttackConfig):
    """The keys of a removal YAML (beyond :class:`AttackConfig`'s)."""

    azimuth_width_deg: float = setting(doc="alpha, degrees", **_SECTOR_WIDTH)
    elevation_width_deg: float = setting(16.0, doc="beta, degrees", **_SECTOR_WIDTH)
    p_remove: float = setting(
        ge=0, le=1, expected="a probability in [0, 1]",
        doc="removal probability inside the sector",
    )  # fmt: skip
    p_dist: PDistConfig = setting(doc="firing probability by target range")
    target: TargetPolicy = section(TargetPolicy, doc="how the target is chosen")
    tracking: TrackingConfig = section(TrackingConfig, doc="frame-to-frame association")


@ATTACKS.register()
class RemovalAttack(BaseAttack):
    """A-HFR point removal aimed at a tracked vehicle.

    Args:
        variant, seed, window: see :class:`BaseAttack`.
        azimuth_width: ``alpha``, radians.
        elevation_width: ``beta``, radians (paper: 16°).
        p_remove: per-point removal probability inside the sector when the gate fires.
        p_dist: firing probability by target range (:class:`PDistTable`).
        target_policy: how the target is chosen (:class:`TargetPolicy`).
        tracker: frame-to-frame association (:class:`Tracker`).
        lidar: sensor model (origin for ranges and angles).
    """

    family = "removal"
    SUCCESS_IF_DETECTED = False  # the target is missed
    CONFIDENCE = "removal"
    RANK_GROUP = "removal"
    CONFIG = RemovalConfig

    def __init__(
        self,
        variant: str,
        azimuth_width: float,
        p_remove: float,
        p_dist: PDistTable,
        elevation_width: float = math.radians(RemovalConfig.elevation_width_deg),
        target_policy: TargetPolicy | None = None,
        tracker: Tracker | None = None,
        lidar: LidarModel | None = None,
        seed: int = 0,
        window: int = 32,
    ):
        super().__init__(variant, seed=seed, window=window)
        if not 0 < azimuth_width < math.pi or not 0 < elevation_width < math.pi:
            raise ValueError(
                f"sector widths must be in (0, 180) degrees, got {math.degrees(azimuth_width)}, "
                f"{math.degrees(elevation_width)}"
            )
        if not 0.0 <= p_remove <= 1.0:
            raise ValueError(f"p_remove must be in [0, 1], got {p_remove}")
        self.azimuth_width = float(azimuth_width)
        self.elevation_width = float(elevation_width)
        self.p_remove = float(p_remove)
        self.p_dist = p_dist
        self.target_policy = target_policy or TargetPolicy()
        self.tracker = tracker or Tracker()
        self.lidar = lidar or LidarModel.waymo_top()

    @classmethod
    def from_config(cls, cfg: Mapping, data_root: str | Path | None = None) -> RemovalAttack:
        settings = cls.read_config(cfg)
        try:
            return cls(
                azimuth_width=math.radians(settings.azimuth_width_deg),
                elevation_width=math.radians(settings.elevation_width_deg),
                p_remove=settings.p_remove,
                p_dist=PDistTable(settings.p_dist.edges_m, settings.p_dist.prob),
                target_policy=settings.target,
                tracker=Tracker(**fields_of(settings.tracking)),
                lidar=LidarModel.from_settings(settings.lidar),
                **cls.common_kwargs(settings),
            )
        except ValueError as err:
            if isinstance(err, ConfigError):
                raise
            raise ConfigError(f"{settings.variant} ({config_files(cfg)}): {err}") from err

    # ------------------------------------------------------------------ per run
    def prepare_run(self, seq: SequenceData, run_id: int) -> RemovalRun:
        """Choose the target at the run's first frame and track it over the run's lifecycle:
        from the frame before onset to ``W`` frames after the run (clipped to the sequence)."""
        start, end = self.run_bounds(seq, run_id)
        first = max(start - 1, 0)
        stop = min(start + 2 * self.window - 1, seq.num_frames - 1)
        labels0 = seq.labels(start)
        target = choose_target(
            labels0,
            self.target_policy,
            self.lidar.origin_np,
            seed_keys=(self.seed, self.family, seq.name, start),
        )
        if target is None:
            lost = {k: TrackedFrame(k, None, None) for k in range(first, stop + 1)}
            return RemovalRun(run_id, start, end, None, lost)
        frames = {k: seq.labels(k) for k in range(first, stop + 1)}
        track = self.tracker.track(
            frames, start, target, self.target_policy.class_name, stop, first=first
        )
        return RemovalRun(run_id, start, end, str(labels0.obj_ids[target]), track)

    def gate_uniform(self, seq_name: str, frame_idx: int) -> float:
        """The firing-gate uniform of a frame; keyed without the width (common random numbers)."""
        return float(numpy_generator(self.seed, self.family, seq_name, frame_idx, "gate").random())

    # ------------------------------------------------------------------ per frame
    def attack_frame(
        self,
        scene_xyz: np.ndarray,
        seq: SequenceData,
        frame_idx: int,
        run: RemovalRun,
        state: ScheduleState,
    ) -> FrameAttack:
        COUNTERS.add(frames_simulated=1)
        tracked = run.track[frame_idx]
        if not tracked.tracked:
            return FrameAttack(None, _EMPTY, self.meta(state, target_obj_id=run.target_obj_id))
        center = tracked.box[:3]
        range_m = float(np.linalg.norm(center - self.lidar.origin_np))
        fired = self.gate_uniform(seq.name, frame_idx) < self.p_dist(range_m)
        if not fired:
            return FrameAttack(
                None, _EMPTY, self.meta(state, target_obj_id=tracked.obj_id, tracked=True)
            )
        idx, examined = sector_mask(
            scene_xyz, center, self.lidar, self.azimuth_width, self.elevation_width
        )
        COUNTERS.add(removal_points_examined=examined)
        gen = numpy_generator(self.seed, self.family, seq.name, frame_idx, "points")
        removed = idx[gen.random(idx.size) < self.p_remove]  # ascending
        meta = self.meta(
            state,
            target_box=tracked.box,
            target_obj_id=tracked.obj_id,
            num_removed=removed.size,
            tracked=True,
            fired=True,
        )
        return FrameAttack.from_removed(scene_xyz.shape[0], removed, _EMPTY, meta)

    def shadow_meta(
        self, seq: SequenceData, frame_idx: int, run: RemovalRun, state: ScheduleState
    ) -> dict:
        tracked = run.track.get(frame_idx)
        if tracked is None or not tracked.tracked:
            return self.meta(state, target_obj_id=run.target_obj_id)  # lost: no shadow target
        return self.meta(
            state,
            target_box=tracked.box,
            target_is_shadow=True,
            target_obj_id=tracked.obj_id,
            tracked=True,
        )
