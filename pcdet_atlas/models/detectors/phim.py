"""PHiM (polar hierarchical Mamba, WACV'26) and PHiM+LOT: a streaming polar detector.

PolarVFE -> [LatentOccupancyTracking] -> PolarSectorMamba -> SectorFeatureBuffer ->
BaseBEVBackbone (the full-scan branch) -> CenterHead. PHiM's code is not released; this is a
reconstruction from its paper, every choice listed in docs/model_zoo.md "PHiM".
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch

from pcdet_atlas.config import ConfigError, key_source
from pcdet_atlas.models.detectors.detector3d_template import Detector3DTemplate
from pcdet_atlas.registry import DETECTORS

__all__ = ["PHiM"]

#: loss terms a PHiM config may ask for (``MODEL.LOSS_TERMS``; the staged LOT training)
LOSS_TERMS = ("detection", "occupancy", "forecast")


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
    EXTRA_MODEL_KEYS = ("LOSS_TERMS",)

    def __init__(self, *, loss_terms: Sequence[str] = ("detection",), **kwargs):
        super().__init__(**kwargs)
        problem = loss_terms_problem(loss_terms, self.lot is not None)
        if problem:
            raise ValueError(f"PHiM: {problem}")
        self.loss_terms = tuple(loss_terms)

    @classmethod
    def from_config(cls, model_cfg: Mapping, **kwargs) -> PHiM:
        terms = list(model_cfg.get("LOSS_TERMS", ["detection"]))
        problem = loss_terms_problem(terms, "LOT" in model_cfg)
        if problem:
            source = key_source(model_cfg, "LOSS_TERMS") if "LOSS_TERMS" in model_cfg else "default"
            raise ConfigError(f"MODEL.LOSS_TERMS {terms} (from {source}): {problem}")
        return super().from_config(model_cfg, loss_terms=terms, **kwargs)

    def loss(self, batch_dict: Mapping) -> dict[str, torch.Tensor]:
        """``{'loss': total, ...}``: ``hm_loss``, ``loc_loss`` (detection), ``occupancy_loss``,
        ``forecast_loss`` (LOT), as ``loss_terms`` ask."""
        if "gt_boxes" not in batch_dict:
            raise KeyError("PHiM.loss needs batch_dict['gt_boxes'] (B, M, 8|10)")
        batch = self.vfe(dict(batch_dict))
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


def loss_terms_problem(terms: Sequence[str], has_lot: bool) -> str | None:
    """What is wrong with a list of loss terms (None: nothing)."""
    if not terms or any(t not in LOSS_TERMS for t in terms):
        return f"loss terms must be a non-empty subset of {list(LOSS_TERMS)}, got {list(terms)}"
    if not has_lot and set(terms) - {"detection"}:
        return f"loss terms {list(terms)} need a LOT stage (MODEL.LOT)"
    return None
