"""Point feature selection (OpenPCDet's ``POINT_FEATURE_ENCODING``)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from pcdet_atlas.config import ConfigError
from pcdet_atlas.config_values import read_section, setting

__all__ = ["PointFeatureConfig", "PointFeatureEncoder"]


@dataclass(frozen=True, kw_only=True)
class PointFeatureConfig:
    """``DATA_CONFIG.POINT_FEATURE_ENCODING`` (OpenPCDet's lower-case keys)."""

    encoding_type: str = setting(
        "absolute_coordinates_encoding",
        key="encoding_type",
        choices=("absolute_coordinates_encoding",),
        doc="only absolute_coordinates_encoding",
    )
    used_feature_list: tuple[str, ...] = setting(
        key="used_feature_list", doc="the columns the model reads, x, y, z first"
    )
    src_feature_list: tuple[str, ...] = setting(
        key="src_feature_list", doc="the columns the dataset produces, x, y, z first"
    )


class PointFeatureEncoder:
    """``absolute_coordinates_encoding``: keep ``x, y, z`` then the other ``used_feature_list``
    columns, looked up by name in ``src_feature_list`` (the columns the dataset produces)."""

    CONFIG = PointFeatureConfig

    def __init__(self, used_feature_list: Sequence[str], src_feature_list: Sequence[str]):
        self.used_feature_list = list(used_feature_list)
        self.src_feature_list = list(src_feature_list)
        if self.src_feature_list[:3] != ["x", "y", "z"]:
            raise ConfigError(f"src_feature_list must start with x, y, z: {src_feature_list}")
        missing = [f for f in self.used_feature_list if f not in self.src_feature_list]
        if missing:
            raise ConfigError(
                f"POINT_FEATURE_ENCODING.used_feature_list has {missing}, which are not in "
                f"src_feature_list {self.src_feature_list}"
            )
        self._columns = [0, 1, 2] + [
            self.src_feature_list.index(f)
            for f in self.used_feature_list
            if f not in ("x", "y", "z")
        ]

    @classmethod
    def from_config(cls, cfg: Mapping) -> PointFeatureEncoder:
        settings = read_section(cls.CONFIG, cfg, "DATA_CONFIG.POINT_FEATURE_ENCODING")
        return cls(list(settings.used_feature_list), list(settings.src_feature_list))

    @property
    def num_point_features(self) -> int:
        """Columns of the encoded points."""
        return len(self._columns)

    def forward(self, data_dict: dict) -> dict:
        """``points`` ``(N, len(src))`` -> ``(N, num_point_features)`` float32."""
        points = data_dict["points"]
        if points.shape[1] != len(self.src_feature_list):
            raise ConfigError(
                f"points have {points.shape[1]} columns but POINT_FEATURE_ENCODING."
                f"src_feature_list names {len(self.src_feature_list)}: {self.src_feature_list}"
            )
        if self._columns != list(range(points.shape[1])):
            points = points[:, self._columns]
        data_dict["points"] = np.ascontiguousarray(points, dtype=np.float32)
        data_dict["use_lead_xyz"] = True
        return data_dict
