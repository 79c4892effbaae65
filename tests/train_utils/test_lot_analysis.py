"""LOT's filter measurements: voxel groups, the recall rule's threshold, the range prior."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch

from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.models import build_network_from_config
from pcdet_atlas.models.model_utils.centernet_utils import focal_loss_centernet_prob
from pcdet_atlas.train_utils.lot_analysis import (
    collect_confidences,
    forecast_quality,
    keep_rate,
    range_prior,
    threshold_for_recall,
    voxel_confidences,
)

sys.path.insert(0, str(REPO_ROOT / "tests" / "models"))
from model_batches import make_batch  # noqa: E402

STAGE3 = REPO_ROOT / "cfgs/atlas/synthetic/phim_lot/stage3_finetune.yaml"


def lot_model():
    cfg = cfg_from_yaml_file(STAGE3)
    cfg.DATA_CONFIG.POINT_CLOUD_RANGE = [-25.6, -25.6, -2.0, 25.6, 25.6, 4.0]
    torch.manual_seed(0)
    return build_network_from_config(cfg).eval()


def test_threshold_for_recall_is_the_highest_that_keeps_the_share():
    values = np.array([0.9, 0.1, 0.5, 0.7, 0.3, 0.8, 0.6, 0.2, 0.4, 0.95])
    t = threshold_for_recall(values, 0.8)
    assert t == 0.3 and keep_rate(values, t) >= 0.8
    assert keep_rate(values, np.nextafter(t, 1.0)) < 0.8  # any higher keeps less
    assert threshold_for_recall(values, 1.0) == 0.1
    assert keep_rate(np.zeros(0), 0.5) is None
    with pytest.raises(ValueError, match="recall"):
        threshold_for_recall(values, 0.0)
    with pytest.raises(ValueError, match="no in-box"):
        threshold_for_recall(np.zeros(0))


def test_voxels_are_grouped_by_their_points_boxes():
    model = lot_model()
    batch = make_batch(num_point_features=5, points_per_box=60, background=500)
    box = batch["gt_boxes"][0, 0, :7].numpy()  # the first box of sample 0 as a phantom
    batch["attack"] = [{"family": "injection", "spoofed": True, "target_box": box}, None]
    groups, forecast = voxel_confidences(model, batch)
    total = model.lot.occupancy_maps(model.vfe(dict(batch)))["lot_voxel_confidence"].numel()
    assert sum(g.numel() for g in groups.values()) == total  # every voxel in one group
    assert groups["phantom"].numel() > 0 and groups["in_box"].numel() > 0
    assert groups["background"].numel() > groups["in_box"].numel()
    assert forecast.shape[0] == 2 and ((forecast >= 0) & (forecast <= 1)).all()
    # without the phantom record, its voxels count as in a box
    del batch["attack"]
    plain, _ = voxel_confidences(model, batch)
    assert plain["phantom"].numel() == 0
    assert plain["in_box"].numel() == groups["in_box"].numel() + groups["phantom"].numel()
    found, maps = collect_confidences(model, [batch])
    assert found.of("in_box").size == plain["in_box"].numel() and len(maps) == 1


def test_range_prior_is_the_best_constant_per_range_cell():
    g = torch.Generator().manual_seed(0)
    targets = (torch.rand(6, 12, 5, generator=g) ** 3) * (torch.rand(6, 12, 5, generator=g) < 0.5)
    targets[:, :3, 1] = 1.0  # positives at range cell 1
    maps = [(torch.zeros_like(targets), targets)]
    prior = range_prior(maps)
    assert prior.shape == (5,) and prior[1] > prior[0]

    def loss(p):
        return sum(float(focal_loss_centernet_prob(p.expand_as(t)[None], t[None])) for t in targets)

    best = loss(prior)
    for r in range(5):
        for factor in (0.5, 2.0):
            moved = prior.clone()
            moved[r] = (moved[r] * factor).clamp(1e-4, 1 - 1e-4)
            assert loss(moved) >= best - 1e-9
    q = forecast_quality([(prior.expand_as(targets), targets)], prior)
    assert q["forecast"] == pytest.approx(q["range_prior"], rel=1e-5)


def test_the_tool_prints_keep_rates_and_forecast_quality(synthetic_root, capsys):
    from pcdet_atlas.utils.common import load_tool

    tool = load_tool("dev/lot_filter")
    out = tool.main(
        ["--cfg", str(STAGE3), "--data_path", str(synthetic_root), "--fit_frames", "2",
         "--frames", "2"]
    )  # fmt: skip
    assert 0.0 <= out["fitted_thresh"] <= 1.0 and out["configured_thresh"] == 0.1
    assert out["keep"]["in_box"]["fitted"] >= 0.95 and out["keep"]["background"]["voxels"] > 0
    assert set(out["forecast_focal_loss"]) == {"forecast", "range_prior"}
    printed = capsys.readouterr().out
    assert "kept @ rule" in printed and "range prior" in printed
