"""The two transform pipelines of a dataset: training augmentations and data processors.

Both are lists of registered :data:`~pcdet_atlas.registry.TRANSFORMS` built from OpenPCDet's
config sections (``DATA_AUGMENTOR.AUG_CONFIG_LIST`` and ``DATA_PROCESSOR``). Every transform is
a class with

* ``CONFIG``: the declaration of its config item's keys besides ``NAME`` (a frozen dataclass of
  :func:`~pcdet_atlas.config_values.setting` fields; other keys are errors),
* ``from_config(cfg, **context)``: config -> plain keyword arguments, reading the item with
  :func:`read_transform_config`. ``context`` holds what the
  dataset knows: ``root_path``, ``class_names``, ``point_cloud_range``, ``training``, ``logger``,
  and ``section``, where the item sits (``DATA_AUGMENTOR.AUG_CONFIG_LIST[i] of <file>``, for
  error messages),
* ``__call__(data_dict, rng) -> data_dict``: ``rng`` is a ``numpy.random.Generator`` keyed by
  ``(seed, epoch, sequence_name, sample_idx, stage, position, NAME)``, so a frame's draws do not
  depend on worker count, batch order or the other frames.

``data_dict`` holds ``points`` float32 ``(N, C)``, ``gt_boxes`` float ``(M, 7|9)``, ``gt_names``
``(M,)`` str and, during augmentation, ``gt_boxes_mask`` ``(M,)`` bool (boxes of the wanted
classes). World transforms left-multiply ``lidar_aug_matrix`` (4x4) by what they did.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pcdet_atlas.config import ConfigError, key_source
from pcdet_atlas.config_values import read_section, setting
from pcdet_atlas.datasets.proposal_history import PROPOSAL_KEYS
from pcdet_atlas.registry import TRANSFORMS
from pcdet_atlas.utils.common import limit_period
from pcdet_atlas.utils.seeding import numpy_generator

__all__ = [
    "AugmentorConfig",
    "DataAugmentor",
    "DataProcessor",
    "build_transform",
    "check_transform_config",
    "read_transform_config",
]

_VOXEL_HINT = (
    "voxelization is part of the model in pcdet_atlas (a torch op in the VFE), not of the data "
    "loader: replace this item by transform_points_to_voxels_placeholder (the model reads its "
    "VOXEL_SIZE) or give the voxel settings to the model config"
)


def _transform_class(item: Mapping, section: str):
    if not isinstance(item, Mapping) or "NAME" not in item:
        raise ConfigError(f"{section}: each item must be a mapping with a NAME, got {item!r}")
    name = item["NAME"]
    if name == "transform_points_to_voxels":
        raise ConfigError(f"{section}: {name!r} (from {key_source(item, 'NAME')}): {_VOXEL_HINT}")
    try:
        return TRANSFORMS.get(name)
    except KeyError as err:
        raise ConfigError(f"{section} (from {key_source(item, 'NAME')}): {err}") from err


def read_transform_config(cls: type, item: Mapping, section: str = "<unknown>") -> Any:
    """The config item of transform ``cls`` read into ``cls.CONFIG``; its keys are named
    ``<NAME>.<KEY>`` in messages, and the item's place by ``section``."""
    name = item["NAME"]
    return read_section(cls.CONFIG, item, name, where=f"{section} ({name})", ignore=("NAME",))


def check_transform_config(item: Mapping, section: str) -> None:
    """Raise :class:`ConfigError` if ``item`` names no known transform or has an unknown key or
    a bad value."""
    read_transform_config(_transform_class(item, section), item, section)


def build_transform(item: Mapping, section: str, **context):
    """Check one config item and build its transform with ``from_config(item, **context)``."""
    check_transform_config(item, section)
    return _transform_class(item, section).from_config(item, section=section, **context)


class _Pipeline:
    stage = ""

    def __init__(self, transforms: Sequence[tuple[str, object]]):
        """``transforms``: ``(NAME, callable)`` pairs applied in order."""
        self.transforms = list(transforms)

    @property
    def names(self) -> list[str]:
        return [name for name, _ in self.transforms]

    def _run(self, data_dict: dict, seed_keys: tuple) -> dict:
        for position, (name, transform) in enumerate(self.transforms):
            rng = numpy_generator(*seed_keys, self.stage, position, name)
            data_dict = transform(data_dict, rng)
        return data_dict

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.names})"


@dataclass(frozen=True, kw_only=True)
class AugmentorConfig:
    """The ``DATA_AUGMENTOR`` section (each item is read by its transform's ``CONFIG``)."""

    disable_aug_list: tuple[str, ...] | None = setting((), doc="NAMEs of AUG_CONFIG_LIST left out")
    aug_config_list: tuple[Mapping, ...] | None = setting(
        (), doc="the augmentations, in order: each a mapping with NAME and its keys"
    )


class DataAugmentor(_Pipeline):
    """Training augmentations (``DATA_AUGMENTOR``), as OpenPCDet's ``DataAugmentor``."""

    stage = "augment"
    CONFIG = AugmentorConfig

    @classmethod
    def check_config(cls, cfg: Mapping) -> AugmentorConfig:
        """Validate ``DATA_AUGMENTOR`` (its keys and every item) without building."""
        settings = read_section(cls.CONFIG, cfg, "DATA_CONFIG.DATA_AUGMENTOR")
        origin = key_source(cfg, "AUG_CONFIG_LIST")
        for i, item in enumerate(settings.aug_config_list or ()):
            check_transform_config(item, f"DATA_AUGMENTOR.AUG_CONFIG_LIST[{i}] of {origin}")
        return settings

    @classmethod
    def from_config(cls, cfg: Mapping, **context) -> DataAugmentor:
        settings = cls.check_config(cfg)
        disabled = set(settings.disable_aug_list or ())
        transforms = []
        origin = key_source(cfg, "AUG_CONFIG_LIST")
        for i, item in enumerate(settings.aug_config_list or ()):
            if item["NAME"] in disabled:
                continue
            section = f"DATA_AUGMENTOR.AUG_CONFIG_LIST[{i}] of {origin}"
            transforms.append((item["NAME"], build_transform(item, section, **context)))
        return cls(transforms)

    def forward(self, data_dict: dict, seed_keys: tuple) -> dict:
        """Apply every augmentation, wrap headings to [-pi, pi), keep only ``gt_boxes_mask``."""
        data_dict = self._run(data_dict, seed_keys)
        boxes = data_dict["gt_boxes"]
        boxes[:, 6] = limit_period(boxes[:, 6], offset=0.5, period=2 * np.pi)
        for key in PROPOSAL_KEYS:  # two-stage training proposals
            if data_dict.get(key) is not None:
                rois = data_dict[key]
                rois[:, 6] = limit_period(rois[:, 6], offset=0.5, period=2 * np.pi)
        if "gt_boxes_mask" in data_dict:
            mask = data_dict.pop("gt_boxes_mask")
            data_dict["gt_boxes"] = boxes[mask]
            data_dict["gt_names"] = data_dict["gt_names"][mask]
        return data_dict


class DataProcessor(_Pipeline):
    """Processors applied in train and test (``DATA_PROCESSOR``), as OpenPCDet's, minus
    voxelization (which lives in the model)."""

    stage = "process"

    @classmethod
    def check_config(cls, cfg: Sequence[Mapping], origin: str = "<unknown>") -> None:
        for i, item in enumerate(cfg or []):
            check_transform_config(item, f"DATA_CONFIG.DATA_PROCESSOR[{i}] of {origin}")

    @classmethod
    def from_config(
        cls, cfg: Sequence[Mapping], origin: str = "<unknown>", **context
    ) -> DataProcessor:
        """``origin``: the file the list came from (for error messages)."""
        cls.check_config(cfg, origin)
        return cls(
            [
                (item["NAME"], build_transform(item, f"DATA_PROCESSOR[{i}] of {origin}", **context))
                for i, item in enumerate(cfg or [])
            ]
        )

    def forward(self, data_dict: dict, seed_keys: tuple) -> dict:
        return self._run(data_dict, seed_keys)
