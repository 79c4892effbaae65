"""The dataset template (OpenPCDet's ``DatasetTemplate``): config sections shared by every
dataset, ``prepare_data`` (augment -> class filter -> feature encoding -> processors) and
``collate_batch``.

Randomness: every augmentation/processor draw comes from a generator keyed by
``(SEED, epoch, sequence_name, sample_idx, stage, position, NAME)``. Call
:meth:`DatasetTemplate.set_epoch` at the start of every epoch (before creating the epoch's
iterator) so that epochs differ; the draws never depend on workers or batch order.

Deliberate differences from OpenPCDet: a training frame left with no GT box is returned as it
is (OpenPCDet silently swaps in a random other frame); ``gt_names`` stays in the sample;
points are float32 and never voxelized here (voxelization is part of the model).
"""

from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch.utils.data as torch_data

from pcdet_atlas.config import ConfigError, key_source, resolve_repo_path
from pcdet_atlas.config_values import read_section, setting
from pcdet_atlas.datasets.augmentor import DataAugmentor, DataProcessor
from pcdet_atlas.datasets.point_features import PointFeatureConfig, PointFeatureEncoder
from pcdet_atlas.utils.seeding import derive_seed

__all__ = ["DatasetConfig", "DatasetTemplate", "collate_batch"]


@dataclass(frozen=True, kw_only=True)
class DatasetConfig:
    """The ``DATA_CONFIG`` keys every dataset reads."""

    dataset: str | None = setting(None, doc="registered dataset class")
    data_path: str | None = setting(None, doc="dataset root, relative to the repository root")
    point_cloud_range: tuple[float, float, float, float, float, float] = setting(
        check=lambda r: all(r[i] < r[i + 3] for i in range(3)),
        expected="6 finite numbers [x_min, y_min, z_min, x_max, y_max, z_max] with min < max (m)",
        doc="the range points and boxes are kept in, m",
    )
    data_augmentor: Mapping | None = setting(
        None, doc="training augmentations (read by DataAugmentor)"
    )
    point_feature_encoding: PointFeatureConfig = setting(doc="which point columns the model reads")
    data_processor: tuple[Mapping, ...] | None = setting(
        (), doc="processors of train and test, in order"
    )
    seed: int = setting(0, doc="seed of every augmentation draw")


class DatasetTemplate(torch_data.Dataset):
    """Base of the datasets: builds the shared pipeline from ``dataset_cfg``.

    Attributes used by models: ``point_cloud_range`` (6,) float32 m, ``num_point_features``,
    ``class_names``, ``training``, ``mode`` (``'train'``/``'test'``).
    """

    #: The declaration of the DATA_CONFIG keys this class reads; subclasses extend it (unknown
    #: keys are errors).
    CONFIG: ClassVar[type[DatasetConfig]] = DatasetConfig

    def __init__(
        self,
        dataset_cfg: Mapping,
        class_names: Sequence[str],
        training: bool = True,
        root_path: str | Path | None = None,
        logger: logging.Logger | None = None,
    ):
        super().__init__()
        #: the checked ``DATA_CONFIG`` (an instance of :attr:`CONFIG`)
        self.settings = read_section(self.CONFIG, dataset_cfg, "DATA_CONFIG")
        self.dataset_cfg = dataset_cfg
        self.training = training
        self.mode = "train" if training else "test"
        self.class_names = list(class_names)
        self.logger = logger if logger is not None else logging.getLogger(__name__)
        if root_path is not None:
            self.root_path = Path(root_path)
        elif self.settings.data_path is not None:
            self.root_path = resolve_repo_path(self.settings.data_path)
        else:
            raise ConfigError("DATA_CONFIG: no DATA_PATH and no root_path given")
        self.point_cloud_range = np.array(self.settings.point_cloud_range, dtype=np.float32)
        self.seed = self.settings.seed
        self.epoch = 0
        self.total_epochs = 0
        self._merge_all_iters_to_one_epoch = False

        encoding = self.settings.point_feature_encoding
        self.point_feature_encoder = PointFeatureEncoder(
            list(encoding.used_feature_list), list(encoding.src_feature_list)
        )
        context = {
            "root_path": self.root_path,
            "class_names": self.class_names,
            "point_cloud_range": self.point_cloud_range,
            "training": training,
            "logger": self.logger,
        }
        augmentor_cfg = self.settings.data_augmentor
        self.data_augmentor = None
        if augmentor_cfg is not None:
            DataAugmentor.check_config(augmentor_cfg)  # unknown keys fail in test mode too
            if training:
                self.data_augmentor = DataAugmentor.from_config(augmentor_cfg, **context)
        self.data_processor = DataProcessor.from_config(
            list(self.settings.data_processor or ()),
            origin=key_source(dataset_cfg, "DATA_PROCESSOR"),
            **context,
        )

    # ------------------------------------------------------------------ epochs and length
    @property
    def num_point_features(self) -> int:
        """Columns of the points a sample carries (after feature encoding)."""
        return self.point_feature_encoder.num_point_features

    def set_epoch(self, epoch: int) -> None:
        """Select the epoch whose augmentation draws the next iterator uses."""
        self.epoch = int(epoch)

    def merge_all_iters_to_one_epoch(self, merge: bool = True, epochs: int | None = None) -> None:
        """OpenPCDet's option: one long epoch of ``epochs`` passes (the pass counts as epoch)."""
        self._merge_all_iters_to_one_epoch = merge
        self.total_epochs = int(epochs) if merge and epochs else 0

    def __len__(self) -> int:
        raise NotImplementedError

    def __getitem__(self, index: int) -> dict:
        raise NotImplementedError

    def frame_seed_keys(self, sequence_name: str, sample_idx: int, epoch: int | None = None):
        """The keys every random draw of one frame's pipeline starts from."""
        return (self.seed, self.epoch if epoch is None else epoch, sequence_name, int(sample_idx))

    # ------------------------------------------------------------------ one sample
    def prepare_data(self, data_dict: dict, epoch: int | None = None) -> dict:
        """Augment (training), keep ``class_names`` boxes, encode features, run processors.

        Args:
            data_dict: ``points`` float32 ``(N, C_src)``, ``sequence_name``, ``sample_idx`` and,
                when labelled, ``gt_boxes`` ``(M, 7|9)`` and ``gt_names`` ``(M,)``.
        Returns:
            the dict with ``points`` float32 ``(N', C_used)``, ``gt_boxes`` float32
            ``(M', 8|10)`` (last column: 1-based index into ``class_names``), ``gt_names``,
            ``lidar_aug_matrix`` (4, 4) float32, ``frame_seed`` (the int a model keys its own
            random draws of this sample by) and, after augmentation, what it drew.
        """
        keys = self.frame_seed_keys(data_dict["sequence_name"], data_dict["sample_idx"], epoch)
        has_boxes = data_dict.get("gt_boxes") is not None
        if has_boxes:
            data_dict["gt_boxes"] = np.array(data_dict["gt_boxes"], dtype=np.float64)
            data_dict["gt_names"] = np.asarray(data_dict["gt_names"])
        if self.training and self.data_augmentor is not None:
            if not has_boxes:
                raise ConfigError(
                    f"{data_dict.get('frame_id')}: training augmentation needs labelled frames"
                )
            mask = np.array([n in self.class_names for n in data_dict["gt_names"]], dtype=bool)
            data_dict["gt_boxes_mask"] = mask
            data_dict = self.data_augmentor.forward(data_dict, keys)
        data_dict["lidar_aug_matrix"] = np.asarray(
            data_dict.get("lidar_aug_matrix", np.eye(4)), dtype=np.float32
        )
        if has_boxes:
            names = data_dict["gt_names"]
            keep = np.array([n in self.class_names for n in names], dtype=bool)
            names = names[keep]
            classes = np.array([self.class_names.index(n) + 1 for n in names], dtype=np.float64)
            boxes = data_dict["gt_boxes"][keep]
            data_dict["gt_boxes"] = np.concatenate([boxes, classes.reshape(-1, 1)], axis=1).astype(
                np.float32
            )
            data_dict["gt_names"] = names
        data_dict = self.point_feature_encoder.forward(data_dict)
        data_dict = self.data_processor.forward(data_dict, keys)
        data_dict["frame_seed"] = derive_seed(*keys, "model")
        return data_dict

    # ------------------------------------------------------------------ batches
    @staticmethod
    def collate_batch(batch_list: list[dict], _unused: bool = False) -> dict:
        """See :func:`collate_batch` (module level)."""
        return collate_batch(batch_list)


#: keys stacked into one array by :func:`collate_batch` (everything unknown stays a list).
STACKED_KEYS = (
    "frame_id",
    "sequence_name",
    "sample_idx",
    "pose",
    "poses",
    "lidar_aug_matrix",
    "use_lead_xyz",
    "flip_x",
    "flip_y",
    "noise_rot",
    "noise_scale",
    "frame_seed",
    "roi_history_frames",
)


def collate_batch(batch_list: list[dict]) -> dict:
    """Merge samples into a batch, as OpenPCDet's ``collate_batch``.

    * ``points`` ``(N_i, C)`` -> ``(sum N_i, 1 + C)`` float32 with the sample index first;
    * ``gt_boxes`` ``(M_i, B)`` -> ``(batch, max M_i, B)`` float32, zero-padded (the same for
      the proposals ``roi_boxes`` / ``roi_history`` of two-stage training, whose zero label
      marks padding);
    * the keys of :data:`STACKED_KEYS` -> ``np.stack`` (``(batch, ...)``);
    * anything else (``gt_names``, ``metadata``, attack metadata, ...) -> a list per key;
    * ``batch_size`` = number of samples.
    Empty samples (0 points, 0 boxes) are fine. Every sample must have the same keys: a key
    missing from some samples (``gt_boxes`` of an unlabelled frame batched with labelled ones)
    raises ``ValueError`` naming the key and those samples.
    """
    data = defaultdict(list)
    for sample in batch_list:
        for key, val in sample.items():
            data[key].append(val)
    batch_size = len(batch_list)
    partial = [key for key, vals in data.items() if len(vals) != batch_size]
    if partial:
        lacking = []
        for key in partial:
            idx = [f"{i} ({s.get('frame_id')})" for i, s in enumerate(batch_list) if key not in s]
            lacking.append(f"{key!r} is missing from sample(s) {', '.join(idx)}")
        raise ValueError(
            f"collate_batch: every sample of a batch must have the same keys; in this batch of "
            f"{batch_size}, {'; '.join(lacking)}"
        )
    ret: dict = {}
    for key, vals in data.items():
        if key == "points":
            widths = {np.shape(v)[1] for v in vals}
            if len(widths) != 1:
                raise ValueError(f"collate_batch: points of different widths {sorted(widths)}")
            out = np.empty((sum(len(v) for v in vals), 1 + widths.pop()), dtype=np.float32)
            start = 0
            for i, v in enumerate(vals):  # one copy into place (no pad + concatenate)
                out[start : start + len(v), 0] = i
                out[start : start + len(v), 1:] = v
                start += len(v)
            ret[key] = out
        elif key in ("gt_boxes", "roi_boxes", "roi_history"):
            max_gt = max(len(v) for v in vals)
            width = vals[0].shape[-1]
            boxes = np.zeros((batch_size, max_gt, width), dtype=np.float32)
            for k, v in enumerate(vals):
                boxes[k, : len(v)] = v
            ret[key] = boxes
        elif key in STACKED_KEYS:
            try:
                ret[key] = np.stack(vals, axis=0)
            except ValueError as err:
                raise ValueError(f"collate_batch: cannot stack key {key!r}: {err}") from err
        else:
            ret[key] = vals
    ret["batch_size"] = batch_size
    return ret
