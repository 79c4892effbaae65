"""Second stages of two-stage detectors (registered in ``MODEL_STAGES``)."""

from pcdet_atlas.models.roi_heads.msf_head import MSFHead
from pcdet_atlas.models.roi_heads.ptt_head import PTTHead

__all__ = ["MSFHead", "PTTHead"]
