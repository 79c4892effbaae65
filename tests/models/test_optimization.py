"""The LR schedules of ``OPTIMIZATION``: the shape docs/getting_started.md states, and the one
run length torch's one-cycle schedule cannot take."""

import math

import pytest
import torch

from pcdet_atlas.config import ConfigError
from pcdet_atlas.models.optimization import build_optimizer, build_scheduler

RUN = {"BATCH_SIZE_PER_GPU": 2, "NUM_EPOCHS": 1, "GRAD_NORM_CLIP": 10}
ONECYCLE = {**RUN, "OPTIMIZER": "adam_onecycle", "LR": 0.003, "MOMS": [0.95, 0.85],
            "PCT_START": 0.4, "DIV_FACTOR": 10, "WEIGHT_DECAY": 0.01}  # fmt: skip


def lrs_of(optim_cfg, steps: int, iters_per_epoch: int | None = None) -> list[float]:
    model = torch.nn.Linear(2, 1)
    optimizer = build_optimizer(model, optim_cfg)
    per_epoch = iters_per_epoch or steps
    scheduler = build_scheduler(
        optimizer, optim_cfg, iters_per_epoch=per_epoch, total_epochs=steps // per_epoch
    )
    out = []
    for _ in range(steps):
        out.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    return out


@pytest.mark.parametrize("steps", [100, 6480])
def test_onecycle_peaks_one_step_before_pct_start_and_ends_at_lr_over_div_over_1e4(steps):
    lrs = lrs_of(ONECYCLE, steps)
    peak = round(0.4 * steps) - 1  # 0.4 x steps is a whole number here
    assert max(lrs) == lrs[peak] == 0.003 and lrs.index(max(lrs)) == peak
    assert math.isclose(lrs[0], 0.003 / 10, rel_tol=1e-12)
    assert math.isclose(lrs[-1], 0.003 / 10 / 1e4, rel_tol=1e-12)


def test_warmup_of_plain_adam_rises_from_zero():
    cfg = {**RUN, "OPTIMIZER": "adam", "LR": 0.01, "LR_WARMUP": True, "WARMUP_EPOCH": 1,
           "DECAY_STEP_LIST": [5], "LR_DECAY": 0.1}  # fmt: skip
    lrs = lrs_of(cfg, 20, iters_per_epoch=4)
    assert lrs[0] == 0.0 and 0 < lrs[1] < lrs[2] < lrs[3] < 0.01 and lrs[4] == 0.01


def test_a_pct_start_that_makes_exactly_one_rising_step_is_a_config_error():
    cfg = {**ONECYCLE, "PCT_START": 0.1}
    with pytest.raises(ConfigError, match=r"OPTIMIZATION\.PCT_START = 0\.1 .* x 10 steps"):
        lrs_of(cfg, 10)
    assert len(lrs_of(cfg, 11)) == 11
