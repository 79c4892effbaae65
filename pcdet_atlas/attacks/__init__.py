"""The ATLAS attack engine: LiDAR model, raycaster, schedule, injection, removal, dataset.

Importing this package registers the attack families in ``ATTACKS`` (``CleanAttack``,
``InjectionAttack``, ``RemovalAttack``) and ``AtlasWaymoDataset`` in ``DATASETS``.
"""

from pcdet_atlas.attacks.atlas_dataset import AtlasWaymoDataset
from pcdet_atlas.attacks.base import (
    BaseAttack,
    FrameAttack,
    ScheduleState,
    SequenceData,
    attack_from_file,
    build_attack,
)
from pcdet_atlas.attacks.clean import CleanAttack
from pcdet_atlas.attacks.counters import COUNTERS, AttackCounters
from pcdet_atlas.attacks.injection import InjectionAttack
from pcdet_atlas.attacks.metadata import META_KEYS, make_meta, validate_meta
from pcdet_atlas.attacks.raycast import raycast_merge
from pcdet_atlas.attacks.removal import RemovalAttack
from pcdet_atlas.attacks.schedule import schedule_runs, spoof_schedule
from pcdet_atlas.attacks.trace_library import TraceLibrary, build_trace_library
from pcdet_atlas.ops.lidar_model import LidarModel

__all__ = [
    "AtlasWaymoDataset",
    "AttackCounters",
    "BaseAttack",
    "COUNTERS",
    "CleanAttack",
    "FrameAttack",
    "InjectionAttack",
    "LidarModel",
    "META_KEYS",
    "RemovalAttack",
    "ScheduleState",
    "SequenceData",
    "TraceLibrary",
    "attack_from_file",
    "build_attack",
    "build_trace_library",
    "make_meta",
    "raycast_merge",
    "schedule_runs",
    "spoof_schedule",
    "validate_meta",
]
