"""Building a detector from its config: ``DETECTORS[MODEL.NAME].from_config`` with what the data
config says of the input (point columns, range, voxel size).

A module of its own, below the detectors: a two-stage detector builds its RPN with it while the
package's ``__init__`` is still registering the detectors (the registry is read at call time).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from pcdet_atlas.config import require_keys, to_plain
from pcdet_atlas.datasets.augmentor.processors import processor_voxel_size
from pcdet_atlas.datasets.point_features import PointFeatureEncoder
from pcdet_atlas.models.detectors.detector3d_template import Detector3DTemplate
from pcdet_atlas.registry import DETECTORS

__all__ = ["build_network", "build_network_from_config", "num_point_features_of"]


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
    require_keys(model_cfg, ["NAME"], "MODEL")
    detector = DETECTORS.get(model_cfg["NAME"]).from_config(
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
    require_keys(data_cfg, ["POINT_FEATURE_ENCODING"], "DATA_CONFIG")
    return PointFeatureEncoder.from_config(data_cfg["POINT_FEATURE_ENCODING"]).num_point_features


def build_network_from_config(cfg: Mapping) -> Detector3DTemplate:
    """Build the model of a full config (``CLASS_NAMES``, ``DATA_CONFIG``, ``MODEL``)."""
    require_keys(cfg, ["CLASS_NAMES", "DATA_CONFIG", "MODEL"], "config")
    require_keys(cfg["DATA_CONFIG"], ["POINT_CLOUD_RANGE"], "DATA_CONFIG")
    require_keys(cfg["MODEL"], ["NAME"], "MODEL")
    check_data = getattr(DETECTORS.get(cfg["MODEL"]["NAME"]), "check_data_config", None)
    if check_data is not None:  # what the detector needs of its samples
        check_data(cfg["MODEL"], cfg["DATA_CONFIG"])
    return build_network(
        cfg["MODEL"],
        class_names=cfg["CLASS_NAMES"],
        point_cloud_range=cfg["DATA_CONFIG"]["POINT_CLOUD_RANGE"],
        num_point_features=num_point_features_of(cfg["DATA_CONFIG"]),
        voxel_size=processor_voxel_size(cfg["DATA_CONFIG"]),
    )
