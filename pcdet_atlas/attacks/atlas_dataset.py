"""``AtlasWaymoDataset``: any ATLAS variant of a Waymo-format split, served on the fly (SPEC §3.7).

It is :class:`~pcdet_atlas.datasets.waymo_dataset.WaymoDataset` with one hook overridden:
:meth:`get_lidar`, through which every frame's points are read, current or history. Each frame
is attacked there by **its own** schedule state (a history frame of a multi-frame input that is
spoofed gets the same run's phantom / removal as when it is the current frame; a clean history
frame is read untouched), so frame ``t`` of a variant is bitwise identical whether it is loaded
as the current frame or as history, in any order, with any number of workers (SPEC §3.6).

Clean frames do no attack work (no raycast, no sector, no ground estimate); the counters of
:mod:`pcdet_atlas.attacks.counters` prove it. ``__getitem__`` returns the clean dataset's dict,
points attacked before any voxelization, plus ``attack``: the metadata record of the current
frame (:mod:`pcdet_atlas.attacks.metadata`), with the shadow target on clean lifecycle frames.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from pcdet_atlas.attacks.base import BaseAttack, FrameAttack, SequenceData, build_attack
from pcdet_atlas.attacks.counters import COUNTERS
from pcdet_atlas.config import cfg_from_yaml_file
from pcdet_atlas.datasets.waymo_dataset import WaymoDataset
from pcdet_atlas.registry import DATASETS

__all__ = ["AtlasWaymoDataset"]


@DATASETS.register()
class AtlasWaymoDataset(WaymoDataset):
    """A Waymo-format split with an ATLAS attack applied per frame.

    Args:
        dataset_cfg, class_names, training, root_path, logger: as :class:`WaymoDataset`.
        attack_cfg: a loaded attack YAML (``EasyDict``), the path of one, or a built
            :class:`~pcdet_atlas.attacks.base.BaseAttack`. Relative trace-library paths resolve
            under the dataset root.
    """

    def __init__(
        self,
        dataset_cfg: Mapping,
        class_names: Sequence[str],
        attack_cfg: Mapping | str | Path | BaseAttack,
        training: bool = False,
        root_path: str | Path | None = None,
        logger: logging.Logger | None = None,
    ):
        super().__init__(dataset_cfg, class_names, training, root_path, logger)
        if isinstance(attack_cfg, BaseAttack):
            self.attack = attack_cfg
        else:
            cfg = attack_cfg if isinstance(attack_cfg, Mapping) else cfg_from_yaml_file(attack_cfg)
            self.attack = build_attack(cfg, data_root=self.root_path)
        self._sequences: dict[str, SequenceData] = {}
        self._current: tuple[str, int] | None = None
        self._current_meta: dict | None = None
        self.logger.info(f"ATLAS attack: {self.attack.variant} ({type(self.attack).__name__})")

    # ------------------------------------------------------------------ frames
    def sequence_data(self, sequence_name: str) -> SequenceData:
        """Poses and labels of a sequence of the split, as the attack sees them."""
        seq = self._sequences.get(sequence_name)
        if seq is None:
            infos = self.seq_name_to_infos.get(sequence_name)
            if infos is None:
                raise KeyError(f"sequence {sequence_name!r} is not in split {self.split!r}")
            seq = self._sequences[sequence_name] = SequenceData(sequence_name, infos)
        return seq

    def raw_to_loaded_features(self, raw: np.ndarray) -> np.ndarray:
        """``(K, 5)`` raw ``[x, y, z, intensity, elongation]`` -> the loader's feature space
        (tanh on the ``POINTS_TANH_DIM`` columns, exactly as :meth:`WaymoDataset.get_lidar`)."""
        out = np.array(raw, dtype=np.float32)
        for dim in self.tanh_dims:
            out[:, dim] = np.tanh(out[:, dim])
        return out

    def simulate_frame(
        self, sequence_name: str, sample_idx: int
    ) -> tuple[np.ndarray, FrameAttack | None]:
        """Clean points of a frame and, if the frame is spoofed, its :class:`FrameAttack`
        (``None`` for a clean frame: nothing was simulated)."""
        points = super().get_lidar(sequence_name, sample_idx)
        seq = self.sequence_data(sequence_name)
        if not self.attack.needs_simulation(sample_idx, seq.num_frames):
            return points, None
        return points, self.attack.simulate(points, seq, sample_idx)

    def get_lidar(self, sequence_name: str, sample_idx: int) -> np.ndarray:
        """Attacked points of one frame, ``(N', 5)`` float32 in the loader's feature space."""
        points, result = self.simulate_frame(sequence_name, sample_idx)
        if result is None:
            return points
        if (sequence_name, int(sample_idx)) == self._current:
            self._current_meta = result.meta
        else:
            COUNTERS.add(history_frames_resimulated=1)
        return result.apply(points, self.raw_to_loaded_features)

    def frame_attack_meta(self, sequence_name: str, sample_idx: int) -> dict:
        """The metadata record of a frame; for a spoofed frame this simulates it."""
        seq = self.sequence_data(sequence_name)
        if self.attack.needs_simulation(sample_idx, seq.num_frames):
            return self.simulate_frame(sequence_name, sample_idx)[1].meta
        return self.attack.frame_meta(seq, sample_idx)

    # ------------------------------------------------------------------ samples
    def __getitem__(self, index: int) -> dict:
        """The clean sample dict with attacked points and ``attack`` (the metadata record)."""
        info = self.infos[index % len(self.infos)]
        sequence_name = info["point_cloud"]["lidar_sequence"]
        sample_idx = int(info["point_cloud"]["sample_idx"])
        self._current, self._current_meta = (sequence_name, sample_idx), None
        try:
            data = super().__getitem__(index)
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
        data["attack"] = meta
        return data
