"""Optimizers and learning-rate schedules of OpenPCDet's ``OPTIMIZATION`` section.

``adam_onecycle`` is AdamW (decoupled weight decay, betas (0.9, 0.99)) with a cosine one-cycle
schedule on the learning rate and on beta1 (``MOMS``), stepped once per iteration: from
``LR / DIV_FACTOR`` up to ``LR`` over ``PCT_START`` of the run, then down to
``LR / DIV_FACTOR / 1e4`` — OpenPCDet's ``OptimWrapper(true_wd=True)`` + ``OneCycle``. ``adam`` and
``sgd`` use step decay at the epochs of ``DECAY_STEP_LIST`` (floored at ``LR_CLIP``) with an
optional cosine warm-up. Both are standard torch objects whose ``state_dict`` resumes exactly.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import nn

from pcdet_atlas.config import ConfigError, check_known_keys, key_source, require_keys

__all__ = ["OPTIMIZATION_KEYS", "build_optimizer", "build_scheduler"]

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
        return torch.optim.lr_scheduler.OneCycleLR(
            optimizer,
            max_lr=lr,
            total_steps=total_steps,
            pct_start=float(optim_cfg.get("PCT_START", 0.4)),
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
