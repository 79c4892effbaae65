"""Procedural synthetic Waymo-format dataset (docs/synthetic.md): the embedded default dataset.

``create_synthetic_waymo(root, {'train': N, 'val': M}, {'train': F, 'val': G}, seed=0)`` writes
OpenPCDet's processed Waymo layout from ray-cast procedural street scenes. See
``docs/synthetic.md``.
"""

from pcdet_atlas.datasets.synthetic.generator import (
    DEFAULT_FRAMES_PER_SEQUENCE,
    DEFAULT_NUM_SEQUENCES,
    GENERATOR_VERSION,
    META_FILE,
    SyntheticDatasetError,
    create_synthetic_waymo,
    format_summary,
    generate_frame,
    sequence_name,
)
from pcdet_atlas.datasets.synthetic.scene import SyntheticScene

__all__ = [
    "create_synthetic_waymo",
    "format_summary",
    "SyntheticScene",
    "SyntheticDatasetError",
    "generate_frame",
    "sequence_name",
    "DEFAULT_NUM_SEQUENCES",
    "DEFAULT_FRAMES_PER_SEQUENCE",
    "GENERATOR_VERSION",
    "META_FILE",
]
