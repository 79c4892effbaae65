"""Building a detector from its config: ``DETECTORS[MODEL.NAME].from_config`` with what the data
config says of the input (point columns, range, voxel size).

A module of its own, below the detectors: a two-stage detector builds its RPN with it while the
package's ``__init__`` is still registering the detectors (the registry is read at call time).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from pcdet_atlas.config import to_plain
from pcdet_atlas.config_values import config_value, read_section, setting
from pcdet_atlas.datasets.augmentor.processors import processor_voxel_size
from pcdet_atlas.datasets.point_features import PointFeatureEncoder
from pcdet_atlas.models.detectors.detector3d_template import Detector3DTemplate
from pcdet_atlas.registry import DETECTORS

__all__ = ["build_network", "build_network_from_config", "num_point_features_of"]


def _is_section(value: Any) -> bool:
    return isinstance(value, Mapping)


@dataclass(frozen=True, kw_only=True)
class _NetworkSections:
    """What building a detector reads of a full config (its other sections have their own
    readers)."""

    class_names: tuple[str, ...] = setting(
        check=bool, expected="a non-empty list of class names", doc="index i is label i + 1"
    )
    data_config: Any = setting(check=_is_section, expected="a section", doc="the dataset's")
    model: Any = setting(check=_is_section, expected="a section", doc="the detector's")


@dataclass(frozen=True, kw_only=True)
class _DataInputs:
    """What the detector is told of ``DATA_CONFIG`` (the dataset reads and checks the rest)."""

    point_cloud_range: tuple[float, float, float, float, float, float] = setting(
        doc="[x_min, y_min, z_min, x_max, y_max, z_max], m"
    )
    point_feature_encoding: Any = setting(
        check=_is_section, expected="a section", doc="the point columns"
    )


def build_network(
    model_cfg: Mapping,
    *,
    class_names: Sequence[str],
    point_cloud_range: Sequence[float],
    num_point_features: int,
    voxel_size: Sequence[float] | None = None,
) -> Detector3DTemplate:
    """The detector ``DETECTORS[model_cfg.NAME]`` built from a ``MODEL`` section (``voxel_size``:
    the data config's, for a VFE whose section does not state one). Its ``build_signature``
    records these arguments."""
    name = config_value(model_cfg, "NAME", str, "MODEL", expected="a registered detector name")
    detector = DETECTORS.get(name).from_config(
        model_cfg,
        class_names=class_names,
        point_cloud_range=point_cloud_range,
        num_point_features=num_point_features,
        voxel_size=voxel_size,
    )
    # what the model computes besides its weights (a PredictionStore's fingerprint)
    detector.build_signature = to_plain({
        "MODEL": model_cfg, "class_names": list(class_names),
        "point_cloud_range": [float(v) for v in point_cloud_range],
        "num_point_features": int(num_point_features),
        "voxel_size": None if voxel_size is None else [float(v) for v in voxel_size],
    })  # fmt: skip
    return detector


def num_point_features_of(data_cfg: Mapping) -> int:
    """Point columns the dataset delivers after the batch index (its ``POINT_FEATURE_ENCODING``:
    5 for ``x, y, z, intensity, elongation``, 6 with the multi-frame ``timestamp``)."""
    encoding = config_value(
        data_cfg, "POINT_FEATURE_ENCODING", lambda v: v, "DATA_CONFIG", valid=_is_section,
        expected="a section (the point columns)",
    )  # fmt: skip
    return PointFeatureEncoder.from_config(encoding).num_point_features


def build_network_from_config(cfg: Mapping) -> Detector3DTemplate:
    """Build the model of a full config (``CLASS_NAMES``, ``DATA_CONFIG``, ``MODEL``)."""
    sections = read_section(_NetworkSections, cfg, ignore=[k for k in cfg if not _builds(k)])
    model_cfg, data_cfg = sections.model, sections.data_config
    data = read_section(
        _DataInputs, data_cfg, "DATA_CONFIG", ignore=[k for k in data_cfg if not _builds(k)]
    )
    name = config_value(model_cfg, "NAME", str, "MODEL", expected="a registered detector name")
    check_data = getattr(DETECTORS.get(name), "check_data_config", None)
    if check_data is not None:  # what the detector needs of its samples
        check_data(model_cfg, data_cfg)
    return build_network(
        model_cfg,
        class_names=cfg["CLASS_NAMES"],
        point_cloud_range=data.point_cloud_range,
        num_point_features=num_point_features_of(data_cfg),
        voxel_size=processor_voxel_size(data_cfg),
    )


def _builds(key: str) -> bool:
    """Whether building the detector reads the config key ``key`` (a top-level or
    ``DATA_CONFIG`` key)."""
    return key in ("CLASS_NAMES", "DATA_CONFIG", "MODEL", "POINT_CLOUD_RANGE",
                   "POINT_FEATURE_ENCODING")  # fmt: skip
