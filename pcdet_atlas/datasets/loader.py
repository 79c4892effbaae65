"""``build_dataloader`` with OpenPCDet's signature and semantics."""

from __future__ import annotations

import logging
import random
from collections.abc import Mapping, Sequence
from functools import partial
from pathlib import Path

import numpy as np
import torch
import torch.distributed as torch_dist
from torch.utils.data import DataLoader, DistributedSampler, RandomSampler

from pcdet_atlas.config import ConfigError
from pcdet_atlas.registry import DATASETS
from pcdet_atlas.utils.processes import tie_to_parent
from pcdet_atlas.utils.seeding import derive_seed, torch_generator

__all__ = ["ContiguousBatchSampler", "ResumableSampler", "build_dataloader", "worker_init_fn"]


class ContiguousBatchSampler(torch.utils.data.Sampler):
    """In-order batches that give each DataLoader worker (and each process) a contiguous run of
    samples, so per-worker caches of neighbouring frames (the attacked-frame cache of
    ``AtlasWaymoDataset``) hit when a temporal input is read.

    The ``num_samples`` indices are split into ``world_size`` contiguous shards (this process
    takes shard ``rank``), each shard into ``num_workers`` contiguous chunks of whole batches,
    and the chunks' batches are interleaved: a DataLoader hands batch ``i`` to worker
    ``i % num_workers``, so worker ``k`` reads chunk ``k`` in order (when the chunks differ in
    length, the last few batches may go to another worker). The yield order is therefore not
    the index order: consumers put predictions back in frame order (as ``predict_dataset``
    does). Every index appears exactly once over all processes; no padding.

    Args:
        num_samples: the dataset's length. batch_size: samples per batch (>= 1).
        num_workers: the DataLoader's workers (0: one chunk). rank, world_size: the process and
            the number of processes.
        compute: optional ``(num_samples,)`` booleans: only the batches holding at least one
            sample marked True are yielded (before the chunking into workers). The batches keep
            the composition they have without ``compute``, so a skipped batch's samples are
            exactly those another run with the same arguments computed together.
    """

    def __init__(
        self,
        num_samples: int,
        batch_size: int,
        num_workers: int = 0,
        rank: int = 0,
        world_size: int = 1,
        compute: Sequence[bool] | None = None,
    ):
        if batch_size < 1 or num_workers < 0 or world_size < 1 or not 0 <= rank < world_size:
            raise ValueError(
                f"ContiguousBatchSampler: batch_size {batch_size} (>= 1), num_workers "
                f"{num_workers} (>= 0), rank {rank} of world_size {world_size}"
            )
        per_rank = -(-num_samples // world_size)  # ceil
        start, stop = rank * per_rank, min(num_samples, (rank + 1) * per_rank)
        batches = [
            list(range(i, min(i + batch_size, stop))) for i in range(start, stop, batch_size)
        ]
        if compute is not None:
            if len(compute) != num_samples:
                raise ValueError(
                    f"ContiguousBatchSampler: compute has {len(compute)} entries, expected "
                    f"num_samples {num_samples}"
                )
            batches = [b for b in batches if any(compute[i] for i in b)]
        self.compute = None if compute is None else np.asarray(compute, dtype=bool)
        chunks = max(1, num_workers)
        per_chunk = -(-len(batches) // chunks)
        runs = [batches[k * per_chunk : (k + 1) * per_chunk] for k in range(chunks)]
        self.batches = [run[j] for j in range(per_chunk) for run in runs if j < len(run)]

    def __iter__(self):
        return iter(self.batches)

    def __len__(self) -> int:
        return len(self.batches)


class ResumableSampler(torch.utils.data.Sampler):
    """A training sampler whose passes can start part-way, for resuming an epoch mid-way.

    Wraps a sampler (the shuffled ``RandomSampler`` or ``DistributedSampler``). After
    ``start_at(n)``, every pass draws the wrapped sampler's whole order as usual (so its random
    generator advances exactly as in an uninterrupted pass) and yields it from position ``n`` on:
    the indices an interrupted pass had not yet reached. ``start_at(0)`` restores whole passes.
    ``set_epoch`` is passed on to the wrapped sampler.
    """

    def __init__(self, sampler: torch.utils.data.Sampler):
        self.sampler = sampler
        self.start = 0

    def start_at(self, position: int) -> None:
        if not 0 <= position <= len(self.sampler):
            raise ValueError(
                f"ResumableSampler.start_at({position}): a pass has {len(self.sampler)} indices"
            )
        self.start = int(position)

    def set_epoch(self, epoch: int) -> None:
        if hasattr(self.sampler, "set_epoch"):
            self.sampler.set_epoch(epoch)

    def __iter__(self):
        order = iter(self.sampler)
        for _ in range(self.start):
            next(order)
        return order

    def __len__(self) -> int:
        return len(self.sampler) - self.start


def worker_init_fn(worker_id: int, seed: int | None = None) -> None:
    """Tie a loader worker to the process that forked it (it dies with it, even when that one
    is killed: :func:`~pcdet_atlas.utils.processes.tie_to_parent`), and seed the worker's
    global RNGs from ``(seed, 'worker', worker_id)`` for third-party code.

    pcdet_atlas itself never draws from global RNGs (its draws are keyed per frame).
    """
    tie_to_parent()
    if seed is None:
        return
    worker_seed = derive_seed(int(seed), "worker", int(worker_id))
    random.seed(worker_seed)
    np.random.seed(worker_seed % 2**32)
    torch.manual_seed(worker_seed)


def build_dataloader(
    dataset_cfg: Mapping,
    class_names: Sequence[str],
    batch_size: int,
    dist: bool,
    root_path: str | Path | None = None,
    workers: int = 4,
    seed: int | None = None,
    logger: logging.Logger | None = None,
    training: bool = True,
    merge_all_iters_to_one_epoch: bool = False,
    total_epochs: int = 0,
):
    """Build ``dataset_cfg.DATASET`` and its loader.

    Args:
        batch_size: samples per batch (per process when ``dist``).
        dist: use a ``DistributedSampler`` (shuffled in training, in order for testing).
        seed: when given, replaces the dataset's ``SEED`` (augmentation draws), seeds the
            training shuffle order and the workers' global RNGs.
    Returns:
        ``(dataset, dataloader, sampler)``. In training, ``sampler`` is a
        :class:`ResumableSampler` around the shuffled order (a ``DistributedSampler`` when
        ``dist``); for testing it is the ``DistributedSampler`` when ``dist``, else ``None``.
        Call ``dataset.set_epoch(e)`` and ``sampler.set_epoch(e)`` before each training epoch.
    """
    if "DATASET" not in dataset_cfg:
        raise ConfigError("DATA_CONFIG has no DATASET name")
    dataset_cls = DATASETS.get(dataset_cfg.DATASET)
    dataset = dataset_cls(
        dataset_cfg=dataset_cfg,
        class_names=class_names,
        root_path=root_path,
        training=training,
        logger=logger,
    )
    if seed is not None:
        dataset.seed = int(seed)
    if merge_all_iters_to_one_epoch:
        if not hasattr(dataset, "merge_all_iters_to_one_epoch"):
            raise ConfigError(f"{dataset_cfg.DATASET} cannot merge all iterations to one epoch")
        dataset.merge_all_iters_to_one_epoch(merge=True, epochs=total_epochs)

    sampler = None
    if dist:
        if not torch_dist.is_available() or not torch_dist.is_initialized():
            raise RuntimeError("build_dataloader(dist=True) needs an initialised process group")
        sampler = DistributedSampler(
            dataset,
            num_replicas=torch_dist.get_world_size(),
            rank=torch_dist.get_rank(),
            shuffle=training,
            seed=0 if seed is None else int(seed) % 2**31,
        )
    # A DataLoader's iterator draws the workers' base seed from its generator, or else from
    # torch's global RNG: seeded and evaluation loaders have their own, so that running one
    # (the RPN over the train split before a second stage trains, a resume that starts a
    # DDP epoch part-way) leaves the global draws of training (dropout) as they were.
    generator = None
    if seed is not None or not training:
        generator = torch_generator(0 if seed is None else int(seed), "dataloader_shuffle")
    if training:  # the order DataLoader(shuffle=True) would draw, startable part-way
        sampler = ResumableSampler(sampler or RandomSampler(dataset, generator=generator))
    dataloader = DataLoader(
        dataset,
        batch_size=batch_size,
        pin_memory=torch.cuda.is_available(),
        num_workers=workers,
        shuffle=False,
        collate_fn=dataset.collate_batch,
        drop_last=False,
        sampler=sampler,
        timeout=0,
        worker_init_fn=partial(worker_init_fn, seed=seed),
        generator=generator,
    )
    return dataset, dataloader, sampler
