"""docs/model_zoo.md "Adding a detector": its example runs as written, builds a model with the
new stage in place, predicts, trains, and refuses a bad value of the stage's declared key."""

from __future__ import annotations

import copy
import re

import pytest
import torch

from pcdet_atlas.config import REPO_ROOT, ConfigError
from pcdet_atlas.models import build_network_from_config
from pcdet_atlas.registry import DETECTORS, MODEL_STAGES


def documented_example() -> str:
    text = (REPO_ROOT / "docs" / "model_zoo.md").read_text()
    section = text[text.index("## Adding a detector") :]
    return re.search(r"^```python\n(.*?)^```", section, flags=re.M | re.S).group(1)


@pytest.fixture
def example():
    namespace: dict = {}
    exec(compile(documented_example(), "docs/model_zoo.md", "exec"), namespace)  # noqa: S102
    yield namespace
    DETECTORS.unregister("ThinCenterPoint")
    MODEL_STAGES.unregister("ThinBEV")


def test_the_documented_detector_builds_predicts_and_trains(example):
    model, cfg = example["model"], example["cfg"]
    assert type(model).__name__ == "ThinCenterPoint"
    assert type(model.backbone_2d).__name__ == "ThinBEV"
    assert model.backbone_2d.conv[0].out_channels == 32
    generator = torch.Generator().manual_seed(0)
    n = 2000
    xyz = torch.rand(n, 3, generator=generator) * torch.tensor([60.0, 60.0, 3.0])
    xyz -= torch.tensor([30.0, 30.0, 1.0])
    features = torch.rand(n, 2, generator=generator)
    points = torch.cat([torch.zeros(n, 1), xyz, features], dim=1)
    model.eval()
    (pred,) = model.predict({"points": points, "batch_size": 1})
    assert pred["pred_boxes"].shape[1] == 7 and torch.isfinite(pred["pred_boxes"]).all()
    model.train()
    gt = torch.tensor([[[5.0, 3.0, 0.0, 4.5, 2.0, 1.6, 0.3, 1.0]]])
    loss = model.loss({"points": points, "batch_size": 1, "gt_boxes": gt})["loss"]
    loss.backward()
    assert model.backbone_2d.conv[0].weight.grad.abs().sum() > 0
    bad = copy.deepcopy(cfg)
    bad.MODEL.BACKBONE_2D = {"NAME": "ThinBEV", "NUM_FILTERS": 0}
    with pytest.raises(ConfigError, match="NUM_FILTERS"):
        build_network_from_config(bad)
