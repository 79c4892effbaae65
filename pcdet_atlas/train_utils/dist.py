"""Process groups of ``torchrun`` and Slurm (OpenPCDet's launchers): gloo on CPU, nccl on GPU."""

from __future__ import annotations

import atexit
import os
import subprocess
from collections.abc import Callable
from datetime import timedelta

import torch
import torch.distributed as dist

__all__ = [
    "init_dist_pytorch",
    "init_dist_slurm",
    "first_slurm_host",
    "get_dist_info",
    "all_gather_objects",
    "unwrap_model",
]


def init_dist_pytorch(backend: str | None = None, timeout_min: int = 30) -> tuple[int, int, int]:
    """Join the process group ``torchrun`` describes in the environment.

    Args:
        backend: ``'nccl'`` / ``'gloo'``; default nccl if CUDA is available, else gloo.
    Returns:
        ``(world_size, rank, local_rank)``; with the nccl backend the process is bound to
        ``cuda:(local_rank % device_count)``.
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
    # A gloo group left to interpreter teardown can abort the process ("terminate called without
    # an active exception") after its work is done, failing a finished torchrun job.
    atexit.register(_destroy_process_group)
    return dist.get_world_size(), dist.get_rank(), local_rank


def _destroy_process_group() -> None:
    if dist.is_initialized():
        dist.destroy_process_group()


def first_slurm_host(node_list: str) -> str:
    """The first host name of a Slurm node list (``scontrol show hostname <list>``, first line)."""
    try:
        proc = subprocess.run(
            ["scontrol", "show", "hostname", node_list], capture_output=True, text=True
        )
    except FileNotFoundError as err:
        raise RuntimeError(
            "--launcher slurm: `scontrol` is not on PATH (start the job with srun inside a "
            "Slurm allocation)"
        ) from err
    hosts = proc.stdout.split()
    if proc.returncode != 0 or not hosts:
        raise RuntimeError(
            f"--launcher slurm: `scontrol show hostname {node_list}` gave no host (exit "
            f"{proc.returncode}): {proc.stderr.strip()}"
        )
    return hosts[0]


def init_dist_slurm(
    tcp_port: int,
    backend: str | None = None,
    timeout_min: int = 30,
    resolve_host: Callable[[str], str] = first_slurm_host,
) -> tuple[int, int, int]:
    """Join the process group of an ``srun`` job, as OpenPCDet's ``init_dist_slurm`` does.

    Reads ``SLURM_PROCID``, ``SLURM_NTASKS`` and ``SLURM_NODELIST``; the first host of the node
    list (``resolve_host``) is the master, listening on ``tcp_port``. Sets ``MASTER_ADDR``,
    ``MASTER_PORT``, ``WORLD_SIZE``, ``RANK`` and ``LOCAL_RANK`` (``SLURM_LOCALID``, else the
    process id) before ``init_process_group``.

    Returns:
        ``(world_size, rank, local_rank)``; on GPU the process is bound to
        ``cuda:local_rank % device_count``.
    """
    for key in ("SLURM_PROCID", "SLURM_NTASKS", "SLURM_NODELIST"):
        if key not in os.environ:
            raise RuntimeError(
                f"--launcher slurm needs the Slurm environment ({key} is not set); start with "
                "`srun --ntasks N python tools/train.py --launcher slurm ...`"
            )
    proc_id = int(os.environ["SLURM_PROCID"])
    local_rank = int(os.environ.get("SLURM_LOCALID", proc_id))
    os.environ["MASTER_ADDR"] = resolve_host(os.environ["SLURM_NODELIST"])
    os.environ["MASTER_PORT"] = str(tcp_port)
    os.environ["WORLD_SIZE"] = str(int(os.environ["SLURM_NTASKS"]))
    os.environ["RANK"] = str(proc_id)
    os.environ["LOCAL_RANK"] = str(local_rank)
    return init_dist_pytorch(backend, timeout_min)


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


def unwrap_model(model: torch.nn.Module) -> torch.nn.Module:
    """The model inside a ``DistributedDataParallel`` wrapper (the model itself otherwise)."""
    return model.module if isinstance(model, torch.nn.parallel.DistributedDataParallel) else model
