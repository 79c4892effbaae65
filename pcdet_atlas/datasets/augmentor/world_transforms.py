"""Global (whole-scene) augmentations: random flip, rotation about z, and scaling.

OpenPCDet's ``random_world_flip`` / ``random_world_rotation`` / ``random_world_scaling``: the same
transform is applied to every point (all frames of a multi-frame input, which share the current
vehicle frame) and every box, velocities included: the ground truth and, for two-stage models,
the proposals ``roi_boxes``. Each records what it drew (``flip_x``,
``flip_y``, ``noise_rot``, ``noise_scale``) and left-multiplies ``lidar_aug_matrix`` (4x4) so a
model can map anything from the un-augmented vehicle frame into the augmented one.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from pcdet_atlas.config import ConfigError
from pcdet_atlas.config_values import setting
from pcdet_atlas.datasets.augmentor.base import read_transform_config
from pcdet_atlas.datasets.proposal_history import PROPOSAL_KEYS
from pcdet_atlas.registry import TRANSFORMS

__all__ = ["RandomWorldFlip", "RandomWorldRotation", "RandomWorldScaling"]


def _box_arrays(data_dict: dict) -> list[np.ndarray]:
    """The box arrays a world transform moves: ``gt_boxes`` and, when present, the first 9
    columns (box and velocity; not score and label) of the proposals ``roi_boxes`` and
    ``roi_history``."""
    arrays = [data_dict["gt_boxes"]]
    for key in PROPOSAL_KEYS:
        if data_dict.get(key) is not None:
            arrays.append(data_dict[key][:, :9])  # a view: changed in place
    return arrays


def _compose(data_dict: dict, linear_3x3: np.ndarray) -> None:
    mat = np.eye(4)
    mat[:3, :3] = linear_3x3
    data_dict["lidar_aug_matrix"] = mat @ data_dict.get("lidar_aug_matrix", np.eye(4))


def _range_pair(value, name: str) -> tuple[float, float]:
    if isinstance(value, (int, float)):
        return -abs(float(value)), abs(float(value))
    if not isinstance(value, Sequence) or len(value) != 2:
        raise ConfigError(f"{name} must be a number or a [low, high] pair, got {value!r}")
    low, high = float(value[0]), float(value[1])
    if low > high:
        raise ConfigError(f"{name} must be [low, high] with low <= high, got {value!r}")
    return low, high


@dataclass(frozen=True, kw_only=True)
class FlipConfig:
    along_axis_list: tuple[str, ...] = setting(
        ("x", "y"), choices=("x", "y"), doc="axes mirrored across, each with probability 1/2"
    )


@dataclass(frozen=True, kw_only=True)
class RotationConfig:
    world_rot_angle: float | tuple[float, float] = setting(
        expected="a number a (for [-a, a]) or a [low, high] pair, rad",
        doc="rotation range about z, rad",
    )


@dataclass(frozen=True, kw_only=True)
class ScalingConfig:
    world_scale_range: tuple[float, float] = setting(
        gt=0,
        check=lambda r: r[0] <= r[1],
        expected="a [low, high] pair of scale factors with 0 < low <= high",
        doc="scale factor range",
    )


@TRANSFORMS.register("random_world_flip")
class RandomWorldFlip:
    """Mirror the scene across the x axis (y -> -y) and/or the y axis (x -> -x), each with
    probability 1/2, in ``along_axis_list`` order."""

    CONFIG = FlipConfig

    def __init__(self, along_axis_list: Sequence[str] = FlipConfig.along_axis_list):
        for axis in along_axis_list:
            if axis not in ("x", "y"):
                raise ConfigError(f"ALONG_AXIS_LIST entries must be 'x' or 'y', got {axis!r}")
        self.along_axis_list = list(along_axis_list)

    @classmethod
    def from_config(cls, cfg: Mapping, **context) -> RandomWorldFlip:
        settings = read_transform_config(cls, cfg, context.get("section", "<unknown>"))
        return cls(along_axis_list=list(settings.along_axis_list))

    def __call__(self, data_dict: dict, rng: np.random.Generator) -> dict:
        points = data_dict["points"]
        for axis in self.along_axis_list:
            enable = bool(rng.random() < 0.5)
            data_dict[f"flip_{axis}"] = enable
            if not enable:
                continue
            for boxes in _box_arrays(data_dict):
                if axis == "x":  # mirror across the x axis
                    boxes[:, 1] = -boxes[:, 1]
                    boxes[:, 6] = -boxes[:, 6]
                    if boxes.shape[1] > 7:
                        boxes[:, 8] = -boxes[:, 8]
                else:  # mirror across the y axis
                    boxes[:, 0] = -boxes[:, 0]
                    boxes[:, 6] = -(boxes[:, 6] + np.pi)
                    if boxes.shape[1] > 7:
                        boxes[:, 7] = -boxes[:, 7]
            if axis == "x":
                points[:, 1] = -points[:, 1]
                _compose(data_dict, np.diag([1.0, -1.0, 1.0]))
            else:
                points[:, 0] = -points[:, 0]
                _compose(data_dict, np.diag([-1.0, 1.0, 1.0]))
        return data_dict


@TRANSFORMS.register("random_world_rotation")
class RandomWorldRotation:
    """Rotate the scene about the vehicle z axis by an angle ~ U(rot_range) (radians, CCW)."""

    CONFIG = RotationConfig

    def __init__(self, rot_range: tuple[float, float] = (-np.pi / 4, np.pi / 4)):
        self.rot_range = _range_pair(rot_range, "WORLD_ROT_ANGLE")

    @classmethod
    def from_config(cls, cfg: Mapping, **context) -> RandomWorldRotation:
        settings = read_transform_config(cls, cfg, context.get("section", "<unknown>"))
        return cls(rot_range=_range_pair(settings.world_rot_angle, "WORLD_ROT_ANGLE"))

    def __call__(self, data_dict: dict, rng: np.random.Generator) -> dict:
        angle = float(rng.uniform(*self.rot_range))
        cos, sin = np.cos(angle), np.sin(angle)
        rot = np.array([[cos, -sin], [sin, cos]])  # column-vector convention, CCW
        points = data_dict["points"]
        # column-wise, float64, reusing two buffers (much faster than an (N, 2) matmul):
        # x' = cos * x - sin * y, y' = sin * x + cos * y
        x, y = points[:, 0].astype(np.float64), points[:, 1].astype(np.float64)
        a, b = np.multiply(x, cos), np.multiply(y, sin)
        points[:, 0] = np.subtract(a, b, out=a)
        np.multiply(x, sin, out=a)
        np.multiply(y, cos, out=b)
        points[:, 1] = np.add(a, b, out=a)
        for boxes in _box_arrays(data_dict):
            boxes[:, 0:2] = boxes[:, 0:2] @ rot.T
            boxes[:, 6] += angle
            if boxes.shape[1] > 7:
                boxes[:, 7:9] = boxes[:, 7:9] @ rot.T
        data_dict["noise_rot"] = angle
        rot3 = np.eye(3)
        rot3[:2, :2] = rot
        _compose(data_dict, rot3)
        return data_dict


@TRANSFORMS.register("random_world_scaling")
class RandomWorldScaling:
    """Scale coordinates, box sizes and velocities by a factor ~ U(scale_range)."""

    CONFIG = ScalingConfig

    def __init__(self, scale_range: tuple[float, float] = (0.95, 1.05)):
        if isinstance(scale_range, (int, float)):  # no symmetric reading, unlike an angle
            raise ConfigError(
                "WORLD_SCALE_RANGE must be a [low, high] pair of scale factors, got "
                f"{scale_range!r}"
            )
        low, high = _range_pair(scale_range, "WORLD_SCALE_RANGE")
        if low <= 0:
            raise ConfigError(f"WORLD_SCALE_RANGE must be positive, got {scale_range!r}")
        self.scale_range = (low, high)

    @classmethod
    def from_config(cls, cfg: Mapping, **context) -> RandomWorldScaling:
        settings = read_transform_config(cls, cfg, context.get("section", "<unknown>"))
        return cls(scale_range=settings.world_scale_range)

    def __call__(self, data_dict: dict, rng: np.random.Generator) -> dict:
        scale = float(rng.uniform(*self.scale_range))
        points = data_dict["points"]
        for column in range(3):  # 1-D strided loops: far faster than an (N, 3) block op
            points[:, column] *= np.float32(scale)
        for boxes in _box_arrays(data_dict):
            boxes[:, 0:6] *= scale
            if boxes.shape[1] > 7:
                boxes[:, 7:] *= scale
        data_dict["noise_scale"] = scale
        _compose(data_dict, np.eye(3) * scale)
        return data_dict
