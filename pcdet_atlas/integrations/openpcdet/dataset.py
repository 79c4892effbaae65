"""An ATLAS variant as an OpenPCDet dataset: OpenPCDet's ``WaymoDataset`` with its one frame
reader, ``get_lidar``, attacking each frame it reads.

OpenPCDet's ``WaymoDataset`` reads every frame through ``get_lidar(sequence_name, sample_idx)``:
the current frame in ``__getitem__`` and each history frame of a sequence input in
``get_sequence_data``. Overriding it attacks every frame of the input by its own schedule state,
as :class:`pcdet_atlas.attacks.atlas_dataset.AtlasWaymoDataset` does: the attack acts on the raw
rows of the frame file (no-label-zone rows included; the added rows carry the NLZ flag -1), and
the loader's row filter and feature transform apply afterwards (OpenPCDet 0.6.0's: rows with
NLZ flag -1 unless ``DISABLE_NLZ_FLAG_ON_POINTS``, ``tanh`` on ``POINTS_TANH_DIM``, default the
intensity). A clean frame is OpenPCDet's own ``get_lidar``. The rest is OpenPCDet's: infos,
sampling, sequence stacking, ``prepare_data``, ``collate_batch``, ``generate_prediction_dicts``,
except the two readers of pickles: the sequence infos and a ``USE_PREDBOX`` box file are read
through the project's restricted unpickler, not ``pickle.load``, so that no data file can run
code under this dataset (see :meth:`AtlasWaymoDataset.include_waymo_data`).

Each sample also carries ``atlas_attack``, the current frame's attack record (the one
:class:`~pcdet_atlas.attacks.atlas_dataset.AtlasWaymoDataset` serves), collated as a list that
OpenPCDet's ``load_data_to_gpu`` leaves alone (it is no array).
"""

from __future__ import annotations

import collections
import copy
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from pcdet.datasets import __all__ as OPENPCDET_DATASETS
from pcdet.datasets.waymo.waymo_dataset import WaymoDataset

from pcdet_atlas.attacks.base import BaseAttack, SequenceData, build_attack
from pcdet_atlas.config import ConfigError, cfg_from_yaml_file
from pcdet_atlas.datasets.waymo_format import (
    find_sequence_pkl,
    load_frame_points,
    load_sequence_infos,
    sequence_name_from_line,
)
from pcdet_atlas.utils.paths import safe_component
from pcdet_atlas.utils.safe_pickle import load_pickle

__all__ = ["ATTACK_KEY", "NAME", "RECORD_KEY", "AtlasWaymoDataset", "register"]

#: the name this dataset has in OpenPCDet's registry (``DATA_CONFIG.DATASET``)
NAME = "AtlasWaymoDataset"
#: the ``DATA_CONFIG`` key naming the attack: an attack YAML's path, or a loaded attack config
ATTACK_KEY = "ATLAS_ATTACK"
#: the sample and batch key of the current frame's attack record
RECORD_KEY = "atlas_attack"
DEFAULT_TANH_DIMS = (3,)  # OpenPCDet's default: tanh of the raw intensity


class AtlasWaymoDataset(WaymoDataset):
    """OpenPCDet's ``WaymoDataset`` serving the ATLAS variant of ``DATA_CONFIG.ATLAS_ATTACK``.

    Args: OpenPCDet's ``WaymoDataset``'s (``dataset_cfg``, ``class_names``, ``training``,
    ``root_path``, ``logger``), as OpenPCDet's ``build_dataloader`` passes them; or
    ``attack`` (a built attack) in place of ``dataset_cfg.ATLAS_ATTACK``.
    """

    def __init__(
        self, dataset_cfg, class_names, training=True, root_path=None, logger=None, attack=None
    ):
        # OpenPCDet's constructor opens ImageSets/<split>.txt and reads under <tag>/ first
        mode = "train" if training else "test"
        safe_component(str(dataset_cfg.DATA_SPLIT[mode]), f"DATA_SPLIT.{mode}", "DATA_CONFIG")
        safe_component(str(dataset_cfg.PROCESSED_DATA_TAG), "PROCESSED_DATA_TAG", "DATA_CONFIG")
        super().__init__(
            dataset_cfg=dataset_cfg, class_names=class_names, training=training,
            root_path=root_path, logger=logger,
        )  # fmt: skip
        if attack is None:
            attack = self.dataset_cfg.get(ATTACK_KEY)
            if attack is None:
                raise ConfigError(
                    f"DATA_CONFIG.DATASET {NAME} needs DATA_CONFIG.{ATTACK_KEY}: the path of an "
                    "attack YAML (cfgs/attacks/<variant>.yaml)"
                )
        if isinstance(attack, BaseAttack):
            self.attack = attack
        else:
            cfg = attack if isinstance(attack, Mapping) else cfg_from_yaml_file(attack)
            self.attack = build_attack(cfg, data_root=self.root_path)
        sequence_cfg = self.dataset_cfg.get("SEQUENCE_CONFIG")
        history = 0
        if sequence_cfg is not None and sequence_cfg.get("ENABLED", False):
            history = int(sequence_cfg.SAMPLE_OFFSET[1] - sequence_cfg.SAMPLE_OFFSET[0])
        # spoofed frames simulated lately: a sequence input read in order reuses its history
        self._simulated: collections.OrderedDict = collections.OrderedDict()
        self._cache_size = history + 1
        self._sequences: dict[str, SequenceData] = {}
        self._by_frame_id = {info["frame_id"]: info for info in self.infos}

    def include_waymo_data(self, mode):
        """OpenPCDet's reader of the split's infos, with the project's reader of a sequence's
        info pkl (:func:`~pcdet_atlas.datasets.waymo_format.load_sequence_infos`: the restricted
        unpickler and the info layout checked) in place of ``pickle.load``, and the sequence
        names of ``ImageSets`` kept to one path component. A listed sequence without an info
        file is an error naming the paths tried (OpenPCDet skips it). As OpenPCDet's:
        ``self.infos`` extended, then every ``SAMPLED_INTERVAL[mode]``-th kept; returns
        ``{sequence: infos}`` for a sequence input (``SEQUENCE_CONFIG.ENABLED``), else None."""
        tag = self.dataset_cfg.PROCESSED_DATA_TAG
        listing = f"{self.root_path / 'ImageSets' / self.split}.txt"
        seq_name_to_infos = {}
        for line_no, line in enumerate(self.sample_sequence_list, 1):
            if not line.strip():
                continue
            where = f"{listing} line {line_no}"
            sequence = safe_component(sequence_name_from_line(line), "sequence name", where)
            infos = load_sequence_infos(find_sequence_pkl(self.root_path, sequence, tag))
            self.infos.extend(infos)
            seq_name_to_infos[infos[0]["point_cloud"]["lidar_sequence"]] = infos
        interval = int(self.dataset_cfg.SAMPLED_INTERVAL[mode])
        if interval > 1:
            self.infos = self.infos[::interval]
        sequence_cfg = self.dataset_cfg.get("SEQUENCE_CONFIG", None)
        return seq_name_to_infos if sequence_cfg is not None and sequence_cfg.ENABLED else None

    def load_pred_boxes_to_dict(self, pred_boxes_path):
        """OpenPCDet's ``USE_PREDBOX`` reader (``{sequence: {sample_idx: (R, 9) boxes, score,
        label}}`` from a ``result.pkl``-style list of prediction dicts), with the project's
        restricted unpickler in place of ``pickle.load``."""
        pred_dicts = load_pickle(pred_boxes_path)
        if not isinstance(pred_dicts, list):
            raise ValueError(
                f"{pred_boxes_path}: expected a list of prediction dicts (a result.pkl), got "
                f"{type(pred_dicts).__name__}"
            )
        table: dict = {}
        for index, box_dict in enumerate(pred_dicts):
            missing = {"frame_id", "name", "boxes_lidar", "score"} - set(box_dict)
            if missing:
                raise ValueError(f"{pred_boxes_path} [{index}]: missing keys {sorted(missing)}")
            frame_id = str(box_dict["frame_id"])
            sequence = frame_id[:-4].replace("training_", "").replace("validation_", "")
            labels = np.array(
                [self.class_names.index(name) + 1 for name in box_dict["name"]], dtype=np.float64
            )
            table.setdefault(sequence, {})[int(frame_id[-3:])] = np.concatenate(
                (box_dict["boxes_lidar"], box_dict["score"][:, None], labels[:, None]), axis=-1
            )
        return table

    def set_split(self, split):
        """OpenPCDet's ``set_split``; the sequences and frames of the previous split forgotten."""
        safe_component(str(split), "split", "set_split")
        super().set_split(split)
        self._sequences, self._simulated = {}, collections.OrderedDict()
        self._by_frame_id = {info["frame_id"]: info for info in self.infos}

    def atlas_sequence(self, sequence_name: str) -> SequenceData:
        """Poses and labels of every frame of a sequence (its info pkl, read without pickled
        code), as the attack sees them."""
        seq = self._sequences.get(sequence_name)
        if seq is None:
            infos = load_sequence_infos(self.data_path / sequence_name / f"{sequence_name}.pkl")
            seq = SequenceData(sequence_name, infos, root=str(self.root_path))
            self._sequences[sequence_name] = seq
        return seq

    def loader_points(self, rows: np.ndarray) -> np.ndarray:
        """Raw ``(N, 6)`` rows -> OpenPCDet 0.6.0 ``WaymoDataset.get_lidar``'s ``(N', 5)``
        points: the NLZ row filter unless ``DISABLE_NLZ_FLAG_ON_POINTS``, then ``tanh`` on the
        ``POINTS_TANH_DIM`` columns (default: the intensity)."""
        points = rows[:, :5]
        if not self.dataset_cfg.get("DISABLE_NLZ_FLAG_ON_POINTS", False):
            points = points[rows[:, 5] == -1]
        else:
            points = points.copy()
        for dim in self.dataset_cfg.get("POINTS_TANH_DIM", None) or DEFAULT_TANH_DIMS:
            points[:, dim] = np.tanh(points[:, dim])
        return points

    def _spoofed_frame(self, sequence_name: str, sample_idx: int) -> tuple[np.ndarray, dict]:
        """A spoofed frame's loader points and attack record, simulated once per cache life."""
        key = (sequence_name, int(sample_idx))
        if key in self._simulated:
            self._simulated.move_to_end(key)
            return self._simulated[key]
        seq = self.atlas_sequence(sequence_name)
        rows = load_frame_points(self.data_path / sequence_name / f"{int(sample_idx):04d}.npy")
        result = self.attack.simulate(rows, seq, int(sample_idx))
        points = self.loader_points(result.apply(rows, fill_value=-1.0))
        points.flags.writeable = False
        self._simulated[key] = (points, result.meta)
        if len(self._simulated) > self._cache_size:
            self._simulated.popitem(last=False)
        return points, result.meta

    def get_lidar(self, sequence_name, sample_idx):
        """The frame's points as OpenPCDet's ``get_lidar`` returns them, attacked when the
        frame is spoofed (a current or a history frame alike)."""
        seq = self.atlas_sequence(sequence_name)
        if not self.attack.needs_simulation(int(sample_idx), seq.num_frames):
            return super().get_lidar(sequence_name, sample_idx)
        return self._spoofed_frame(sequence_name, sample_idx)[0].copy()

    def frame_attack_meta(self, sequence_name: str, sample_idx: int) -> dict:
        """The attack record of a frame (``sequence_name`` added), as
        :meth:`pcdet_atlas.attacks.atlas_dataset.AtlasWaymoDataset.frame_attack_meta`."""
        seq = self.atlas_sequence(sequence_name)
        if self.attack.needs_simulation(int(sample_idx), seq.num_frames):
            meta = copy.deepcopy(self._spoofed_frame(sequence_name, sample_idx)[1])
        else:
            meta = self.attack.frame_meta(seq, int(sample_idx))
        return {**meta, "sequence_name": sequence_name}

    def __getitem__(self, index):
        data_dict = super().__getitem__(index)
        point_cloud = self._by_frame_id[data_dict["frame_id"]]["point_cloud"]
        data_dict[RECORD_KEY] = self.frame_attack_meta(
            point_cloud["lidar_sequence"], int(point_cloud["sample_idx"])
        )
        return data_dict

    @staticmethod
    def collate_batch(batch_list, _unused=False):
        """OpenPCDet's ``collate_batch``, the attack records kept as a list."""
        records = [sample.pop(RECORD_KEY) for sample in batch_list]
        batch = WaymoDataset.collate_batch(batch_list, _unused)
        batch[RECORD_KEY] = records
        return batch


def register() -> None:
    """Put :class:`AtlasWaymoDataset` in OpenPCDet's dataset registry as :data:`NAME`.

    Raises:
        ValueError: another class holds the name there.
    """
    existing = OPENPCDET_DATASETS.get(NAME)
    if existing is not None and existing is not AtlasWaymoDataset:
        raise ValueError(
            f"OpenPCDet's dataset registry holds {existing.__module__}.{existing.__qualname__} "
            f"as {NAME!r}; cannot register pcdet_atlas's"
        )
    OPENPCDET_DATASETS[NAME] = AtlasWaymoDataset


def attack_data_cfg(data_cfg: Mapping, attack: str | Path | BaseAttack) -> dict:
    """A copy of an OpenPCDet ``DATA_CONFIG`` (of OpenPCDet's ``WaymoDataset``) serving the
    variant of ``attack`` (an attack YAML's path, or a built attack) through this dataset.

    Raises:
        ConfigError: a ``DATASET`` other than OpenPCDet's ``WaymoDataset`` (or this one).
    """
    if data_cfg.get("DATASET") not in ("WaymoDataset", NAME):
        raise ConfigError(
            f"DATA_CONFIG.DATASET is {data_cfg.get('DATASET')!r}: the ATLAS variants are served "
            "for OpenPCDet's WaymoDataset configs"
        )
    out = copy.deepcopy(data_cfg)
    out["DATASET"] = NAME
    out[ATTACK_KEY] = attack if isinstance(attack, BaseAttack) else str(attack)
    return out
