"""Pure-torch detectors and their stages (no spconv, no compiled ops).

Importing this package registers every stage in ``MODEL_STAGES`` and every detector in
``DETECTORS``. Build a model from a full config with :func:`build_network_from_config`, or from
its parts with :func:`build_network`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from pcdet_atlas.config import require_keys, to_plain
from pcdet_atlas.models import (  # noqa: F401
    backbones_2d,
    backbones_3d,
    dense_heads,
    detectors,
    map_to_bev,
    occupancy,
    roi_heads,
    vfe,
)
from pcdet_atlas.models.batch import load_data_to_device
from pcdet_atlas.models.detectors import Detector3DTemplate
from pcdet_atlas.registry import DETECTORS

__all__ = [
    "build_network",
    "build_network_from_config",
    "num_point_features_of",
    "load_data_to_device",
]


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
    from pcdet_atlas.datasets.point_features import PointFeatureEncoder

    require_keys(data_cfg, ["POINT_FEATURE_ENCODING"], "DATA_CONFIG")
    return PointFeatureEncoder.from_config(data_cfg["POINT_FEATURE_ENCODING"]).num_point_features


def build_network_from_config(cfg: Mapping) -> Detector3DTemplate:
    """Build the model of a full config (``CLASS_NAMES``, ``DATA_CONFIG``, ``MODEL``)."""
    require_keys(cfg, ["CLASS_NAMES", "DATA_CONFIG", "MODEL"], "config")
    require_keys(cfg["DATA_CONFIG"], ["POINT_CLOUD_RANGE"], "DATA_CONFIG")
    from pcdet_atlas.datasets.augmentor.processors import processor_voxel_size

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
