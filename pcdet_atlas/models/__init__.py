"""Pure-torch detectors and their stages (no spconv, no compiled ops).

Importing this package registers every stage in ``MODEL_STAGES`` and every detector in
``DETECTORS``. Build a model from a full config with :func:`build_network_from_config`, or from
its parts with :func:`build_network`.
"""

from __future__ import annotations

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
from pcdet_atlas.models.build import build_network, build_network_from_config, num_point_features_of

__all__ = [
    "build_network",
    "build_network_from_config",
    "num_point_features_of",
    "load_data_to_device",
]
