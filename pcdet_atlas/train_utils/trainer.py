"""The training loop: OpenPCDet's ``train_model`` / ``train_one_epoch``, resumable exactly.

Determinism: the shuffle order of epoch ``e`` is a function of ``(seed, e)`` (the loader's
generator is re-seeded, or the ``DistributedSampler`` gets ``set_epoch(e)``), augmentation draws
are keyed by the dataset's ``set_epoch(e)``, and the checkpoint carries the optimizer, schedule,
AMP scaler and torch RNG state, so training N epochs in one go or in two resumed parts gives the
same weights bit for bit on CPU.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import torch
import tqdm
from torch import nn

from pcdet_atlas.models.batch import load_data_to_device
from pcdet_atlas.train_utils.checkpoint import checkpoint_state, save_checkpoint
from pcdet_atlas.train_utils.cpu_memory import trim_cpu_memory
from pcdet_atlas.train_utils.dist import get_dist_info
from pcdet_atlas.utils.seeding import derive_seed

__all__ = ["TrainState", "train_one_epoch", "train_model"]


@dataclass
class TrainState:
    """Where training stands: finished epochs, optimizer steps taken, and the mean losses of
    the epochs trained in this process."""

    epoch: int = 0
    it: int = 0
    history: list[dict[str, float]] = field(default_factory=list)


def _set_loader_epoch(dataloader, sampler, seed: int, epoch: int) -> None:
    dataset = dataloader.dataset
    if hasattr(dataset, "set_epoch"):
        dataset.set_epoch(epoch)
    if sampler is not None and hasattr(sampler, "set_epoch"):
        sampler.set_epoch(epoch)
    if getattr(dataloader, "generator", None) is not None:
        dataloader.generator.manual_seed(derive_seed(seed, "dataloader_shuffle", epoch))


def train_one_epoch(
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler,
    dataloader,
    *,
    state: TrainState,
    device: torch.device,
    grad_norm_clip: float,
    scaler: torch.amp.GradScaler | None = None,
    use_amp: bool = False,
    tb_log=None,
    logger: logging.Logger | None = None,
    logger_iter_interval: int = 50,
    show_progress: bool = True,
) -> dict[str, float]:
    """One pass over ``dataloader``; updates ``state.it``. Returns the epoch's mean losses."""
    rank, _ = get_dist_info()
    model.train()
    sums: dict[str, float] = {}
    n = 0
    amp_dtype = torch.float16 if device.type == "cuda" else torch.bfloat16
    bar = tqdm.tqdm(
        total=len(dataloader), leave=False, desc="train", dynamic_ncols=True,
        disable=not show_progress or rank != 0,
    )  # fmt: skip
    t_end = time.perf_counter()
    for i, batch in enumerate(dataloader):
        t_data = time.perf_counter() - t_end
        batch = load_data_to_device(batch, device)
        optimizer.zero_grad(set_to_none=True)
        with torch.autocast(device_type=device.type, dtype=amp_dtype, enabled=use_amp):
            ret_dict, tb_dict, _ = model(batch)
        loss = ret_dict["loss"]
        loss_value = float(loss.detach())
        if not math.isfinite(loss_value):
            raise FloatingPointError(
                f"non-finite loss {loss_value} at iteration {state.it} (frames "
                f"{list(batch.get('frame_id', []))}): {tb_dict}"
            )
        if scaler is not None:
            scaler.scale(loss).backward()
            scaler.unscale_(optimizer)
        else:
            loss.backward()
        grad_norm = nn.utils.clip_grad_norm_(model.parameters(), grad_norm_clip)
        if scaler is not None:
            scaler.step(optimizer)
            scaler.update()
        else:
            optimizer.step()
        lr = optimizer.param_groups[0]["lr"]
        scheduler.step()
        state.it += 1
        n += 1
        for k, v in tb_dict.items():
            sums[k] = sums.get(k, 0.0) + float(v)
        if tb_log is not None and rank == 0:
            tb_log.add_scalar("train/loss", loss_value, state.it)
            tb_log.add_scalar("meta_data/learning_rate", lr, state.it)
            tb_log.add_scalar("train/grad_norm", float(grad_norm), state.it)
            for k, v in tb_dict.items():
                tb_log.add_scalar(f"train/{k}", float(v), state.it)
        bar.set_postfix(loss=f"{loss_value:.3f}", lr=f"{lr:.2e}", data=f"{t_data:.2f}s")
        bar.update()
        if logger is not None and rank == 0 and (i + 1) % logger_iter_interval == 0:
            logger.info(
                f"epoch {state.epoch + 1} iter {i + 1}/{len(dataloader)} (total {state.it}): "
                f"loss {loss_value:.4f} lr {lr:.3e} grad_norm {float(grad_norm):.2f}"
            )
        t_end = time.perf_counter()
    bar.close()
    return {k: v / max(n, 1) for k, v in sums.items()}


def train_model(
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler,
    dataloader,
    sampler,
    *,
    state: TrainState,
    total_epochs: int,
    device: torch.device,
    seed: int,
    grad_norm_clip: float,
    ckpt_dir: str | Path,
    ckpt_save_interval: int = 1,
    max_ckpt_save_num: int = 30,
    scaler: torch.amp.GradScaler | None = None,
    use_amp: bool = False,
    tb_log=None,
    logger: logging.Logger | None = None,
    logger_iter_interval: int = 50,
    show_progress: bool = True,
    train_settings: Mapping | None = None,
) -> TrainState:
    """Train from ``state.epoch`` to ``total_epochs``; saves ``checkpoint_epoch_N.pth`` every
    ``ckpt_save_interval`` epochs (and at the end), keeping the newest ``max_ckpt_save_num``.
    ``train_settings`` (the optimization settings in effect) is stored in each checkpoint."""
    rank, _ = get_dist_info()
    ckpt_dir = Path(ckpt_dir)
    epochs = tqdm.trange(
        state.epoch, total_epochs, desc="epochs", dynamic_ncols=True,
        disable=not show_progress or rank != 0,
    )  # fmt: skip
    for epoch in epochs:
        _set_loader_epoch(dataloader, sampler, seed, epoch)
        means = train_one_epoch(
            model, optimizer, scheduler, dataloader, state=state, device=device,
            grad_norm_clip=grad_norm_clip, scaler=scaler, use_amp=use_amp, tb_log=tb_log,
            logger=logger, logger_iter_interval=logger_iter_interval, show_progress=show_progress,
        )  # fmt: skip
        state.epoch = epoch + 1
        state.history.append(means)
        if device.type == "cpu":  # bound the heap that retain_freed_cpu_memory keeps
            trim_cpu_memory()
        if logger is not None and rank == 0:
            logger.info(
                f"epoch {state.epoch}/{total_epochs} done ({state.it} iterations): "
                + ", ".join(f"{k} {v:.4f}" for k, v in means.items())
            )
        if rank == 0 and (state.epoch % ckpt_save_interval == 0 or state.epoch == total_epochs):
            existing = sorted(
                ckpt_dir.glob("checkpoint_epoch_*.pth"), key=lambda p: p.stat().st_mtime
            )
            for old in existing[: max(0, len(existing) - max_ckpt_save_num + 1)]:
                old.unlink()
            path = save_checkpoint(
                checkpoint_state(
                    model,
                    optimizer,
                    scheduler,
                    scaler,
                    epoch=state.epoch,
                    it=state.it,
                    train_settings=train_settings,
                ),  # fmt: skip
                ckpt_dir / f"checkpoint_epoch_{state.epoch}.pth",
            )
            if logger is not None:
                logger.info(f"saved {path}")
    return state
