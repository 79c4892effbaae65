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
from dataclasses import dataclass

import torch
from torch import nn

from pcdet_atlas.config import ConfigError, key_source
from pcdet_atlas.config_values import declared_keys, read_section, setting

__all__ = [
    "OPTIMIZATION_KEYS",
    "OptimizationConfig",
    "build_optimizer",
    "build_scheduler",
    "check_optimization_config",
]

OPTIMIZERS = ("adam_onecycle", "adam", "sgd")


@dataclass(frozen=True, kw_only=True)
class OptimizationConfig:
    """The ``OPTIMIZATION`` section (OpenPCDet's keys)."""

    batch_size_per_gpu: int = setting(ge=1, doc="samples per process and step")
    num_epochs: int = setting(ge=1, doc="epochs of the run")
    optimizer: str = setting(
        choices=OPTIMIZERS, expected=f"one of {', '.join(OPTIMIZERS)}",
        doc="adam_onecycle (AdamW), adam or sgd",
    )  # fmt: skip
    lr: float = setting(gt=0, doc="peak learning rate")
    weight_decay: float = setting(0.0, ge=0, doc="weight decay (AdamW's decoupled)")
    momentum: float = setting(0.9, ge=0, doc="SGD momentum (sgd only)")
    moms: tuple[float, float] = setting(
        (0.95, 0.85), ge=0, lt=1, doc="beta1 at the start and at the peak (adam_onecycle)",
        expected="two numbers in [0, 1): beta1 at the start and at the peak, e.g. [0.95, 0.85]",
    )  # fmt: skip
    pct_start: float = setting(
        0.4, gt=0, lt=1, doc="share of the steps rising to LR (adam_onecycle)",
        expected="a number between 0 and 1, exclusive (the share of steps rising to LR)",
    )  # fmt: skip
    div_factor: float = setting(
        10.0, gt=0, doc="the one-cycle schedule starts at LR / DIV_FACTOR (adam_onecycle)"
    )
    decay_step_list: tuple[float, ...] = setting(
        (), ge=0, doc="epochs at which LR is multiplied by LR_DECAY (adam, sgd)"
    )
    lr_decay: float = setting(0.1, gt=0, doc="step decay factor (adam, sgd)")
    lr_clip: float = setting(0.0, ge=0, doc="floor of the decayed LR (adam, sgd)")
    lr_warmup: bool = setting(False, doc="cosine warm-up from 0 (adam, sgd)")
    warmup_epoch: int = setting(1, ge=0, doc="epochs of the warm-up (adam, sgd)")
    grad_norm_clip: float = setting(gt=0, doc="the gradient norm is clipped to it")


#: the ``OPTIMIZATION`` section's keys
OPTIMIZATION_KEYS = tuple(declared_keys(OptimizationConfig))


def check_optimization_config(optim_cfg: Mapping) -> OptimizationConfig:
    """``OPTIMIZATION`` read into its declaration, before anything is built or written.

    Raises:
        ConfigError: naming the key, its value, its file and what was expected.
    """
    return read_section(OptimizationConfig, optim_cfg, "OPTIMIZATION")


def build_optimizer(model: nn.Module, optim_cfg: Mapping) -> torch.optim.Optimizer:
    """The optimizer named by ``OPTIMIZATION.OPTIMIZER`` over all trainable parameters."""
    settings = check_optimization_config(optim_cfg)
    params = [p for p in model.parameters() if p.requires_grad]
    lr, wd = settings.lr, settings.weight_decay
    if settings.optimizer == "adam_onecycle":
        return torch.optim.AdamW(params, lr=lr, betas=(0.9, 0.99), weight_decay=wd)
    if settings.optimizer == "adam":
        return torch.optim.Adam(params, lr=lr, weight_decay=wd)
    return torch.optim.SGD(params, lr=lr, weight_decay=wd, momentum=settings.momentum)


def build_scheduler(
    optimizer: torch.optim.Optimizer, optim_cfg: Mapping, *, iters_per_epoch: int, total_epochs: int
) -> torch.optim.lr_scheduler.LRScheduler:
    """The per-iteration LR schedule for ``total_epochs`` of ``iters_per_epoch`` steps."""
    settings = check_optimization_config(optim_cfg)
    total_steps = max(1, iters_per_epoch * total_epochs)
    lr = settings.lr
    if settings.optimizer == "adam_onecycle":
        moms, pct_start = settings.moms, settings.pct_start
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
            base_momentum=moms[1],
            max_momentum=moms[0],
            div_factor=settings.div_factor,
            final_div_factor=1e4,
        )
    decay_epochs, decay, clip = settings.decay_step_list, settings.lr_decay, settings.lr_clip
    warmup_iters = settings.warmup_epoch * iters_per_epoch if settings.lr_warmup else 0

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
