"""``AtlasWaymoDataset``: any ATLAS variant of a Waymo-format split, served on the fly.

The attack physics and determinism rules are in docs/attacks.md.

It is :class:`~pcdet_atlas.datasets.waymo_dataset.WaymoDataset` with one hook overridden:
:meth:`get_lidar`, through which every frame's points are read, current or history. Each frame
is attacked there by **its own** schedule state (a history frame of a multi-frame input that is
spoofed gets the same run's phantom / removal as when it is the current frame; a clean history
frame is read untouched), so frame ``t`` of a variant is bitwise identical whether it is loaded
as the current frame or as history, in any order, with any number of workers.

The attack acts on the returns of the frame file as the sensor recorded them, rows of no-label
zones (NLZ) included (they are surfaces the sensor sees: they occlude a phantom and can be
occluded by it); the loader's own row filter applies afterwards, so an attacked frame does not
depend on ``DISABLE_NLZ_FLAG_ON_POINTS``. The file is read with room for the attack's added rows
(:meth:`~pcdet_atlas.attacks.base.BaseAttack.max_added_points`), so the attacked points cost one
row selection, the same as a clean frame's.

Clean frames do no attack work (no raycast, no sector, no ground estimate); the counters of
:mod:`pcdet_atlas.attacks.counters` prove it. ``__getitem__`` returns the clean dataset's dict,
points attacked before any voxelization, plus ``attack``: the metadata record of the current
frame (:mod:`pcdet_atlas.attacks.metadata`), with the shadow target on clean lifecycle frames.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from pcdet_atlas.attacks.base import BaseAttack, FrameAttack, SequenceData, build_attack
from pcdet_atlas.attacks.counters import COUNTERS
from pcdet_atlas.config import cfg_from_yaml_file
from pcdet_atlas.datasets.waymo_dataset import WaymoDataset
from pcdet_atlas.datasets.waymo_format import NUM_POINT_COLUMNS, load_frame_points
from pcdet_atlas.registry import DATASETS

__all__ = ["AtlasWaymoDataset"]


def _key_distance(key: tuple[str, int]):
    """Sort key of frame-cache entries by their distance in time from ``key``'s frame (frames
    of other sequences are the farthest)."""
    sequence, frame = key
    return lambda other: (other[0] != sequence, abs(other[1] - frame))


@DATASETS.register()
class AtlasWaymoDataset(WaymoDataset):
    """A Waymo-format split with an ATLAS attack applied per frame.

    Args:
        dataset_cfg, class_names, root_path, logger: as :class:`WaymoDataset`.
        training: as :class:`WaymoDataset`, but the third argument here is ``attack_cfg`` and
            ``training`` defaults to False (an attacked split is a test split).
        attack_cfg: a loaded attack YAML (``EasyDict``), the path of one, or a built
            :class:`~pcdet_atlas.attacks.base.BaseAttack`. Relative trace-library paths resolve
            under the dataset root.
        frame_cache_size: how many attacked frames this process keeps; a full cache drops the
            frame farthest in time from the one being stored (another sequence's first).
            ``None``: the input's frame count for a multi-frame input (what reading samples in
            order, forward or backward, needs: each new sample simulates one new frame), 0 for a
            single-frame one (no frame is read twice).
    """

    def __init__(
        self,
        dataset_cfg: Mapping,
        class_names: Sequence[str],
        attack_cfg: Mapping | str | Path | BaseAttack,
        training: bool = False,
        root_path: str | Path | None = None,
        logger: logging.Logger | None = None,
        frame_cache_size: int | None = None,
    ):
        super().__init__(dataset_cfg, class_names, training, root_path, logger)
        if frame_cache_size is None:
            num_frames = self.sequence_cfg.num_frames if self.sequence_cfg is not None else 1
            frame_cache_size = num_frames if num_frames > 1 else 0
        if isinstance(frame_cache_size, bool) or not isinstance(frame_cache_size, int):
            raise TypeError(f"frame_cache_size must be an int >= 0, got {frame_cache_size!r}")
        if frame_cache_size < 0:
            raise ValueError(f"frame_cache_size must be >= 0, got {frame_cache_size}")
        self.frame_cache_size = frame_cache_size
        # (sequence, frame) -> (read-only attacked points, metadata record) of spoofed frames
        self._frame_cache: dict[tuple[str, int], tuple[np.ndarray, dict]] = {}
        if isinstance(attack_cfg, BaseAttack):
            self.attack = attack_cfg
        else:
            cfg = attack_cfg if isinstance(attack_cfg, Mapping) else cfg_from_yaml_file(attack_cfg)
            self.attack = build_attack(cfg, data_root=self.root_path)
        self._sequences: dict[str, SequenceData] = {}
        self._current: tuple[str, int] | None = None
        self._current_meta: dict | None = None
        self.logger.info(f"ATLAS attack: {self.attack.variant} ({type(self.attack).__name__})")

    def set_split(self, split: str) -> None:
        """Load the sequences of another split (as :class:`WaymoDataset`) and forget the
        sequences and attacked frames of the previous one."""
        super().set_split(split)
        self._sequences = {}
        self._frame_cache = {}

    # ------------------------------------------------------------------ frames
    def sequence_data(self, sequence_name: str) -> SequenceData:
        """Poses and labels of a sequence of the split, as the attack sees them."""
        seq = self._sequences.get(sequence_name)
        if seq is None:
            infos = self.seq_name_to_infos.get(sequence_name)
            if infos is None:
                raise KeyError(f"sequence {sequence_name!r} is not in split {self.split!r}")
            seq = SequenceData(sequence_name, infos, root=str(self.root_path))
            self._sequences[sequence_name] = seq
        return seq

    def simulate_frame(
        self, sequence_name: str, sample_idx: int, spare_rows: int = 0
    ) -> tuple[np.ndarray, FrameAttack | None]:
        """The raw rows of a frame file and, if the frame is spoofed, its
        :class:`FrameAttack` (``None`` for a clean frame: nothing was simulated).

        The attack acts on every return of the file, as the sensor records them; the loader's
        own row filter (NLZ) applies afterwards. The rows come back in an array of
        ``spare_rows`` more rows than the file holds (uninitialised; see
        :func:`~pcdet_atlas.datasets.waymo_format.load_frame_points`).
        """
        rows = load_frame_points(self.frame_path(sequence_name, sample_idx), spare_rows)
        seq = self.sequence_data(sequence_name)
        if not self.attack.needs_simulation(sample_idx, seq.num_frames):
            return rows, None
        num_rows = len(rows) - spare_rows
        return rows, self.attack.simulate(rows[:num_rows], seq, sample_idx)

    def get_lidar(self, sequence_name: str, sample_idx: int) -> np.ndarray:
        """Attacked points of one frame, ``(N', 5)`` float32 in the loader's feature space.

        A spoofed frame is simulated once and kept in the frame cache, so the windows of a
        multi-frame input read in order reuse it as history; with the cache on, history frames
        come back read-only, the current frame as a copy the sample owns.
        """
        seq = self.sequence_data(sequence_name)
        if not self.attack.needs_simulation(sample_idx, seq.num_frames):
            return super().get_lidar(sequence_name, sample_idx)
        key = (sequence_name, int(sample_idx))
        cached = self._frame_cache.get(key)
        if cached is not None:
            COUNTERS.add(frame_cache_hits=1)
            points, meta = cached
        else:
            points, meta = self._simulate_points(sequence_name, sample_idx, seq)
            if key != self._current:
                COUNTERS.add(history_frames_resimulated=1)
            if self.frame_cache_size:
                COUNTERS.add(frame_cache_misses=1)
                points.flags.writeable = False
                if len(self._frame_cache) >= self.frame_cache_size:
                    # least recently used would evict the next window's frames: history is
                    # read newest first, after the current frame
                    del self._frame_cache[max(self._frame_cache, key=_key_distance(key))]
                self._frame_cache[key] = (points, meta)
        if key != self._current:
            return points
        self._current_meta = copy.deepcopy(meta) if self.frame_cache_size else meta
        return points.copy() if self.frame_cache_size else points

    def _simulate_points(
        self, sequence_name: str, sample_idx: int, seq: SequenceData
    ) -> tuple[np.ndarray, dict]:
        """Simulate a spoofed frame: its loaded points and its metadata record."""
        spare = self.attack.max_added_points(seq, sample_idx)
        buffer, result = self.simulate_frame(sequence_name, sample_idx, spare)
        num_rows, added = len(buffer) - spare, result.added
        if len(added) <= spare:  # the phantom's rows go into the room read with the frame
            rows = buffer[: num_rows + len(added)]
        else:  # a family whose bound was too low: one copy
            rows = np.empty((num_rows + len(added), NUM_POINT_COLUMNS), dtype=np.float32)
            rows[:num_rows] = buffer[:num_rows]
        rows[num_rows:, :5] = added
        rows[num_rows:, 5:] = -1.0  # not in a no-label zone
        return self.loaded_points(rows, drop=result.removed_rows()), result.meta

    def frame_attack_meta(self, sequence_name: str, sample_idx: int) -> dict:
        """The metadata record of a frame; for a spoofed frame not in the frame cache this
        simulates it."""
        seq = self.sequence_data(sequence_name)
        if self.attack.needs_simulation(sample_idx, seq.num_frames):
            cached = self._frame_cache.get((sequence_name, int(sample_idx)))
            if cached is not None:
                meta = copy.deepcopy(cached[1])
            else:
                meta = self.simulate_frame(sequence_name, sample_idx)[1].meta
        else:
            meta = self.attack.frame_meta(seq, sample_idx)
        return {**meta, "sequence_name": sequence_name}

    # ------------------------------------------------------------------ samples
    def get_sample(self, info: Mapping, epoch: int | None = None) -> dict:
        """The clean sample dict with attacked points and ``attack`` (the metadata record)."""
        sequence_name = info["point_cloud"]["lidar_sequence"]
        sample_idx = int(info["point_cloud"]["sample_idx"])
        self._current, self._current_meta = (sequence_name, sample_idx), None
        try:
            data = super().get_sample(info, epoch)
            meta = self._current_meta
        finally:
            self._current, self._current_meta = None, None
        if meta is None:  # clean frame: metadata only (shadow target on lifecycle frames)
            seq = self.sequence_data(sequence_name)
            if self.attack.needs_simulation(sample_idx, seq.num_frames):
                raise RuntimeError(
                    f"{info['frame_id']} is spoofed but was not simulated through get_lidar"
                )
            meta = self.attack.frame_meta(seq, sample_idx)
        data["attack"] = {**meta, "sequence_name": sequence_name}  # a run is (sequence, run_id)
        return data
