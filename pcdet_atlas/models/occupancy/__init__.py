"""Occupancy memories between the VFE and the backbone (stage ``lot``)."""

from pcdet_atlas.models.occupancy.latent_occupancy_tracking import LatentOccupancyTracking

__all__ = ["LatentOccupancyTracking"]
