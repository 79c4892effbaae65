"""Optimizers and learning-rate schedules of OpenPCDet's ``OPTIMIZATION`` section.

``adam_onecycle`` is AdamW (decoupled weight decay, betas (0.9, 0.99)) with a cosine one-cycle
schedule on the learning rate and on beta1 (``MOMS``), stepped once per iteration: from
``LR / DIV_FACTOR`` up to ``LR`` over ``PCT_START`` of the run, then down to
``LR / DIV_FACTOR / 1e4`` — OpenPCDet's ``OptimWrapper(true_wd=True)`` + ``OneCycle``. ``adam`` and
``sgd`` use step decay at the epochs of ``DECAY_STEP_LIST`` (floored at ``LR_CLIP``) with an
optional cosine warm-up. Both are standard torch objects whose ``state_dict`` resumes exactly.

Known small differences from OpenPCDet's own schedules (docs/getting_started.md): torch's
``OneCycleLR`` has ``LR`` at step ``PCT_START * T - 1`` (0-based, T steps; between two steps when
that is not whole) and exactly ``LR / DIV_FACTOR / 1e4`` at its last step, where OpenPCDet's
``OneCycle`` has ``LR`` at step ``int(PCT_START * T)`` and ends slightly above that; the warm-up
of ``adam``/``sgd`` rises from 0, where OpenPCDet's ``CosineWarmupLR`` rises from
``LR / DIV_FACTOR``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import nn

from pcdet_atlas.config import ConfigError, check_known_keys, key_source, require_keys
from pcdet_atlas.config_values import config_value

__all__ = ["OPTIMIZATION_KEYS", "build_optimizer", "build_scheduler", "check_optimization_config"]

OPTIMIZATION_KEYS = (
    "BATCH_SIZE_PER_GPU",
    "NUM_EPOCHS",
    "OPTIMIZER",
    "LR",
    "WEIGHT_DECAY",
    "MOMENTUM",
    "MOMS",
    "PCT_START",
    "DIV_FACTOR",
    "DECAY_STEP_LIST",
    "LR_DECAY",
    "LR_CLIP",
    "LR_WARMUP",
    "WARMUP_EPOCH",
    "GRAD_NORM_CLIP",
)
OPTIMIZERS = ("adam_onecycle", "adam", "sgd")


def _two_numbers(value) -> tuple[float, float]:
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise ValueError(value)
    if any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in value):
        raise ValueError(value)
    return float(value[0]), float(value[1])


def check_optimization_config(optim_cfg: Mapping) -> None:
    """Check what training reads of ``OPTIMIZATION`` before anything is built or written:
    known keys, ``OPTIMIZER``, ``GRAD_NORM_CLIP`` (required), and ``PCT_START``, ``MOMS`` and
    ``DIV_FACTOR`` where given (``LR``, ``NUM_EPOCHS`` and ``BATCH_SIZE_PER_GPU`` are checked
    when the config is loaded).

    Raises:
        ConfigError: naming the key, its value, its file and what was expected.
    """
    section = "OPTIMIZATION"
    check_known_keys(optim_cfg, OPTIMIZATION_KEYS, section)
    config_value(
        optim_cfg, "OPTIMIZER", str, section, valid=lambda v: v in OPTIMIZERS,
        expected=f"one of {', '.join(OPTIMIZERS)}",
    )  # fmt: skip
    config_value(
        optim_cfg, "GRAD_NORM_CLIP", float, section, valid=lambda v: v > 0,
        expected="a number > 0 (the gradient norm is clipped to it)",
    )  # fmt: skip
    config_value(
        optim_cfg, "PCT_START", float, section, default=None, valid=lambda v: 0 < v < 1,
        expected="a number between 0 and 1, exclusive (the share of steps rising to LR)",
    )  # fmt: skip
    config_value(
        optim_cfg, "MOMS", _two_numbers, section, default=None,
        valid=lambda v: all(0 <= m < 1 for m in v),
        expected="two numbers in [0, 1): beta1 at the start and at the peak, e.g. [0.95, 0.85]",
    )  # fmt: skip
    config_value(
        optim_cfg, "DIV_FACTOR", float, section, default=None, valid=lambda v: v > 0,
        expected="a number > 0 (the one-cycle schedule starts at LR / DIV_FACTOR)",
    )  # fmt: skip


def build_optimizer(model: nn.Module, optim_cfg: Mapping) -> torch.optim.Optimizer:
    """The optimizer named by ``OPTIMIZATION.OPTIMIZER`` over all trainable parameters."""
    check_known_keys(optim_cfg, OPTIMIZATION_KEYS, "OPTIMIZATION")
    require_keys(optim_cfg, ["OPTIMIZER", "LR"], "OPTIMIZATION")
    name = optim_cfg["OPTIMIZER"]
    params = [p for p in model.parameters() if p.requires_grad]
    lr, wd = float(optim_cfg["LR"]), float(optim_cfg.get("WEIGHT_DECAY", 0.0))
    if name == "adam_onecycle":
        return torch.optim.AdamW(params, lr=lr, betas=(0.9, 0.99), weight_decay=wd)
    if name == "adam":
        return torch.optim.Adam(params, lr=lr, weight_decay=wd)
    if name == "sgd":
        return torch.optim.SGD(
            params, lr=lr, weight_decay=wd, momentum=float(optim_cfg.get("MOMENTUM", 0.9))
        )
    raise ConfigError(
        f"OPTIMIZATION.OPTIMIZER {name!r} (from {key_source(optim_cfg, 'OPTIMIZER')}) is not one "
        f"of {', '.join(OPTIMIZERS)}"
    )


def build_scheduler(
    optimizer: torch.optim.Optimizer, optim_cfg: Mapping, *, iters_per_epoch: int, total_epochs: int
) -> torch.optim.lr_scheduler.LRScheduler:
    """The per-iteration LR schedule for ``total_epochs`` of ``iters_per_epoch`` steps."""
    total_steps = max(1, iters_per_epoch * total_epochs)
    lr = float(optim_cfg["LR"])
    if optim_cfg["OPTIMIZER"] == "adam_onecycle":
        moms = optim_cfg.get("MOMS", [0.95, 0.85])
        pct_start = float(optim_cfg.get("PCT_START", 0.4))
        if float(pct_start * total_steps) - 1 == 0:  # torch's rising phase would have 0 steps
            raise ConfigError(
                f"OPTIMIZATION.PCT_START = {pct_start} (from {key_source(optim_cfg, 'PCT_START')})"
                f" x {total_steps} steps is exactly 1: torch's OneCycleLR cannot rise over 0 "
                "steps; expected another PCT_START or run length"
            )
        return torch.optim.lr_scheduler.OneCycleLR(
            optimizer,
            max_lr=lr,
            total_steps=total_steps,
            pct_start=pct_start,
            anneal_strategy="cos",
            cycle_momentum=True,
            base_momentum=float(moms[1]),
            max_momentum=float(moms[0]),
            div_factor=float(optim_cfg.get("DIV_FACTOR", 10)),
            final_div_factor=1e4,
        )
    decay_epochs = [float(e) for e in optim_cfg.get("DECAY_STEP_LIST", [])]
    decay = float(optim_cfg.get("LR_DECAY", 0.1))
    clip = float(optim_cfg.get("LR_CLIP", 0.0))
    warmup_iters = (
        int(optim_cfg.get("WARMUP_EPOCH", 1)) * iters_per_epoch
        if optim_cfg.get("LR_WARMUP", False)
        else 0
    )

    def factor(step: int) -> float:
        epoch = step / max(1, iters_per_epoch)
        f = 1.0
        for e in decay_epochs:
            if epoch >= e:
                f *= decay
        f = max(f, clip / lr)
        if step < warmup_iters:
            f *= (1 - math.cos(math.pi * step / warmup_iters)) / 2
        return f

    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)
