"""The per-frame attack interface shared by every attack family, and building attacks from YAML.

An attack family is one class registered in ``ATTACKS`` that subclasses :class:`BaseAttack` and
implements three things:

* ``prepare_run(seq, run_id)``: everything a run needs that does not depend on the frame's points
  (phantom sampling, target tracking). Pure function of ``(seq, run_id)`` and the config, so it is
  cached per ``(sequence, run)`` and never depends on which frame asked first.
* ``attack_frame(scene_xyz, seq, frame_idx, run_state, schedule) -> FrameAttack``: the physics of
  one spoofed frame, from the scene's xyz only (features are carried, never read).
* ``shadow_meta(seq, frame_idx, run_state, schedule) -> dict``: the metadata of a clean lifecycle
  frame (the frame before a run and the W frames after it; docs/evaluation.md, "Lifecycle"),
  without touching points.

:meth:`BaseAttack.simulate` is the one entry point: it looks the frame up in the schedule and
does **no** work for a clean frame. A new variant is a YAML file; a new family is a registered
class plus YAML (see ``docs/attacks.md``).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from pcdet_atlas.attacks import schedule as sched
from pcdet_atlas.attacks.metadata import make_meta
from pcdet_atlas.attacks.tracking import FrameLabels
from pcdet_atlas.config import ConfigError, cfg_from_yaml_file, key_source
from pcdet_atlas.config_values import check_finite, config_device, read_section, section, setting
from pcdet_atlas.datasets.multiframe import copy_rows_except
from pcdet_atlas.ops.lidar_model import LidarConfig
from pcdet_atlas.registry import ATTACKS
from pcdet_atlas.utils.paths import safe_component

__all__ = [
    "BaseAttack",
    "FrameAttack",
    "ScheduleState",
    "SequenceData",
    "build_attack",
    "attack_from_file",
    "AttackConfig",
    "ScheduleConfig",
]


@dataclass(frozen=True, kw_only=True)
class ScheduleConfig:
    """The ``SCHEDULE`` section of an attack config."""

    window: int = setting(
        sched.DEFAULT_WINDOW,
        ge=1,
        expected="a positive integer (frames)",
        doc="frames per clean / spoofed window",
    )


@dataclass(frozen=True, kw_only=True)
class AttackConfig:
    """The keys every attack YAML holds; a family's declaration subclasses it with its own."""

    name: str = setting(doc="registered attack class")
    variant: str = setting(
        check=bool, expected="a non-empty variant name", doc="name recorded in the metadata"
    )
    seed: int = setting(0, expected="an integer", doc="global seed of every draw")
    schedule: ScheduleConfig = section(ScheduleConfig)
    lidar: LidarConfig = section(LidarConfig, doc="the sensor model (``LidarModel``)")
    device: str = setting("cpu", doc="where the injection raycast runs")


@dataclass(frozen=True)
class ScheduleState:
    """Where a frame sits in the schedule (docs/attacks.md; lifecycle: docs/evaluation.md)."""

    spoofed: bool
    run_id: int  # spoofing run, or the run whose lifecycle holds this clean frame; -1 if none
    run_position: int  # 0-based position in the run, -1 if clean
    lifecycle_k: int  # -1 if in no lifecycle


@dataclass
class SequenceData:
    """What attacks need of a sequence besides points: poses and labels, by frame index.

    Labels and inverse poses are computed lazily, frame by frame, so building this is cheap.
    ``root``: the dataset root the sequence was read from (``None`` for one built by hand); it
    keeps apart same-named sequences of two roots in an attack's run cache.
    """

    name: str
    infos: Sequence[Mapping]
    root: str | None = None
    _labels: dict[int, FrameLabels] = field(default_factory=dict, repr=False)
    _inverse_poses: dict[int, np.ndarray] = field(default_factory=dict, repr=False)

    @property
    def num_frames(self) -> int:
        return len(self.infos)

    def pose(self, frame_idx: int) -> np.ndarray:
        """``(4, 4)`` float64 vehicle -> world pose of a frame."""
        return np.asarray(self.infos[frame_idx]["pose"], dtype=np.float64).reshape(4, 4)

    def world_to_vehicle(self, frame_idx: int) -> np.ndarray:
        """``(4, 4)`` float64 inverse of :meth:`pose` (``np.linalg.inv``, cached read-only), so
        ``world_to_vehicle(k) @ pose(a)`` is :func:`~pcdet_atlas.datasets.multiframe.
        relative_pose` ``(pose(a), pose(k))`` bit for bit."""
        inverse = self._inverse_poses.get(frame_idx)
        if inverse is None:
            inverse = np.linalg.inv(self.pose(frame_idx))
            inverse.flags.writeable = False
            self._inverse_poses[frame_idx] = inverse
        return inverse

    def labels(self, frame_idx: int) -> FrameLabels:
        if frame_idx not in self._labels:
            self._labels[frame_idx] = FrameLabels.from_info(self.infos[frame_idx])
        return self._labels[frame_idx]


class FrameAttack:
    """The result of attacking one frame.

    Attributes:
        keep: ``(N,)`` bool mask of scene points kept, or ``None`` (all kept); built on first
            access when the attack gave the removed rows instead (:meth:`from_removed`).
        added: ``(K, 5)`` float32 points added: ``x, y, z`` (vehicle frame, m) and **raw**
            intensity and elongation (the dataset applies its feature transform, e.g. tanh).
        meta: the metadata record (:mod:`pcdet_atlas.attacks.metadata`).
        removed: ``(R,)`` int64 ascending indices of the rows ``keep`` drops, when the attack
            has them at hand (saves two passes over the mask); derived from ``keep`` otherwise.
    """

    def __init__(
        self,
        keep: np.ndarray | None,
        added: np.ndarray,
        meta: dict,
        removed: np.ndarray | None = None,
    ):
        self._keep, self.added, self.meta, self.removed = keep, added, meta, removed
        self._num_points: int | None = None

    @classmethod
    def from_removed(
        cls, num_points: int, removed: np.ndarray, added: np.ndarray, meta: dict
    ) -> FrameAttack:
        """The attack that drops the ascending row indices ``removed`` of a ``num_points``-row
        scene and adds ``added`` (``keep`` is derived from them only if asked for)."""
        attack = cls(None, added, meta, removed=removed)
        attack._num_points = int(num_points)
        return attack

    @property
    def keep(self) -> np.ndarray | None:
        if self._keep is None and self._num_points is not None:
            self._keep = np.ones(self._num_points, dtype=bool)
            self._keep[self.removed] = False
        return self._keep

    def removed_rows(self) -> np.ndarray:
        """``(R,)`` int64 ascending indices of the scene rows the attack drops."""
        if self.removed is not None:
            return self.removed
        return _EMPTY_INDEX if self._keep is None else (~self._keep).nonzero()[0]

    def __repr__(self) -> str:
        removed = self.removed_rows().size
        return f"FrameAttack(removed={removed}, added={len(self.added)}, meta={self.meta!r})"

    def apply(
        self,
        points: np.ndarray,
        feature_fn: Callable[[np.ndarray], np.ndarray] | None = None,
        fill_value: float = -1.0,
    ) -> np.ndarray:
        """``points[keep]`` followed by the added points as rows of the same width (``points``
        itself when the attack removes and adds nothing).

        Args:
            points: ``(N, C)`` scene points, ``C >= 5``.
            feature_fn: maps the ``(K, 5)`` raw added points into the dataset's feature space.
            fill_value: value of the columns beyond the fifth for added rows (default -1: the
                NLZ flag of a frame file's sixth column for a point outside any no-label zone,
                the rows the loader keeps).
        """
        num_added = self.added.shape[0]
        removed = self.removed_rows()
        if removed.size == 0 and num_added == 0:
            return points
        added = self.added if feature_fn is None else feature_fn(self.added.copy())
        num_kept = points.shape[0] - removed.size
        out = np.empty((num_kept + num_added, points.shape[1]), dtype=points.dtype)  # one copy
        copy_rows_except(points, removed, out[:num_kept])
        if num_added:
            out[num_kept:] = fill_value
            out[num_kept:, :5] = added[:, :5]
        return out


_EMPTY_INDEX = np.zeros(0, dtype=np.int64)


class BaseAttack(ABC):
    """Common state and the schedule-driven entry point of every attack family.

    Args:
        variant: the variant name recorded in metadata (e.g. ``'inj_global_hard'``).
        seed: global seed of every random draw of this attack.
        window: schedule window ``W`` in frames.
        run_cache_size: how many prepared runs to keep (LRU), per attack instance.
    """

    family: ClassVar[str] = "base"
    #: How the evaluation scores this family (written into every frame's metadata): a target
    #: is a success when detected (True) or when missed (False); None for a family without
    #: targets.
    SUCCESS_IF_DETECTED: ClassVar[bool | None] = None
    #: The confidence kind of its targets: 'injection' (scores of the detected targets),
    #: 'removal' (scores of surviving targets against the clean run), a kind registered with
    #: ``pcdet_atlas.evaluation.analyses.register_confidence_kind``, or None.
    CONFIDENCE: ClassVar[str | None] = None
    #: Robustness ranks average a model's per-variant ranks within this group (None: not ranked).
    RANK_GROUP: ClassVar[str | None] = None
    #: The declaration of its YAML keys (:class:`AttackConfig` or a subclass with the family's).
    CONFIG: ClassVar[type[AttackConfig]] = AttackConfig

    def __init__(
        self,
        variant: str,
        seed: int = AttackConfig.seed,
        window: int = ScheduleConfig.window,
        run_cache_size: int = 64,
    ):
        self.variant = str(variant)
        self.seed = int(seed)
        self.window = int(window)
        if self.window < 1:
            raise ValueError(f"schedule window must be >= 1, got {window}")
        self._run_cache: OrderedDict[tuple, Any] = OrderedDict()
        self._run_cache_size = int(run_cache_size)
        # (frame, num_frames) -> state: a few hundred entries per distinct sequence length
        self._states: dict[tuple[int, int], ScheduleState] = {}

    # ------------------------------------------------------------------ config
    @classmethod
    def from_config(cls, cfg: Mapping, data_root: str | Path | None = None) -> BaseAttack:
        """Build from an attack YAML (already loaded). ``data_root`` resolves relative paths."""
        raise NotImplementedError

    @classmethod
    def read_config(cls, cfg: Mapping) -> AttackConfig:
        """The attack YAML read into :attr:`CONFIG` (every key and value checked, errors naming
        the key, the value and the file), with ``DEVICE`` checked to exist on this machine."""
        check_finite(cfg)  # names a NaN inside a list by its index (OFFSET_X[1])
        settings = read_section(cls.CONFIG, cfg, where=f"attack config {cls.__name__}")
        config_device(cfg)
        # the variant names its results' folder: one safe path component
        safe_component(settings.variant, "VARIANT", key_source(cfg, "VARIANT"))
        return settings

    @staticmethod
    def common_kwargs(settings: AttackConfig) -> dict:
        """The :class:`BaseAttack` keyword arguments of a read config."""
        return {
            "variant": settings.variant,
            "seed": settings.seed,
            "window": settings.schedule.window,
        }

    @classmethod
    def _common_kwargs(cls, cfg: Mapping) -> dict:
        """:meth:`common_kwargs` of :meth:`read_config` (a family without keys of its own)."""
        return cls.common_kwargs(cls.read_config(cfg))

    # ------------------------------------------------------------------ schedule
    def schedule_state(self, frame_idx: int, num_frames: int) -> ScheduleState:
        """The schedule state of a frame of a ``num_frames`` sequence (memoised for plain int
        arguments: a loaded frame asks for it several times)."""
        key = (frame_idx, num_frames) if type(frame_idx) is type(num_frames) is int else None
        state = None if key is None else self._states.get(key)
        if state is not None:
            return state
        run_id, pos = sched.run_of_frame(frame_idx, num_frames, self.window)
        if run_id >= 0:
            state = ScheduleState(True, run_id, pos, pos + 1)
        else:
            run_id, k = sched.lifecycle_of_frame(frame_idx, num_frames, self.window)
            state = ScheduleState(False, run_id, -1, k)
        if key is not None:
            self._states[key] = state
        return state

    def run_state(self, seq: SequenceData, run_id: int) -> Any:
        """The prepared state of a run (cached; a pure function of ``(seq, run_id)``, keyed by
        the sequence's root, name and frame count, so one attack serves several datasets)."""
        key = (seq.root, seq.name, seq.num_frames, run_id)
        if key in self._run_cache:
            self._run_cache.move_to_end(key)
            return self._run_cache[key]
        state = self.prepare_run(seq, run_id)
        self._run_cache[key] = state
        while len(self._run_cache) > self._run_cache_size:
            self._run_cache.popitem(last=False)
        return state

    def run_bounds(self, seq: SequenceData, run_id: int) -> tuple[int, int]:
        """``(start, end_inclusive)`` of a run of ``seq``."""
        return sched.run_bounds(run_id, seq.num_frames, self.window)

    def needs_simulation(self, frame_idx: int, num_frames: int) -> bool:
        """Whether a frame's points are changed by this attack (a clean frame never is)."""
        return self.schedule_state(frame_idx, num_frames).spoofed

    def max_added_points(self, seq: SequenceData, frame_idx: int) -> int:
        """An upper bound of the rows :meth:`simulate` adds to frame ``frame_idx``, so that a
        loader can read the frame with room for them (0: this family only removes points).
        A bound that is too low costs a copy, never a wrong frame."""
        return 0

    def meta(self, state: ScheduleState, **kwargs) -> dict:
        """A metadata record of this attack for a frame in ``state``."""
        return make_meta(
            self.variant,
            self.family,
            spoofed=state.spoofed,
            run_id=state.run_id,
            run_position=state.run_position,
            lifecycle_k=state.lifecycle_k,
            success_if_detected=self.SUCCESS_IF_DETECTED,
            confidence=self.CONFIDENCE,
            rank_group=self.RANK_GROUP,
            **kwargs,
        )

    def simulate(
        self, scene_xyz: np.ndarray | None, seq: SequenceData, frame_idx: int
    ) -> FrameAttack:
        """Attack frame ``frame_idx`` of ``seq`` by its own schedule state.

        Args:
            scene_xyz: ``(N, 3+)`` scene points of the frame (vehicle frame). Only read for a
                spoofed frame; may be ``None`` for a clean one.
        Returns:
            The :class:`FrameAttack`; for a clean frame ``keep is None`` and nothing is added.
        """
        state = self.schedule_state(frame_idx, seq.num_frames)
        if not state.spoofed:
            return FrameAttack(None, _EMPTY_ADDED, self.frame_meta(seq, frame_idx, state))
        if scene_xyz is None:
            raise ValueError(f"{seq.name} frame {frame_idx} is spoofed: scene points are needed")
        run = self.run_state(seq, state.run_id)
        return self.attack_frame(np.asarray(scene_xyz)[:, :3], seq, frame_idx, run, state)

    def frame_meta(
        self, seq: SequenceData, frame_idx: int, state: ScheduleState | None = None
    ) -> dict:
        """Metadata of a clean frame (with its shadow target on lifecycle frames)."""
        state = state or self.schedule_state(frame_idx, seq.num_frames)
        if state.spoofed:
            raise ValueError(f"{seq.name} frame {frame_idx} is spoofed; use simulate()")
        if state.run_id < 0:
            return self.meta(state)
        return self.shadow_meta(seq, frame_idx, self.run_state(seq, state.run_id), state)

    # ------------------------------------------------------------------ family hooks
    @abstractmethod
    def prepare_run(self, seq: SequenceData, run_id: int) -> Any:
        """Per-run state (no point work)."""

    @abstractmethod
    def attack_frame(
        self,
        scene_xyz: np.ndarray,
        seq: SequenceData,
        frame_idx: int,
        run: Any,
        state: ScheduleState,
    ) -> FrameAttack:
        """Attack one spoofed frame. ``scene_xyz`` is ``(N, 3)`` in the frame's vehicle frame."""

    @abstractmethod
    def shadow_meta(
        self, seq: SequenceData, frame_idx: int, run: Any, state: ScheduleState
    ) -> dict:
        """Metadata of a clean lifecycle frame of ``run`` (shadow target, not attacked)."""


_EMPTY_ADDED = np.zeros((0, 5), dtype=np.float32)
_EMPTY_ADDED.setflags(write=False)


def build_attack(cfg: Mapping, data_root: str | Path | None = None) -> BaseAttack:
    """Build the registered attack named by ``cfg.NAME`` from a loaded attack config."""
    if "NAME" not in cfg:
        origin = {key_source(cfg, k) for k in cfg} - {"<unknown>"}
        raise ConfigError(f"attack config {sorted(origin) or ''}: missing NAME (the attack class)")
    cls = ATTACKS.get(str(cfg["NAME"]))
    return cls.from_config(cfg, data_root=data_root)


def attack_from_file(path: str | Path, data_root: str | Path | None = None) -> BaseAttack:
    """Load an attack YAML (with its ``_BASE_CONFIG_`` chain) and build it."""
    return build_attack(cfg_from_yaml_file(path), data_root=data_root)
