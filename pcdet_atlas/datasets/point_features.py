"""Point feature selection (OpenPCDet's ``POINT_FEATURE_ENCODING``)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from pcdet_atlas.config import ConfigError, check_known_keys

__all__ = ["PointFeatureEncoder"]


class PointFeatureEncoder:
    """``absolute_coordinates_encoding``: keep ``x, y, z`` then the other ``used_feature_list``
    columns, looked up by name in ``src_feature_list`` (the columns the dataset produces)."""

    CONFIG_KEYS = ("encoding_type", "used_feature_list", "src_feature_list")

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
        check_known_keys(cfg, cls.CONFIG_KEYS, "DATA_CONFIG.POINT_FEATURE_ENCODING")
        encoding = cfg.get("encoding_type", "absolute_coordinates_encoding")
        if encoding != "absolute_coordinates_encoding":
            raise ConfigError(
                f"POINT_FEATURE_ENCODING.encoding_type {encoding!r} is not supported "
                f"(only 'absolute_coordinates_encoding')"
            )
        return cls(cfg["used_feature_list"], cfg["src_feature_list"])

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
