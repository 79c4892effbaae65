"""Datasets (OpenPCDet's processed Waymo format, the synthetic default) and their transforms.

Importing the package registers :class:`WaymoDataset` in ``DATASETS`` and the augmentations /
processors in ``TRANSFORMS``.
"""

from pcdet_atlas.datasets import augmentor  # noqa: F401  (registers the transforms)
from pcdet_atlas.datasets.dataset import DatasetTemplate, collate_batch
from pcdet_atlas.datasets.loader import build_dataloader, worker_init_fn
from pcdet_atlas.datasets.waymo_dataset import WaymoDataset

__all__ = [
    "DatasetTemplate",
    "WaymoDataset",
    "build_dataloader",
    "collate_batch",
    "worker_init_fn",
]
