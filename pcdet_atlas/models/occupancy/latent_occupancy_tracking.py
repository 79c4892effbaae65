"""Latent Occupancy Tracking (LOT), the ATLAS paper's defence on PHiM (its appendix "LOT
Implementation Details"; docs/model_zoo.md "PHiM+LOT").

Between the VFE and the backbone: a score MLP (Linear, GELU, Linear) gives every polar voxel an
occupancy probability; the scores fill a dense ``(z, azimuth, range)`` grid, pooled to
occupancy cells (``pooling``: the mean score of each cell's voxels, or the paper's masked mean
over height average-pooled over the cell's bins, in which empty bins count as zero occupancy):
the frame's occupancy map. A :class:`~pcdet_atlas.models.ssm.ConvSSM` forecasts the current map
from ``K`` earlier maps (``forecast_from``):

- ``frames``: the maps of the ``K`` previous frames, each made by the same VFE and score MLP
  from that frame's points, which the data pipeline has already moved into the current vehicle
  frame by ego motion (``SEQUENCE_CONFIG.SAMPLE_OFFSET [-K, 0]``), so a cell of every map is the
  same place in the world. The forecast needs nothing of the current frame: a streaming
  detector has it before the frame's first sector arrives.
- ``sectors``: the ``K`` sector maps streamed before each sector of the same frame, laid on the
  same relative grid with nothing aligning them (the first design; it learns little beyond a
  range prior, docs/model_zoo.md "PHiM+LOT").

``X_final = 0.5 X_current + 0.5 X_forecast``; a voxel's confidence is the value of the
confidence map at its cell, and voxels below ``filter_thresh`` are removed (with their points)
before the detector sees them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from pcdet_atlas.config_values import fields_of, setting
from pcdet_atlas.models.model_utils.centernet_utils import (
    focal_loss_centernet,
    focal_loss_centernet_prob,
)
from pcdet_atlas.models.model_utils.polar_grid import PolarGrid
from pcdet_atlas.models.occupancy.occupancy_targets import occupancy_target
from pcdet_atlas.models.ssm import ConvSSM
from pcdet_atlas.models.stage_config import StageConfig, read_stage
from pcdet_atlas.registry import MODEL_STAGES

__all__ = ["LOTConfig", "LatentOccupancyTracking"]

CONFIDENCE_MAPS = ("final", "forecast")
POOLINGS = ("masked", "average")
FORECAST_SOURCES = ("frames", "sectors")


@dataclass(frozen=True, kw_only=True)
class LOTConfig(StageConfig):
    """``MODEL.LOT``."""

    hidden_channels: int = setting(32, ge=1, doc="width of the score MLP")
    pool_size: tuple[int, int] = setting(
        (2, 2), ge=1, doc="(azimuth, range) grid cells per occupancy cell"
    )
    buffer_length: int = setting(4, ge=1, doc="K, the earlier maps the ConvSSM reads")
    state_channels: int = setting(16, ge=1, doc="ConvSSM state width")
    kernel_size: int = setting(3, ge=1, doc="ConvSSM kernel size")
    filter_thresh: float = setting(0.1, doc="voxels whose confidence is below it are removed")
    confidence_map: str = setting("final", choices=CONFIDENCE_MAPS, doc="final or forecast")
    gt_min_sigma: float = setting(0.5, gt=0, doc="smallest sigma of the occupancy target, cells")
    forecast_from: str = setting("frames", choices=FORECAST_SOURCES, doc="frames or sectors")
    pooling: str = setting(
        "masked", choices=POOLINGS,
        doc="masked: an occupancy cell is the mean score of its voxels; average: the paper's "
        "average pooling of the height-collapsed map (empty bins count as 0)",
    )  # fmt: skip


@MODEL_STAGES.register()
class LatentOccupancyTracking(nn.Module):
    """Reads ``voxel_features`` (V, C), ``voxel_coords`` (V, 4) ``[b, z, a, r]``,
    ``voxel_point_idx``, ``voxel_point_xy``, ``batch_size`` and, forecasting from frames,
    ``lot_history`` (B, K, A', R'): the previous frames' :meth:`current_map`, oldest first (the
    detector makes them); writes the kept voxels (and points) under the same keys, and
    ``lot_current``, ``lot_forecast_logits``, ``lot_final`` (B, A', R') maps,
    ``lot_voxel_confidence`` (V,) and ``lot_keep`` (V,) of the input voxels."""

    CONFIG = LOTConfig

    def __init__(
        self,
        *,
        input_channels: int,
        grid: PolarGrid,
        hidden_channels: int = LOTConfig.hidden_channels,
        pool_size: tuple[int, int] = LOTConfig.pool_size,
        buffer_length: int = LOTConfig.buffer_length,
        state_channels: int = LOTConfig.state_channels,
        kernel_size: int = LOTConfig.kernel_size,
        filter_thresh: float = LOTConfig.filter_thresh,
        confidence_map: str = LOTConfig.confidence_map,
        gt_min_sigma: float = LOTConfig.gt_min_sigma,
        forecast_from: str = LOTConfig.forecast_from,
        pooling: str = LOTConfig.pooling,
    ):
        """
        Args:
            input_channels: VFE feature width.
            grid: the VFE's polar grid.
            pool_size: ``(azimuth, range)`` grid cells per occupancy cell; a sector's azimuth
                bins must be a multiple of the first.
            buffer_length: K, the earlier maps the ConvSSM reads: previous frames or sectors.
            filter_thresh: voxels whose confidence is below it are removed.
            confidence_map: ``final`` (0.5 current + 0.5 forecast) or ``forecast``.
            gt_min_sigma: smallest Gaussian sigma of the occupancy target, in cells.
            forecast_from: ``frames`` or ``sectors`` (module docstring).
            pooling: ``masked`` (the mean score of the voxels in each occupancy cell) or
                ``average`` (the paper's average pooling of the height-collapsed map, in which
                empty bins count as zero, so a sparse object's cell scores below dense ground).
        """
        super().__init__()
        pa, pr = (int(v) for v in pool_size)
        if grid.sector_bins % pa or grid.grid_size[0] % pr:
            raise ValueError(
                f"LOT: POOL_SIZE {list(pool_size)} must divide the {grid.sector_bins} azimuth "
                f"bins of a sector and the {grid.grid_size[0]} range bins"
            )
        if confidence_map not in CONFIDENCE_MAPS:
            raise ValueError(
                f"LOT: CONFIDENCE_MAP must be one of {CONFIDENCE_MAPS}, got {confidence_map!r}"
            )
        if buffer_length < 1:
            raise ValueError(f"LOT: BUFFER_LENGTH must be >= 1, got {buffer_length}")
        if forecast_from not in FORECAST_SOURCES:
            raise ValueError(
                f"LOT: FORECAST_FROM must be one of {FORECAST_SOURCES}, got {forecast_from!r}"
            )
        if pooling not in POOLINGS:
            raise ValueError(f"LOT: POOLING must be one of {POOLINGS}, got {pooling!r}")
        self.forecast_from = forecast_from
        self.pooling = pooling
        self.grid = grid
        self.pool_size = (pa, pr)
        self.buffer_length = int(buffer_length)
        self.filter_thresh = float(filter_thresh)
        self.confidence_map = confidence_map
        self.gt_min_sigma = float(gt_min_sigma)
        self.score_mlp = nn.Sequential(
            nn.Linear(input_channels, hidden_channels), nn.GELU(), nn.Linear(hidden_channels, 1)
        )
        self.convssm = ConvSSM(1, state_channels, kernel_size)

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> LatentOccupancyTracking:
        settings = read_stage(cls, cfg, "MODEL.LOT")
        grid = model_info.get("polar_grid")
        if grid is None:
            raise ValueError("LOT needs a polar VFE (MODEL.VFE.NAME: PolarVFE)")
        kwargs = {f: v for f, v in fields_of(settings).items() if f != "name"}
        return cls(input_channels=model_info["num_point_features"], grid=grid, **kwargs)

    @property
    def history_frames(self) -> int:
        """Previous frames whose maps the forecast reads (0 when it reads sectors)."""
        return self.buffer_length if self.forecast_from == "frames" else 0

    def current_map(self, batch_dict: Mapping) -> torch.Tensor:
        """(B, A', R') occupancy map of the voxels in ``batch_dict`` from the score MLP's
        probabilities: per occupancy cell, the mean over its voxels (``pooling`` ``masked``), or
        the average pooling of their masked mean over height (``average``)."""
        feats, coords = batch_dict["voxel_features"], batch_dict["voxel_coords"]
        B = int(batch_dict["batch_size"])
        nr, na, nz = self.grid.grid_size
        score = torch.sigmoid(self.score_mlp(feats)).squeeze(1)  # (V,)
        b, z, a, r = coords.unbind(1)
        flat = ((b * nz + z) * na + a) * nr + r
        occ = score.new_zeros(B * nz * na * nr).index_put((flat,), score).view(B, nz, na, nr)
        valid = score.new_zeros(B * nz * na * nr).index_put((flat,), torch.ones_like(score))
        valid = valid.view(B, nz, na, nr)
        if self.pooling == "average":
            occ_2d = occ.sum(1) / valid.sum(1).clamp(min=1)  # (B, na, nr) masked mean over height
            return F.avg_pool2d(occ_2d[:, None], self.pool_size)[:, 0]  # (B, A', R')
        # masked: the scores' and the voxels' means over each cell's bins; their ratio is the
        # mean score of its voxels (a non-empty cell's voxel mean is at least 1 / its bins)
        means = F.avg_pool2d(torch.stack([occ.sum(1), valid.sum(1)], 1), self.pool_size)
        bins = self.pool_size[0] * self.pool_size[1]
        return means[:, 0] / means[:, 1].clamp(min=1.0 / bins)  # (B, A', R')

    def forecast_logits(self, batch_dict: Mapping, current: torch.Tensor) -> torch.Tensor:
        """(B, A', R') forecast logits of the current map (module docstring)."""
        B, A, R = current.shape
        K = self.buffer_length
        if self.forecast_from == "frames":
            history = batch_dict.get("lot_history")
            if history is None or tuple(history.shape) != (B, K, A, R):
                got = None if history is None else tuple(history.shape)
                raise ValueError(
                    f"LOT forecasting from frames needs batch_dict['lot_history'] of shape "
                    f"{(B, K, A, R)} (the previous frames' maps), got {got}"
                )
            return self.convssm(history[:, :, None]).view(B, A, R)  # (B, A', R')
        S = self.grid.num_sectors
        sectors = current.view(B, S, A // S, R)  # (B, S, A/S, R') in streaming order
        # the buffer of each sector: the K sectors streamed before it, empty before the first
        padded = torch.cat([sectors.new_zeros(B, K, A // S, R), sectors], dim=1)
        history = torch.stack([padded[:, k : k + S] for k in range(K)], dim=2)  # (B, S, K, ...)
        logits = self.convssm(history.reshape(B * S, K, 1, A // S, R))  # (B*S, 1, A/S, R')
        return logits.view(B, A, R)

    def occupancy_maps(self, batch_dict: Mapping) -> dict[str, torch.Tensor]:
        """``lot_current``, ``lot_forecast_logits``, ``lot_final`` (B, A', R') and the
        confidence of every voxel ``lot_voxel_confidence`` (V,)."""
        current = self.current_map(batch_dict)
        logits = self.forecast_logits(batch_dict, current)
        final = 0.5 * current + 0.5 * torch.sigmoid(logits)
        conf_map = final if self.confidence_map == "final" else torch.sigmoid(logits)
        b, _, a, r = batch_dict["voxel_coords"].unbind(1)
        pa, pr = self.pool_size
        confidence = conf_map[b, a // pa, r // pr]  # (V,)
        return {
            "lot_current": current, "lot_forecast_logits": logits, "lot_final": final,
            "lot_voxel_confidence": confidence,
        }  # fmt: skip

    def forward(self, batch_dict: dict) -> dict:
        maps = self.occupancy_maps(batch_dict)
        batch_dict.update(maps)
        keep = maps["lot_voxel_confidence"] >= self.filter_thresh  # (V,)
        batch_dict["lot_keep"] = keep
        idx = batch_dict["voxel_point_idx"]
        new_index = torch.cumsum(keep, 0) - 1  # (V,) position among the kept voxels
        point_keep = keep.index_select(0, idx)
        batch_dict["voxel_features"] = batch_dict["voxel_features"][keep]
        batch_dict["voxel_coords"] = batch_dict["voxel_coords"][keep]
        batch_dict["voxel_point_idx"] = new_index.index_select(0, idx)[point_keep]
        batch_dict["voxel_point_xy"] = batch_dict["voxel_point_xy"][point_keep]
        return batch_dict

    def loss(self, batch_dict: Mapping, term: str) -> torch.Tensor:
        """CenterNet focal loss of the current map (``term`` ``occupancy``, stage 1) or of the
        forecast (``forecast``, stage 2) against :func:`occupancy_target` of ``gt_boxes``."""
        target = occupancy_target(
            batch_dict["gt_boxes"], self.grid, self.pool_size, self.gt_min_sigma
        )  # (B, A', R')
        if term == "occupancy":
            return focal_loss_centernet_prob(batch_dict["lot_current"], target)
        if term == "forecast":
            return focal_loss_centernet(batch_dict["lot_forecast_logits"], target)
        raise ValueError(f"LOT.loss: term must be 'occupancy' or 'forecast', got {term!r}")
