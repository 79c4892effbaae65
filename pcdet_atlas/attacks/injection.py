"""Point injection (docs/attacks.md): a recorded vehicle trace replayed as a phantom through the
sensor-level raycaster.

Per run (all draws keyed by ``(seed, 'injection', position_mode, sequence, run_start, purpose)``,
never by the budget, so easy/medium/hard of one position mode share trace, placement and point
order — *common random numbers*; the easy phantom's points are a prefix of the hard one's):

* a trace of the library, and one permutation of its points;
* a budget ``n ~ U{lo, hi}`` from one uniform shared by all budgets, capped at the trace size;
  the phantom is the first ``n`` points of the permutation (sampling without replacement);
* an offset ``x ~ U(15, 20)``, ``y ~ U(-3, 3)`` m and a yaw ``psi ~ U(-0.2, 0.2)`` rad;
* the raycaster's dual-return uniforms, one row per frame of the run (``p_dual > 0``).

Position modes: ``relative`` keeps the phantom's ego-relative pose in every frame of the run;
``global`` places it in the run's anchor frame (its last frame) and holds it fixed in the world,
``p_k = T_k^-1 T_anchor p``.

Per spoofed frame: pose the phantom, set its bottom on the local ground
(:class:`~pcdet_atlas.attacks.ground.GroundEstimator`), correct intensity and elongation for the
new range (:class:`~pcdet_atlas.attacks.intensity.RangeIntensityModel`), then
:func:`~pcdet_atlas.attacks.raycast.raycast_merge` with the frame's scene decides which phantom
points a real sensor would report and which scene points they occlude.
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
    ScheduleConfig,
    ScheduleState,
    SequenceData,
)
from pcdet_atlas.attacks.counters import COUNTERS
from pcdet_atlas.attacks.ground import GROUND_SLACK_M, GroundConfig, GroundEstimator
from pcdet_atlas.attacks.intensity import IntensityConfig, RangeIntensityModel
from pcdet_atlas.attacks.raycast import disc_wedges, raycast_merge, wedge_rows
from pcdet_atlas.attacks.trace_library import TraceFilter, TraceLibrary, library_file
from pcdet_atlas.config import REPO_ROOT, ConfigError, key_source
from pcdet_atlas.config_values import config_files, fields_of, section, setting
from pcdet_atlas.ops.lidar_model import LidarModel
from pcdet_atlas.registry import ATTACKS
from pcdet_atlas.utils.common import limit_period
from pcdet_atlas.utils.seeding import numpy_generator

__all__ = ["InjectionAttack", "InjectionConfig", "PhantomRun", "sample_phantom"]

POSITION_MODES = ("relative", "global")


@dataclass(frozen=True)
class PhantomRun:
    """A run's phantom in its reference ego frame (relative: every frame; global: the anchor).

    Attributes:
        xyz: ``(n, 3)`` float64 phantom points, bottom of the box at z = 0, m.
        intensity, elongation, src_range: ``(n,)`` float32 raw values and recording range (m).
        box: ``(7,)`` float64 phantom box in the same frame.
        anchor_pose: ``(4, 4)`` vehicle -> world pose of the anchor frame (global mode), or None.
        dual_uniforms: ``(end - start + 1, n)`` float64 uniforms of the raycaster's dual returns,
            one row per frame of the run (a frame never draws more than ``n``: one per primary
            ray, and each ray has a phantom point), or None when ``p_dual = 0``.
        reach: the largest distance of a phantom point from the box centre (m, 3-D, so any
            rigid pose keeps every point within it of the posed centre, plus 1 mm for the
            float32 rounding of the points).
        trace_index: library index. budget_requested: the drawn ``n`` before capping.
    """

    run_id: int
    start: int
    end: int
    trace_index: int
    budget_requested: int
    xyz: np.ndarray
    intensity: np.ndarray
    elongation: np.ndarray
    src_range: np.ndarray
    box: np.ndarray
    anchor_pose: np.ndarray | None
    dual_uniforms: np.ndarray | None = None
    reach: float = math.inf

    @property
    def budget(self) -> int:
        return int(self.xyz.shape[0])


def sample_phantom(
    library: TraceLibrary,
    keys: tuple,
    budget_range: tuple[int, int],
    offset_x: tuple[float, float] = (15.0, 20.0),
    offset_y: tuple[float, float] = (-3.0, 3.0),
    yaw_range: tuple[float, float] = (-0.2, 0.2),
) -> tuple[int, int, np.ndarray, np.ndarray]:
    """Draw one run's phantom (common random numbers across budgets).

    Args:
        keys: seed keys of the run, e.g. ``(seed, 'injection', mode, sequence, run_start)``.
    Returns:
        trace index, requested budget, selected point indices into the trace ``(n,)`` (a prefix
        of one permutation), and the placement ``[x, y, yaw]`` (m, m, rad).
    """
    trace_index = int(numpy_generator(*keys, "trace").integers(len(library)))
    size = int(library.trace_sizes()[trace_index])
    order = numpy_generator(*keys, "subsample").permutation(size)
    lo, hi = int(budget_range[0]), int(budget_range[1])
    u = float(numpy_generator(*keys, "budget").random())
    requested = min(lo + int(u * (hi - lo + 1)), hi)
    place = numpy_generator(*keys, "placement").random(3)
    x = offset_x[0] + place[0] * (offset_x[1] - offset_x[0])
    y = offset_y[0] + place[1] * (offset_y[1] - offset_y[0])
    yaw = yaw_range[0] + place[2] * (yaw_range[1] - yaw_range[0])
    return trace_index, requested, order[: min(requested, size)], np.array([x, y, yaw])


def _ordered(pair: tuple) -> bool:
    return pair[0] <= pair[1]


def _range(default: tuple[float, float], doc: str):
    return setting(default, check=_ordered, expected="[lo, hi], two numbers with lo <= hi", doc=doc)


@dataclass(frozen=True, kw_only=True)
class InjectionConfig(AttackConfig):
    """The keys of an injection YAML (beyond :class:`AttackConfig`'s)."""

    trace_library: TraceFilter = setting(doc="the trace library and its build filters")
    position_mode: str = setting(
        choices=POSITION_MODES,
        expected=f"one of {POSITION_MODES}",
        doc="`relative` or `global`",
    )
    budget: tuple[int, int] = setting(
        ge=1,
        check=_ordered,
        expected="[lo, hi], two integers with 1 <= lo <= hi",
        doc="`[lo, hi]` phantom points",
    )
    offset_x: tuple[float, float] = _range((15.0, 20.0), "placement range ahead, m")
    offset_y: tuple[float, float] = _range((-3.0, 3.0), "lateral placement range, m")
    yaw_range: tuple[float, float] = setting(
        (-0.2, 0.2),
        key="YAW",
        check=_ordered,
        expected="[lo, hi], two numbers with lo <= hi",
        doc="heading range, rad",
    )
    ground: GroundConfig = section(GroundConfig, doc="local ground estimate")
    intensity: IntensityConfig = section(IntensityConfig, doc="range correction of features")
    p_dual: float = setting(
        0.01, ge=0, le=1, expected="a probability in [0, 1]", doc="dual-return probability"
    )


@ATTACKS.register()
class InjectionAttack(BaseAttack):
    """Phantom-vehicle injection through the raycaster.

    Args:
        variant, seed, window: see :class:`BaseAttack`.
        library: a :class:`TraceLibrary`, or a path loaded on first use.
        position_mode: ``'relative'`` or ``'global'``.
        budget: ``(lo, hi)`` point budget (inclusive).
        offset_x, offset_y: placement ranges in the reference ego frame, m.
        yaw_range: phantom heading range, rad.
        ground: local ground estimator. intensity: range correction of features.
        p_dual: dual-return probability of the raycaster.
        lidar: sensor model. device: where the raycast runs.
        trace_filter: the filters and split the library must have been built with (checked on
            load, with the sensor origin of ``lidar``).
    """

    family = "injection"
    SUCCESS_IF_DETECTED = True  # the phantom is detected
    CONFIDENCE = "injection"
    RANK_GROUP = "injection"
    CONFIG = InjectionConfig

    def __init__(
        self,
        variant: str,
        library: TraceLibrary | str | Path,
        position_mode: str,
        budget: tuple[int, int],
        offset_x: tuple[float, float] = InjectionConfig.offset_x,
        offset_y: tuple[float, float] = InjectionConfig.offset_y,
        yaw_range: tuple[float, float] = InjectionConfig.yaw_range,
        ground: GroundEstimator | None = None,
        intensity: RangeIntensityModel | None = None,
        p_dual: float = InjectionConfig.p_dual,
        lidar: LidarModel | None = None,
        device: str = InjectionConfig.device,
        trace_filter: TraceFilter | None = None,
        seed: int = InjectionConfig.seed,
        window: int = ScheduleConfig.window,
    ):
        super().__init__(variant, seed=seed, window=window)
        if position_mode not in POSITION_MODES:
            raise ValueError(
                f"position_mode must be one of {POSITION_MODES}, got {position_mode!r}"
            )
        if not 1 <= int(budget[0]) <= int(budget[1]):
            raise ValueError(f"budget must be [lo, hi] with 1 <= lo <= hi, got {budget}")
        if not 0.0 <= p_dual <= 1.0:
            raise ValueError(f"p_dual must be in [0, 1], got {p_dual}")
        self._library = library if isinstance(library, TraceLibrary) else None
        self.library_path = None if self._library is not None else Path(library)
        self.position_mode = position_mode
        self.budget = (int(budget[0]), int(budget[1]))
        self.offset_x = tuple(float(v) for v in offset_x)
        self.offset_y = tuple(float(v) for v in offset_y)
        self.yaw_range = tuple(float(v) for v in yaw_range)
        self.ground = ground or GroundEstimator()
        self.intensity = intensity or RangeIntensityModel()
        self.p_dual = float(p_dual)
        self.lidar = lidar or LidarModel.waymo_top()
        self.device = torch.device(device)
        self.trace_filter = trace_filter

    @classmethod
    def from_config(cls, cfg: Mapping, data_root: str | Path | None = None) -> InjectionAttack:
        """Relative ``TRACE_LIBRARY.PATH`` resolves under ``data_root`` (the dataset root) when
        given, else under the repository root, and must stay under it
        (:func:`~pcdet_atlas.attacks.trace_library.library_file`)."""
        settings = cls.read_config(cfg)
        trace_filter = TraceFilter.from_config(cfg["TRACE_LIBRARY"])  # with its cross-key check
        path = library_file(
            trace_filter.path,
            data_root if data_root is not None else REPO_ROOT,
            key_source(cfg["TRACE_LIBRARY"], "PATH"),
        )
        try:
            return cls(
                library=path,
                position_mode=settings.position_mode,
                budget=settings.budget,
                offset_x=settings.offset_x,
                offset_y=settings.offset_y,
                yaw_range=settings.yaw_range,
                ground=GroundEstimator(**fields_of(settings.ground)),
                intensity=RangeIntensityModel(**fields_of(settings.intensity)),
                p_dual=settings.p_dual,
                lidar=LidarModel.from_settings(settings.lidar),
                device=settings.device,
                trace_filter=trace_filter,
                **cls.common_kwargs(settings),
            )
        except ValueError as err:
            if isinstance(err, ConfigError):
                raise
            raise ConfigError(f"{settings.variant} ({config_files(cfg)}): {err}") from err

    @property
    def library(self) -> TraceLibrary:
        """The trace library (loaded on first use; with ``trace_filter`` its build filters, split
        and sensor origin must match the config)."""
        if self._library is None:
            lib = TraceLibrary.load(self.library_path)
            differs = {} if self.trace_filter is None else (
                lib.build_mismatch(self.trace_filter, self.lidar.origin_xyz)
            )  # fmt: skip
            if differs:
                stored = {key: pair[0] for key, pair in differs.items()}
                expected = {key: pair[1] for key, pair in differs.items()}
                raise ConfigError(
                    f"{self.library_path}: trace library built with {stored}, but "
                    f"{self.variant} asks for {expected} (its TRACE_LIBRARY and LIDAR.ORIGIN); "
                    "rebuild the library with tools/data/build_trace_library.py"
                )
            self._library = lib
        return self._library

    def rng_keys(self, seq_name: str, start: int) -> tuple:
        """Seed keys of a run: no budget in them (common random numbers across budgets)."""
        return (self.seed, self.family, self.position_mode, seq_name, int(start))

    # ------------------------------------------------------------------ per run
    def prepare_run(self, seq: SequenceData, run_id: int) -> PhantomRun:
        start, end = self.run_bounds(seq, run_id)
        lib = self.library
        trace_index, requested, sel, (x, y, yaw) = sample_phantom(
            lib, self.rng_keys(seq.name, start), self.budget, self.offset_x, self.offset_y,
            self.yaw_range,
        )  # fmt: skip
        trace = lib.trace(trace_index)
        l, w, h = (float(v) for v in trace.box_size)
        can = trace.xyz[sel].astype(np.float64)  # (n, 3), box centre at the origin
        c, s = np.cos(yaw), np.sin(yaw)
        xyz = np.stack(
            [
                c * can[:, 0] - s * can[:, 1] + x,
                s * can[:, 0] + c * can[:, 1] + y,
                can[:, 2] + h / 2,
            ],
            axis=1,
        )  # bottom of the box on z = 0 of the reference frame
        reach = float(np.linalg.norm(xyz - [x, y, h / 2], axis=1).max(initial=0.0))
        return PhantomRun(
            run_id=run_id,
            start=start,
            end=end,
            trace_index=trace_index,
            budget_requested=requested,
            xyz=xyz,
            intensity=trace.intensity[sel],
            elongation=trace.elongation[sel],
            src_range=trace.src_range[sel],
            box=np.array([x, y, h / 2, l, w, h, yaw]),
            reach=reach + 1e-3,
            anchor_pose=seq.pose(end) if self.position_mode == "global" else None,
            dual_uniforms=(
                numpy_generator(*self.rng_keys(seq.name, start), "dual").random(
                    (end - start + 1, len(sel))
                )
                if self.p_dual > 0
                else None
            ),
        )

    def phantom_pose(
        self, seq: SequenceData, frame_idx: int, run: PhantomRun
    ) -> tuple[np.ndarray, np.ndarray]:
        """Phantom points ``(n, 3)`` and box ``(7,)`` in frame ``frame_idx``'s vehicle frame,
        before ground anchoring (float64)."""
        if run.anchor_pose is None:
            return run.xyz, run.box
        rel = seq.world_to_vehicle(frame_idx) @ run.anchor_pose  # anchor ego -> frame ego
        # r0 x + r1 y + r2 z + t left to right in float64, for the points (a few whole-array
        # ops on (3, n)) and the box centre alike: transform_points_into's arithmetic, no BLAS
        # call (the same bits on every CPU, no thread pool woken for a few hundred points)
        x, y, z = run.xyz.T
        xyz = (rel[:3, 0:1] * x + rel[:3, 1:2] * y + rel[:3, 2:3] * z + rel[:3, 3:4]).T
        box = run.box.copy()  # the size columns are unchanged
        cx, cy, cz = run.box[0:3].tolist()
        for r, row in enumerate(rel[:3].tolist()):
            box[r] = row[0] * cx + row[1] * cy + row[2] * cz + row[3]
        box[6] = limit_period(run.box[6] + math.atan2(rel[1, 0], rel[0, 0]))
        return xyz, box

    def max_added_points(self, seq: SequenceData, frame_idx: int) -> int:
        """The run's budget on a spoofed frame (at most every phantom point is visible)."""
        state = self.schedule_state(frame_idx, seq.num_frames)
        return self.run_state(seq, state.run_id).budget if state.spoofed else 0

    def phantom_id(self, run: PhantomRun) -> str:
        return f"phantom_run{run.run_id}"

    # ------------------------------------------------------------------ per frame
    def attack_frame(
        self,
        scene_xyz: np.ndarray,
        seq: SequenceData,
        frame_idx: int,
        run: PhantomRun,
        state: ScheduleState,
    ) -> FrameAttack:
        COUNTERS.add(frames_simulated=1)
        xyz, box = self.phantom_pose(seq, frame_idx, run)
        scene_t = torch.from_numpy(scene_xyz[:, :3]).to(self.device)  # strided view on CPU
        # the only full-scene pass: one azimuth sector holding both the ground disc and the
        # phantom's rays (their azimuths do not depend on the ground height), shared by the
        # ground estimate and the raycaster
        near = self._phantom_sector(scene_t, run, box)
        ground = self.ground(scene_xyz, box[:2], rows=None if near is None else near.cpu().numpy())
        if ground.source == "fallback":
            COUNTERS.add(ground_fallbacks=1)
        dz = ground.z + box[5] / 2 - box[2]
        box = box.copy()
        box[2] += dz
        spoof = (xyz + np.array([0.0, 0.0, dz])).astype(np.float32)  # (n, 3)
        gen = None if run.dual_uniforms is None else run.dual_uniforms[frame_idx - run.start]
        keep_scene, keep_spoof = raycast_merge(
            scene_t, torch.from_numpy(spoof).to(self.device), self.lidar, self.p_dual, gen,
            candidates=near,
        )  # fmt: skip
        removed = torch.nonzero(~keep_scene).squeeze(1).cpu().numpy()  # ascending
        keep_spoof = keep_spoof.cpu().numpy()
        # range-corrected features of the visible phantom points only
        visible = keep_spoof.nonzero()[0]
        rel = spoof[visible].astype(np.float64) - self.lidar.origin_np
        new_range = np.sqrt(np.add.reduce(rel * rel, axis=1))  # np.linalg.norm's arithmetic
        inten, elong = self.intensity(
            run.intensity[visible], run.elongation[visible], run.src_range[visible], new_range
        )
        added = np.concatenate([spoof[visible], inten[:, None], elong[:, None]], axis=1)
        meta = self.meta(
            state,
            # a target only when the phantom is in the scan (the paper records g "when a
            # spoofed object is present"); a fully occluded one is counted as untargeted
            target_box=box if visible.size else None,
            target_obj_id=self.phantom_id(run),
            num_spoof_points=run.budget,
            num_visible=int(visible.size),
            num_removed=int(removed.size),
            tracked=True,
            fired=True,
        )
        return FrameAttack.from_removed(scene_xyz.shape[0], removed, added.astype(np.float32), meta)

    def _phantom_sector(
        self, scene: torch.Tensor, run: PhantomRun, box: np.ndarray
    ) -> torch.Tensor | None:
        """Ascending scene rows of one azimuth sector around the phantom: its points (within
        ``run.reach`` of the box centre, whatever the pose and the ground height) and the
        ground disc, or ``None`` when that sector is most of the circle. Its rows serve both
        the ground estimate and the raycaster's sector test, so the scene is scanned once."""
        radius = max(run.reach, self.ground.radius + GROUND_SLACK_M)
        wedges = disc_wedges(self.lidar, box[:2], radius)
        return None if wedges is None else wedge_rows(scene, wedges, self.lidar)

    def shadow_meta(
        self, seq: SequenceData, frame_idx: int, run: PhantomRun, state: ScheduleState
    ) -> dict:
        """The phantom's pose continued into a clean lifecycle frame. No points are read, so
        the box is not ground-anchored: its bottom stays on the reference frame's z = 0 (the
        vehicle frame's ground plane), carried by the poses in global mode."""
        _, box = self.phantom_pose(seq, frame_idx, run)
        return self.meta(
            state,
            target_box=box,
            target_is_shadow=True,
            target_obj_id=self.phantom_id(run),
            num_spoof_points=run.budget,
        )
