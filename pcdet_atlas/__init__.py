"""pcdet_atlas: the Adversarial Temporal LiDAR Attack Suite, a pure-PyTorch OpenPCDet plugin."""

from pcdet_atlas.version import __version__

__all__ = ["__version__"]
