"""Detectors: stage containers with ``loss(batch)`` and ``predict(batch)``."""

from pcdet_atlas.models.detectors.centerformer import CenterFormer
from pcdet_atlas.models.detectors.centerpoint import CenterPoint
from pcdet_atlas.models.detectors.detector3d_template import Detector3DTemplate
from pcdet_atlas.models.detectors.msf import MSF
from pcdet_atlas.models.detectors.phim import PHiM
from pcdet_atlas.models.detectors.ptt import PTT
from pcdet_atlas.models.detectors.two_stage import TwoStageDetector

__all__ = [
    "CenterFormer",
    "CenterPoint",
    "Detector3DTemplate",
    "MSF",
    "PHiM",
    "PTT",
    "TwoStageDetector",
]
