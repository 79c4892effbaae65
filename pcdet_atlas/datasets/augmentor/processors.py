"""Data processors run in training and testing (OpenPCDet's ``DATA_PROCESSOR``), minus
voxelization, which is a torch op inside the model here."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from pcdet_atlas.config import ConfigError
from pcdet_atlas.config_values import fields_of, setting
from pcdet_atlas.datasets.augmentor.base import read_transform_config
from pcdet_atlas.datasets.multiframe import compress_rows
from pcdet_atlas.ops.boxes import boxes_to_corners_3d
from pcdet_atlas.registry import TRANSFORMS

__all__ = [
    "MaskPointsAndBoxesOutsideRange",
    "ShufflePoints",
    "VoxelSizePlaceholder",
    "mask_points_by_range",
    "processor_voxel_size",
    "row_hash_order",
]


def mask_points_by_range(points: np.ndarray, limit_range, filter_z: bool = False) -> np.ndarray:
    """``(N,)`` bool: points inside ``limit_range`` ``[x0, y0, z0, x1, y1, z1]`` (closed).

    As OpenPCDet, only x and y are tested unless ``filter_z``.
    """
    r = np.asarray(limit_range)
    mask = (
        (points[:, 0] >= r[0])
        & (points[:, 0] <= r[3])
        & (points[:, 1] >= r[1])
        & (points[:, 1] <= r[4])
    )
    if filter_z:
        mask &= (points[:, 2] >= r[2]) & (points[:, 2] <= r[5])
    return mask


def mask_boxes_outside_range(
    boxes: np.ndarray, limit_range, min_num_corners: int = 1, use_center_to_filter: bool = True
) -> np.ndarray:
    """``(M,)`` bool: boxes to keep. By centre (inside the 3D range), or else by the number of
    the 8 box corners whose xy lies inside the xy range (at least ``min_num_corners``; each
    BEV corner counts twice, bottom and top), as OpenPCDet."""
    r = np.asarray(limit_range, dtype=np.float64)
    boxes = np.asarray(boxes, dtype=np.float64)
    if use_center_to_filter:
        centers = boxes[:, 0:3]
        return ((centers >= r[0:3]) & (centers <= r[3:6])).all(axis=-1)
    corners = boxes_to_corners_3d(boxes[:, :7])[:, :, 0:2]  # (M, 8, 2) xy of all 8 corners
    inside = ((corners >= r[0:2]) & (corners <= r[3:5])).all(axis=2)
    return inside.sum(axis=1) >= min_num_corners


@dataclass(frozen=True, kw_only=True)
class MaskOutsideRangeConfig:
    remove_outside_boxes: bool = setting(True, doc="in training, drop boxes outside the range")
    filter_z: bool = setting(False, doc="also drop points outside the z range")
    min_num_corners: int = setting(
        1, key="min_num_corners", ge=1, le=8, doc="corners inside for a box to stay"
    )
    use_center_to_filter: bool = setting(True, doc="keep a box by its centre, not its corners")


@TRANSFORMS.register("mask_points_and_boxes_outside_range")
class MaskPointsAndBoxesOutsideRange:
    """Drop points outside ``POINT_CLOUD_RANGE``; in training also drop boxes outside it."""

    CONFIG = MaskOutsideRangeConfig

    def __init__(
        self,
        point_cloud_range: Sequence[float],
        training: bool,
        remove_outside_boxes: bool = MaskOutsideRangeConfig.remove_outside_boxes,
        filter_z: bool = MaskOutsideRangeConfig.filter_z,
        min_num_corners: int = MaskOutsideRangeConfig.min_num_corners,
        use_center_to_filter: bool = MaskOutsideRangeConfig.use_center_to_filter,
    ):
        if len(point_cloud_range) != 6:
            raise ConfigError(f"POINT_CLOUD_RANGE must have 6 values, got {point_cloud_range!r}")
        self.point_cloud_range = np.asarray(point_cloud_range, dtype=np.float32)
        self.training = training
        self.remove_outside_boxes = remove_outside_boxes
        self.filter_z = filter_z
        self.min_num_corners = min_num_corners
        self.use_center_to_filter = use_center_to_filter

    @classmethod
    def from_config(
        cls, cfg: Mapping, *, point_cloud_range, training: bool, **context
    ) -> MaskPointsAndBoxesOutsideRange:
        settings = read_transform_config(cls, cfg, context.get("section", "<unknown>"))
        return cls(point_cloud_range=point_cloud_range, training=training, **fields_of(settings))

    def __call__(self, data_dict: dict, rng: np.random.Generator) -> dict:
        if data_dict.get("points") is not None:
            mask = mask_points_by_range(data_dict["points"], self.point_cloud_range, self.filter_z)
            if not mask.all():
                data_dict["points"] = compress_rows(mask, data_dict["points"])
        boxes = data_dict.get("gt_boxes")
        if boxes is not None and self.remove_outside_boxes and self.training:
            keep = mask_boxes_outside_range(
                boxes, self.point_cloud_range, self.min_num_corners, self.use_center_to_filter
            )
            data_dict["gt_boxes"] = boxes[keep]
            if "gt_names" in data_dict:
                data_dict["gt_names"] = data_dict["gt_names"][keep]
        return data_dict


_MIX_1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX_2 = np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


def _splitmix64(z: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser on a ``uint64`` array (wrapping arithmetic)."""
    z = z + _GOLDEN
    z = (z ^ (z >> np.uint64(30))) * _MIX_1
    z = (z ^ (z >> np.uint64(27))) * _MIX_2
    return z ^ (z >> np.uint64(31))


def row_hash_order(points: np.ndarray, seed: int) -> np.ndarray:
    """``(N,)`` int64: the rows of ``points`` ``(N, C)`` sorted by a seeded hash of their bytes.

    A permutation that depends only on the set of rows, not on their input order: any subset of
    the rows comes out in the same relative order as within the whole set (equal rows are
    interchangeable; the sort is stable, so distinct rows whose 64-bit hashes collide keep
    their input order). A multi-frame sample's newest frames therefore keep the order the
    shorter sample of those frames gets, so a model reading them sees the same array.
    """
    rows = np.ascontiguousarray(points)
    if rows.ndim != 2:
        raise ValueError(f"shuffle_points needs (N, C) points, got shape {rows.shape}")
    if rows.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    row_bytes = rows.view(np.uint8).reshape(rows.shape[0], -1)
    pad = -row_bytes.shape[1] % 8
    if pad:
        row_bytes = np.concatenate([row_bytes, np.zeros((rows.shape[0], pad), np.uint8)], axis=1)
    words = row_bytes.view(np.uint64)  # (N, ceil(C * itemsize / 8))
    with np.errstate(over="ignore"):
        h = np.full(rows.shape[0], np.uint64(seed), dtype=np.uint64)
        for column in range(words.shape[1]):
            h = _splitmix64(h ^ words[:, column])
    keys = torch.from_numpy(h.view(np.int64))
    return torch.sort(keys, stable=True).indices.numpy()


@dataclass(frozen=True, kw_only=True)
class ShuffleConfig:
    shuffle_enabled: dict[str, bool] = setting(
        default_factory=lambda: {"train": True, "test": True},
        check=lambda d: all(isinstance(v, bool) for v in d.values()),
        expected="{train: true|false, test: true|false}",
        doc="whether points are shuffled, per mode",
    )


@TRANSFORMS.register("shuffle_points")
class ShufflePoints:
    """Randomly permute the points (``SHUFFLE_ENABLED: {train: bool, test: bool}``).

    The permutation sorts the rows by a hash of their bytes seeded from the frame's generator
    (:func:`row_hash_order`), so the points a sample shares with a shorter sample of the same
    frame come out in the same order (docs/data.md).
    """

    CONFIG = ShuffleConfig

    def __init__(self, enabled: bool = True):
        self.enabled = enabled

    @classmethod
    def from_config(cls, cfg: Mapping, *, training: bool, **context) -> ShufflePoints:
        settings = read_transform_config(cls, cfg, context.get("section", "<unknown>"))
        enabled = settings.shuffle_enabled
        mode = "train" if training else "test"
        if mode not in enabled:
            raise ConfigError(f"shuffle_points.SHUFFLE_ENABLED needs a {mode!r} entry: {enabled}")
        return cls(enabled=bool(enabled[mode]))

    def __call__(self, data_dict: dict, rng: np.random.Generator) -> dict:
        if self.enabled and data_dict.get("points") is not None:
            points = data_dict["points"]
            order = row_hash_order(points, int(rng.integers(0, 2**63)))
            data_dict["points"] = np.take(points, order, axis=0)
        return data_dict


@dataclass(frozen=True, kw_only=True)
class VoxelSizeConfig:
    voxel_size: tuple[float, float, float] = setting(
        gt=0, expected="3 finite sizes > 0 [vx, vy, vz] (m)", doc="the model's voxel size, m"
    )


@TRANSFORMS.register("transform_points_to_voxels_placeholder")
class VoxelSizePlaceholder:
    """OpenPCDet's processor of dynamic-voxel models: it states the ``VOXEL_SIZE`` (m) the model
    voxelizes with and leaves the points as they are (the model reads the size through
    :func:`processor_voxel_size`)."""

    CONFIG = VoxelSizeConfig

    def __init__(self, voxel_size: Sequence[float]):
        self.voxel_size = tuple(float(v) for v in voxel_size)

    @classmethod
    def from_config(cls, cfg: Mapping, **context) -> VoxelSizePlaceholder:
        settings = read_transform_config(cls, cfg, context.get("section", "<unknown>"))
        return cls(settings.voxel_size)

    def __call__(self, data_dict: dict, rng: np.random.Generator) -> dict:
        return data_dict


def processor_voxel_size(data_cfg: Mapping) -> tuple[float, float, float] | None:
    """The ``VOXEL_SIZE`` of a ``transform_points_to_voxels_placeholder`` in ``DATA_PROCESSOR``
    (checked), or ``None`` when there is none."""
    name = "transform_points_to_voxels_placeholder"
    for item in data_cfg.get("DATA_PROCESSOR", []) or []:
        if isinstance(item, Mapping) and item.get("NAME") == name:
            return VoxelSizePlaceholder.from_config(item).voxel_size
    return None
