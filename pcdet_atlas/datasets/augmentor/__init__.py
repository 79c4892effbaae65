"""Registered training augmentations and data processors (see :mod:`.base`)."""

from pcdet_atlas.datasets.augmentor import gt_sampling, processors, world_transforms  # noqa: F401
from pcdet_atlas.datasets.augmentor.base import (
    DataAugmentor,
    DataProcessor,
    build_transform,
    check_transform_config,
)

__all__ = ["DataAugmentor", "DataProcessor", "build_transform", "check_transform_config"]
