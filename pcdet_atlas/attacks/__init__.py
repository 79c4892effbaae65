"""The ATLAS attack engine: LiDAR model, raycaster, injection, removal, schedule."""

from pcdet_atlas.attacks.lidar_model import LidarModel

__all__ = ["LidarModel"]
