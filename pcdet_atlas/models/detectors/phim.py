"""PHiM (polar hierarchical Mamba, WACV'26) and PHiM+LOT: a streaming polar detector.

PolarVFE -> [LatentOccupancyTracking] -> PolarSectorMamba -> SectorFeatureBuffer ->
BaseBEVBackbone (the full-scan branch) -> CenterHead. PHiM's code is not released; this is a
reconstruction from its paper, every choice listed in docs/model_zoo.md "PHiM".

With a LOT that forecasts from frames, the input holds the ``K`` previous frames too (a time-lag
column last, ``SEQUENCE_CONFIG.SAMPLE_OFFSET [-K, 0]``): the detector runs on the current
frame's points alone, and the previous frames only give LOT their occupancy maps, made by the
same VFE and score MLP without gradients (every LOT training stage freezes the VFE, and the
score MLP trains on the current map only).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch

from pcdet_atlas.config import ConfigError, key_source
from pcdet_atlas.config_values import read_section, setting
from pcdet_atlas.models.detectors.detector3d_template import Detector3DTemplate, DetectorConfig
from pcdet_atlas.models.model_utils.motion_sampler import frame_of_points
from pcdet_atlas.models.occupancy.latent_occupancy_tracking import LOTConfig
from pcdet_atlas.registry import DETECTORS

__all__ = ["PHiM"]

#: loss terms a PHiM config may ask for (``MODEL.LOSS_TERMS``; the staged LOT training)
LOSS_TERMS = ("detection", "occupancy", "forecast")


@dataclass(frozen=True, kw_only=True)
class PHiMConfig(DetectorConfig):
    """``MODEL`` of PHiM: the detector's keys and the loss terms of a LOT training stage."""

    loss_terms: tuple[str, ...] = setting(
        ("detection",), choices=LOSS_TERMS, check=bool,
        expected=f"a non-empty subset of {list(LOSS_TERMS)}",
        doc="the loss terms that train (occupancy and forecast need MODEL.LOT)",
    )  # fmt: skip


@DETECTORS.register()
class PHiM(Detector3DTemplate):
    """Single-frame streaming detector; with a ``lot`` stage it is PHiM+LOT.

    ``loss_terms`` say what :meth:`loss` trains: ``detection`` (the CenterHead's losses, all
    stages run), ``occupancy`` (LOT's current map, stage 1) and ``forecast`` (LOT's ConvSSM,
    stage 2); the two LOT terms run only the VFE and LOT.
    """

    module_topology = [
        "vfe", "lot", "backbone_3d", "map_to_bev_module", "backbone_2d", "dense_head",
    ]  # fmt: skip
    required_stages = ("vfe", "backbone_3d", "map_to_bev_module", "backbone_2d", "dense_head")
    CONFIG = PHiMConfig

    def __init__(self, *, loss_terms: Sequence[str] = PHiMConfig.loss_terms, **kwargs):
        super().__init__(**kwargs)
        problem = loss_terms_problem(loss_terms, self.lot is not None)
        if problem:
            raise ValueError(f"PHiM: {problem}")
        self.loss_terms = tuple(loss_terms)

    @classmethod
    def from_config(cls, model_cfg: Mapping, *, num_point_features: int, **kwargs) -> PHiM:
        terms = list(cls.read_config(model_cfg).loss_terms)
        problem = loss_terms_problem(terms, "LOT" in model_cfg)
        if problem:
            source = key_source(model_cfg, "LOSS_TERMS") if "LOSS_TERMS" in model_cfg else "default"
            raise ConfigError(f"MODEL.LOSS_TERMS {terms} (from {source}): {problem}")
        if lot_history_frames(model_cfg):  # the stages read the points without the lag column
            num_point_features -= 1
        return super().from_config(
            model_cfg, loss_terms=terms, num_point_features=num_point_features, **kwargs
        )

    @classmethod
    def check_data_config(cls, model_cfg: Mapping, data_cfg: Mapping) -> None:
        """A LOT forecasting from ``K`` frames needs samples of frames ``t-K .. t``."""
        k = lot_history_frames(model_cfg)
        seq = data_cfg.get("SEQUENCE_CONFIG") or {}
        offset = list(seq.get("SAMPLE_OFFSET", [0, 0])) if seq.get("ENABLED") else [0, 0]
        if k and (offset != [-k, 0] or seq.get("ONEHOT_TIMESTAMP")):
            source = key_source(model_cfg["LOT"], "BUFFER_LENGTH")
            raise ConfigError(
                f"MODEL.LOT.BUFFER_LENGTH {k} (from {source}) forecasts from the {k} previous "
                f"frames: DATA_CONFIG.SEQUENCE_CONFIG needs ENABLED: True and SAMPLE_OFFSET "
                f"[-{k}, 0] with a time-lag column, got {dict(seq) or 'none'}"
            )
        if not k and seq.get("ENABLED"):
            raise ConfigError(
                "PHiM reads one frame: DATA_CONFIG.SEQUENCE_CONFIG is for a LOT that forecasts "
                f"from frames (MODEL.LOT.FORECAST_FROM: frames), got {dict(seq)}"
            )

    def split_frames(self, batch_dict: Mapping) -> dict:
        """A shallow copy of ``batch_dict`` whose ``points`` are the current frame's, without
        the lag column, and with ``lot_history`` (B, K, A', R'): the previous frames' LOT maps,
        oldest first (an absent frame, before the sequence start, gives an empty map)."""
        batch = dict(batch_dict)
        k = self.lot.history_frames if self.lot is not None else 0
        if not k:
            return batch
        points = batch["points"]  # (N, 1 + C + 1): batch index, features, lag (s)
        frame = frame_of_points(points[:, -1], k + 1)  # (N,) 0 = current .. K
        if bool((frame < 0).any()):
            lag = float(points[frame < 0, -1][0])
            raise ValueError(
                f"PHiM+LOT reads frames t-{k}..t (time lags 0..{0.1 * k:.1f} s), got a point "
                f"with time lag {lag} s"
            )
        columns = points[:, :-1]
        maps = []
        with torch.no_grad():
            for j in range(k, 0, -1):  # oldest first
                frame_j = self.vfe({**batch, "points": columns[frame == j]})
                maps.append(self.lot.current_map(frame_j))
        batch["lot_history"] = torch.stack(maps, dim=1)  # (B, K, A', R')
        batch["points"] = columns[frame == 0]
        return batch

    def run_stages(self, batch_dict: Mapping) -> dict:
        return super().run_stages(self.split_frames(batch_dict))

    def loss(self, batch_dict: Mapping) -> dict[str, torch.Tensor]:
        """``{'loss': total, ...}``: ``hm_loss``, ``loc_loss`` (detection), ``occupancy_loss``,
        ``forecast_loss`` (LOT), as ``loss_terms`` ask."""
        if "gt_boxes" not in batch_dict:
            raise KeyError("PHiM.loss needs batch_dict['gt_boxes'] (B, M, 8|10)")
        batch = self.vfe(self.split_frames(batch_dict))
        if self.lot is not None:
            batch = self.lot(batch)
        losses: dict[str, torch.Tensor] = {}
        for term in ("occupancy", "forecast"):
            if term in self.loss_terms:
                losses[f"{term}_loss"] = self.lot.loss(batch, term)
        if "detection" in self.loss_terms:
            for stage in self.module_list[2 if self.lot is not None else 1 :]:
                batch = stage(batch)
            head = self.dense_head.loss(batch["head_outputs"], batch["gt_boxes"])
            losses.update({k: v for k, v in head.items() if k != "loss"})
            losses["detection_loss"] = head["loss"]
        losses["loss"] = sum(
            v for k, v in losses.items() if k in {f"{t}_loss" for t in self.loss_terms}
        )
        return losses

    @torch.no_grad()
    def predict(self, batch_dict: Mapping) -> list[dict[str, torch.Tensor]]:
        """Per sample ``{'pred_boxes': (K, 7), 'pred_scores': (K,), 'pred_labels': (K,)}``."""
        out = self.run_stages(batch_dict)
        return self.dense_head.predict(out["head_outputs"])


def lot_history_frames(model_cfg: Mapping) -> int:
    """``K`` of a ``MODEL.LOT`` that forecasts from the previous frames; 0 otherwise."""
    if not model_cfg.get("LOT"):
        return 0
    lot = read_section(LOTConfig, model_cfg["LOT"], "MODEL.LOT")
    return lot.buffer_length if lot.forecast_from == "frames" else 0


def loss_terms_problem(terms: Sequence[str], has_lot: bool) -> str | None:
    """What is wrong with a list of loss terms (None: nothing)."""
    if not terms or any(t not in LOSS_TERMS for t in terms):
        return f"loss terms must be a non-empty subset of {list(LOSS_TERMS)}, got {list(terms)}"
    if not has_lot and set(terms) - {"detection"}:
        return f"loss terms {list(terms)} need a LOT stage (MODEL.LOT)"
    return None
