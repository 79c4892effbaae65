"""The training loop: OpenPCDet's ``train_model`` / ``train_one_epoch``, resumable exactly.

Determinism: the shuffle order of epoch ``e`` is a function of ``(seed, e)`` (the loader's
generator is re-seeded, or the ``DistributedSampler`` gets ``set_epoch(e)``), augmentation draws
are keyed by the dataset's ``set_epoch(e)``, and the checkpoint carries the optimizer, schedule,
AMP scaler and torch RNG state, so training N epochs in one go or in two resumed parts gives the
same weights bit for bit on CPU. Besides the per-epoch checkpoints, ``latest_model.pth`` is
rewritten every ``ckpt_save_time_interval`` seconds inside an epoch; a run resumed from it
starts the epoch's shuffled order at the first batch not yet trained
(:class:`~pcdet_atlas.datasets.loader.ResumableSampler`), so it too ends bit for bit the same.

With ``merge_all_iters_to_one_epoch`` (OpenPCDet's option) the dataset is ``E`` passes long
(``E`` = ``total_epochs``; pass ``p`` of a frame draws its augmentation as epoch ``p``) and is
read in one shuffled pass: each of the ``E`` epochs takes the next ``len(loader) // E`` batches
of that one iterator, so the run trains as many steps as ``E`` plain epochs.
"""

from __future__ import annotations

import itertools
import logging
import math
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import torch
import tqdm
from torch import nn

from pcdet_atlas.models.batch import load_data_to_device
from pcdet_atlas.train_utils.checkpoint import LATEST_NAME, checkpoint_state, save_checkpoint
from pcdet_atlas.train_utils.cpu_memory import trim_cpu_memory
from pcdet_atlas.train_utils.dist import get_dist_info
from pcdet_atlas.utils.provenance import source_revision
from pcdet_atlas.utils.seeding import derive_seed
from pcdet_atlas.version import __version__

__all__ = ["TrainState", "iterations_per_epoch", "train_one_epoch", "train_model"]


@dataclass
class TrainState:
    """Where training stands: finished epochs, optimizer steps taken, the batches of the next
    epoch already trained (``epoch_it``, non-zero only when resumed mid-epoch) with their summed
    losses, the mean losses of the epochs finished in this process, and ``runs``: the training
    calls that brought it here, oldest first (:func:`run_record`; a checkpoint's ``train_runs``)."""

    epoch: int = 0
    it: int = 0
    epoch_it: int = 0
    epoch_loss_sums: dict[str, float] = field(default_factory=dict)
    history: list[dict[str, float]] = field(default_factory=list)
    runs: list[dict] = field(default_factory=list)


def run_record(state: TrainState, device: torch.device, processes: int = 1) -> dict:
    """What a training call that starts at ``state`` runs on: the iteration and epoch it starts
    from, the device, the CPU threads, the process count, torch's and this package's versions
    and the source commit (:func:`~pcdet_atlas.utils.provenance.source_revision`; None where
    unknown). Together, a checkpoint's records say which code and runtime trained which
    iterations, what a bit-exact retraining has to repeat (the float results of a step depend on
    the thread count and the code); iterations before the first record's ``from_it`` were
    trained by a version that kept none."""
    revision = source_revision()
    return {
        "from_epoch": int(state.epoch),
        "from_it": int(state.it),
        "device": str(device),
        "threads": int(torch.get_num_threads()),
        "processes": int(processes),
        "torch": str(torch.__version__),  # a str subclass: plain text loads under weights_only
        "package": __version__,
        "source_commit": None if revision is None else revision.commit,
        "source_dirty": None if revision is None else revision.dirty,
    }


def iterations_per_epoch(dataloader, total_epochs: int, merged: bool = False) -> int:
    """Optimizer steps per epoch: the loader's length, or with ``merged``
    (``merge_all_iters_to_one_epoch``: the dataset is ``total_epochs`` passes long) that length
    divided by ``total_epochs``, rounded down (OpenPCDet's ``total_it_each_epoch``). Call it
    before a resume starts the loader part-way (its length then counts only the rest)."""
    if not merged:
        return len(dataloader)
    per_epoch = len(dataloader) // total_epochs
    if per_epoch < 1:
        raise ValueError(
            f"merge_all_iters_to_one_epoch: {len(dataloader)} batches of the merged dataset "
            f"cannot make {total_epochs} epochs of at least one step: lower the batch size or "
            "train without the flag"
        )
    return per_epoch


def _set_loader_epoch(dataloader, sampler, seed: int, epoch: int, start_batch: int = 0) -> None:
    dataset = dataloader.dataset
    if hasattr(dataset, "set_epoch"):
        dataset.set_epoch(epoch)
    if sampler is not None and hasattr(sampler, "set_epoch"):
        sampler.set_epoch(epoch)
    if getattr(dataloader, "generator", None) is not None:
        dataloader.generator.manual_seed(derive_seed(seed, "dataloader_shuffle", epoch))
    if hasattr(sampler, "start_at"):
        sampler.start_at(start_batch * dataloader.batch_size)
    elif start_batch:
        raise ValueError(
            f"resuming mid-epoch (after batch {start_batch}) needs a sampler with start_at "
            f"(build_dataloader(training=True) gives one), not {type(sampler).__name__}"
        )


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
    after_step: Callable[[], None] | None = None,
    batches: Iterator | None = None,
    epoch_batches: int | None = None,
) -> dict[str, float]:
    """One pass over ``dataloader`` (the rest of the epoch when ``state.epoch_it`` batches of it
    were trained before a resume; the loader then yields only the others), or, when ``batches``
    is given, the next ``epoch_batches - state.epoch_it`` batches of that iterator (an epoch of
    ``epoch_batches`` steps taken from a longer pass, as ``merge_all_iters_to_one_epoch`` does);
    updates ``state.it``, ``state.epoch_it`` and ``state.epoch_loss_sums``, and calls
    ``after_step()`` after every optimizer step but the epoch's last (the epoch's end is the
    caller's to record). Returns the epoch's mean losses over all its batches.

    Raises:
        RuntimeError: ``batches`` ran out before the epoch's ``epoch_batches``.
        ValueError: only one of ``batches`` and ``epoch_batches`` is given.
        FloatingPointError: a non-finite loss (the step and its batch are named).
    """
    if (batches is None) != (epoch_batches is None):
        raise ValueError("train_one_epoch: give both batches and epoch_batches, or neither")
    rank, _ = get_dist_info()
    model.train()
    sums = state.epoch_loss_sums
    start = state.epoch_it
    if batches is None:
        source, total = dataloader, start + len(dataloader)
    else:
        source, total = itertools.islice(batches, epoch_batches - start), epoch_batches
    amp_dtype = torch.float16 if device.type == "cuda" else torch.bfloat16
    bar = tqdm.tqdm(
        total=total, initial=start, leave=False, desc="train", dynamic_ncols=True,
        disable=not show_progress or rank != 0,
    )  # fmt: skip
    t_end = time.perf_counter()
    for batch in source:
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
        state.epoch_it += 1
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
        if logger is not None and rank == 0 and state.epoch_it % logger_iter_interval == 0:
            logger.info(
                f"epoch {state.epoch + 1} iter {state.epoch_it}/{total} (total {state.it}): "
                f"loss {loss_value:.4f} lr {lr:.3e} grad_norm {float(grad_norm):.2f}"
            )
        if after_step is not None and state.epoch_it < total:
            after_step()
        t_end = time.perf_counter()
    bar.close()
    if state.epoch_it != total:
        raise RuntimeError(
            f"the loader ran out after {state.epoch_it} of the epoch's {total} batches"
        )
    return {k: v / max(state.epoch_it, 1) for k, v in sums.items()}


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
    ckpt_save_time_interval: float | None = 300.0,
    merge_all_iters_to_one_epoch: bool = False,
    cpu_trim_every: int | None = 20,
) -> TrainState:
    """Train from where ``state`` stands to ``total_epochs``; saves ``checkpoint_epoch_N.pth``
    every ``ckpt_save_interval`` epochs (and at the end), keeping the newest
    ``max_ckpt_save_num``, and rewrites ``latest_model.pth`` once at least
    ``ckpt_save_time_interval`` seconds have passed since the last save (0: after every step;
    None: never), inside an epoch or at the end of one that writes no epoch checkpoint; an epoch
    checkpoint supersedes it (it is removed). It never records an epoch's last batch as
    pending: a resume always starts inside an epoch or at its beginning. ``train_settings`` (the
    settings in effect, :func:`~pcdet_atlas.train_utils.checkpoint.resume_settings`) is stored in
    each checkpoint. ``merge_all_iters_to_one_epoch``: the loader's dataset is merged to
    ``total_epochs`` passes (``build_dataloader(merge_all_iters_to_one_epoch=True,
    total_epochs=...)``) and the epochs share one pass over it (module docstring). On CPU the
    heap's free memory goes back to the OS every ``cpu_trim_every`` steps (None: once per epoch;
    :func:`~pcdet_atlas.train_utils.cpu_memory.trim_cpu_memory`): with freed memory retained,
    steps of varying sizes fragment the heap, which otherwise grows over an epoch to several
    times a step's peak."""
    rank, world = get_dist_info()
    ckpt_dir = Path(ckpt_dir)
    last_save = time.monotonic()
    if state.epoch < total_epochs:
        state.runs.append(run_record(state, device, world))
    batches, epoch_batches = None, None
    if merge_all_iters_to_one_epoch and state.epoch < total_epochs:
        merged = getattr(dataloader.dataset, "total_epochs", None)
        if merged != total_epochs:
            raise ValueError(
                f"merge_all_iters_to_one_epoch: the loader's dataset is merged to {merged} "
                f"passes, not total_epochs {total_epochs} (build it with build_dataloader("
                f"merge_all_iters_to_one_epoch=True, total_epochs={total_epochs}))"
            )
        # one pass keyed as epoch 0: the dataset maps index i to pass i // frames as its epoch
        _set_loader_epoch(dataloader, sampler, seed, 0)
        epoch_batches = iterations_per_epoch(dataloader, total_epochs, merged=True)
        done = state.epoch * epoch_batches + state.epoch_it
        _set_loader_epoch(dataloader, sampler, seed, 0, start_batch=done)
        batches = iter(dataloader)

    def state_dict() -> dict:
        return checkpoint_state(
            model, optimizer, scheduler, scaler, epoch=state.epoch, it=state.it,
            epoch_it=state.epoch_it, epoch_loss_sums=state.epoch_loss_sums,
            train_settings=train_settings, train_runs=state.runs,
        )  # fmt: skip

    def save_latest() -> None:
        nonlocal last_save
        if rank != 0 or ckpt_save_time_interval is None:
            return
        if time.monotonic() - last_save >= ckpt_save_time_interval:
            save_checkpoint(state_dict(), ckpt_dir / LATEST_NAME)
            last_save = time.monotonic()

    def after_step() -> None:
        save_latest()
        if device.type == "cpu" and cpu_trim_every and state.it % cpu_trim_every == 0:
            trim_cpu_memory()

    epochs = tqdm.trange(
        state.epoch, total_epochs, desc="epochs", dynamic_ncols=True,
        disable=not show_progress or rank != 0,
    )  # fmt: skip
    for epoch in epochs:
        if batches is None:
            _set_loader_epoch(dataloader, sampler, seed, epoch, start_batch=state.epoch_it)
        means = train_one_epoch(
            model, optimizer, scheduler, dataloader, state=state, device=device,
            grad_norm_clip=grad_norm_clip, scaler=scaler, use_amp=use_amp, tb_log=tb_log,
            logger=logger, logger_iter_interval=logger_iter_interval, show_progress=show_progress,
            after_step=after_step, batches=batches, epoch_batches=epoch_batches,
        )  # fmt: skip
        state.epoch = epoch + 1
        state.epoch_it, state.epoch_loss_sums = 0, {}
        state.history.append(means)
        if device.type == "cpu":  # bound the heap that retain_freed_cpu_memory keeps
            trim_cpu_memory()
        if logger is not None and rank == 0:
            logger.info(
                f"epoch {state.epoch}/{total_epochs} done ({state.it} iterations): "
                + ", ".join(f"{k} {v:.4f}" for k, v in means.items())
            )
        if rank == 0 and (state.epoch % ckpt_save_interval == 0 or state.epoch == total_epochs):
            path = save_checkpoint(state_dict(), ckpt_dir / f"checkpoint_epoch_{state.epoch}.pth")
            # the oldest go only once the new one is on disk: a kill in between leaves both
            existing = sorted(
                ckpt_dir.glob("checkpoint_epoch_*.pth"), key=lambda p: p.stat().st_mtime
            )
            for old in existing[: max(0, len(existing) - max_ckpt_save_num)]:
                old.unlink()
            (ckpt_dir / LATEST_NAME).unlink(missing_ok=True)
            last_save = time.monotonic()
            if logger is not None:
                logger.info(f"saved {path}")
        else:
            save_latest()
    return state
