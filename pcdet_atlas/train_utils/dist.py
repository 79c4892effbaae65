"""``torchrun`` process groups: gloo on CPU, nccl on GPU."""

from __future__ import annotations

import os
from datetime import timedelta

import torch
import torch.distributed as dist

__all__ = ["init_dist_pytorch", "get_dist_info", "all_gather_objects"]


def init_dist_pytorch(backend: str | None = None, timeout_min: int = 30) -> tuple[int, int, int]:
    """Join the process group ``torchrun`` describes in the environment.

    Args:
        backend: ``'nccl'`` / ``'gloo'``; default nccl if CUDA is available, else gloo.
    Returns:
        ``(world_size, rank, local_rank)``; on GPU the process is bound to ``cuda:local_rank``.
    """
    for key in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        if key not in os.environ:
            raise RuntimeError(
                f"--launcher pytorch needs the torchrun environment ({key} is not set); "
                "start with `torchrun --nproc_per_node N tools/train.py --launcher pytorch ...`"
            )
    local_rank = int(os.environ["LOCAL_RANK"])
    if backend is None:
        backend = "nccl" if torch.cuda.is_available() else "gloo"
    if backend == "nccl":
        torch.cuda.set_device(local_rank % torch.cuda.device_count())
    dist.init_process_group(backend=backend, timeout=timedelta(minutes=timeout_min))
    return dist.get_world_size(), dist.get_rank(), local_rank


def get_dist_info() -> tuple[int, int]:
    """``(rank, world_size)``; ``(0, 1)`` without a process group."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def all_gather_objects(obj) -> list:
    """Every rank's ``obj`` (picklable), in rank order; ``[obj]`` without a process group."""
    rank, world = get_dist_info()
    if world == 1:
        return [obj]
    out: list = [None] * world
    dist.all_gather_object(out, obj)
    return out
