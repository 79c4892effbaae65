"""Shared set-up of the train/test tools: config + ``--set``, output tree, device, seed."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from pathlib import Path

import torch

from pcdet_atlas.config import (
    REPO_ROOT,
    cfg_from_list,
    cfg_from_yaml_file,
    check_experiment_config,
    resolve_repo_path,
)
from pcdet_atlas.models.optimization import check_optimization_config
from pcdet_atlas.train_utils.dist import init_dist_pytorch, init_dist_slurm
from pcdet_atlas.utils.cli import RenamedFlag, add_set_flag
from pcdet_atlas.utils.common import resolve_device
from pcdet_atlas.utils.locks import FolderLock, FolderLockedError
from pcdet_atlas.utils.paths import (
    SAFE_COMPONENT_RULE,
    UnsafePathError,
    join_under,
    safe_component,
)

__all__ = [
    "add_common_args",
    "count_arg",
    "device_arg",
    "folder_name_arg",
    "lock_output_folder",
    "load_cfg",
    "exp_group_and_tag",
    "output_dir_for",
    "setup_runtime",
]

DEFAULT_SEED = 666  # OpenPCDet's fixed seed
DEFAULT_TCP_PORT = 18888  # master port of --launcher slurm
#: OpenPCDet's default of 4 loader workers, capped at this machine's CPU count
DEFAULT_WORKERS = min(4, os.cpu_count() or 1)


def count_arg(minimum: int):
    """An argparse ``type`` for an integer flag that must be ``>= minimum``: a smaller value is a
    usage error naming the flag (``argument --epochs: must be an integer >= 1, got 0``)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"must be an integer >= {minimum}, got {text!r}"
            ) from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be an integer >= {minimum}, got {value}")
        return value

    return parse


def add_common_args(parser: argparse.ArgumentParser) -> dict[str, argparse._ArgumentGroup]:
    """The arguments ``train.py`` and ``test.py`` share (OpenPCDet's names), in three groups of
    the tool's ``--help``; returns them (``'model'``, ``'outputs'``, ``'runtime'``) so that a
    tool adds its own flags where they belong."""
    model = parser.add_argument_group("model and data")
    model.add_argument("--cfg_file", "--cfg", dest="cfg_file", required=True, help="model YAML")
    model.add_argument(
        "--ckpt", type=str, default=None,
        help="train: resume from it (default: the run's newest); test: evaluate it (default: "
        "the config's ATLAS.CHECKPOINT)",
    )  # fmt: skip
    model.add_argument("--batch_size", type=count_arg(1), default=None, help="total over processes")
    model.add_argument(
        "--workers", type=count_arg(0), default=DEFAULT_WORKERS,
        help=f"dataloader workers per process (default: {DEFAULT_WORKERS}, OpenPCDet's 4 capped "
        "at the CPU count)",
    )  # fmt: skip
    add_set_flag(model)
    outputs = parser.add_argument_group("outputs")
    outputs.add_argument(
        "--out_dir", "--output_root", action=RenamedFlag, old=("--output_root",),
        dest="output_root", type=str, default=str(REPO_ROOT / "output"), metavar="DIR",
        help="root of the output/<group>/<tag>/<extra_tag>/ tree (default: <repo>/output)",
    )  # fmt: skip
    outputs.add_argument(
        "--extra_tag", type=folder_name_arg, default="default",
        help="the run's folder under output/<group>/<tag>/",
    )  # fmt: skip
    runtime = parser.add_argument_group("runtime")
    runtime.add_argument(
        "--device", type=device_arg, default=None, help="cpu / cuda / cuda:N (default: auto)"
    )
    runtime.add_argument(
        "--threads", type=count_arg(1), default=None,
        help="torch CPU threads of the process (default: torch's, one per core); 1 is faster "
        "on a 2-core CPU shared with other jobs or with --workers",
    )  # fmt: skip
    runtime.add_argument(
        "--fix_random_seed", action="store_true", default=False,
        help="seed every draw with --seed and run deterministic algorithms (reproducible runs)",
    )  # fmt: skip
    runtime.add_argument("--seed", type=int, default=DEFAULT_SEED, help="seed of every draw")
    runtime.add_argument(
        "--launcher", choices=["none", "pytorch", "slurm"], default="none",
        help="pytorch: under torchrun; slurm: under srun (one process per task)",
    )  # fmt: skip
    runtime.add_argument(
        "--tcp_port", type=count_arg(1), default=DEFAULT_TCP_PORT,
        help="master port of --launcher slurm (torchrun sets its own)",
    )  # fmt: skip
    runtime.add_argument("--local_rank", type=int, default=None, help="unused: from LOCAL_RANK")
    runtime.add_argument(
        "--default_malloc", action="store_true", default=False,
        help="on CPU, leave glibc malloc as it is (default: keep freed memory for reuse, "
        "pcdet_atlas.train_utils.cpu_memory; faster CPU steps, same results: docs/benchmarks.md)",
    )  # fmt: skip
    return {"model": model, "outputs": outputs, "runtime": runtime}


def load_cfg(cfg_file: str, set_cfgs: list[str] | None):
    """The merged config with ``--set`` applied, plus ``TAG`` and ``EXP_GROUP_PATH``."""
    cfg = cfg_from_yaml_file(cfg_file)
    if set_cfgs:
        cfg_from_list(set_cfgs, cfg)
    check_experiment_config(cfg)
    if "OPTIMIZATION" in cfg:  # every key against its declaration, before anything is built
        check_optimization_config(cfg.OPTIMIZATION)
    group, tag = exp_group_and_tag(cfg_file)
    cfg.TAG, cfg.EXP_GROUP_PATH = tag, group
    return cfg


def require_dataset(cfg, cfg_file: str | Path) -> None:
    """Stop with a one-line message (no traceback) when the config's ``DATA_CONFIG.DATA_PATH``
    is not there, naming the path and, for a real-Waymo config, its synthetic counterpart."""
    root = resolve_repo_path(cfg.DATA_CONFIG.get("DATA_PATH", ""))
    if root.is_dir():
        return
    hint = "convert Waymo with OpenPCDet into it (docs/data.md)"
    path = Path(cfg_file).resolve()
    twin = path.parent / "synthetic" / path.name
    if twin.is_file():
        try:
            shown = twin.relative_to(REPO_ROOT)
        except ValueError:
            shown = twin
        hint += f", or run the synthetic config instead: --cfg {shown}"
    raise SystemExit(
        f"{cfg_file}: DATA_CONFIG.DATA_PATH {cfg.DATA_CONFIG.get('DATA_PATH')!r} ({root}) does "
        f"not exist: {hint}"
    )


def exp_group_and_tag(cfg_file: str | Path) -> tuple[str, str]:
    """``cfgs/atlas/synthetic/cp4f.yaml`` -> ``('atlas/synthetic', 'cp4f')``; a file outside
    ``cfgs/`` gets its parent folder's name as group."""
    path = Path(cfg_file).resolve()
    try:
        rel = path.relative_to(REPO_ROOT / "cfgs")
        group = "/".join(rel.parts[:-1])
    except ValueError:
        group = path.parent.name
    return group or "default", path.stem


def output_dir_for(
    cfg, output_root: str | Path, extra_tag: str, *below: tuple[object, str], source: str = ""
) -> Path:
    """``<output_root>/<EXP_GROUP_PATH>/<TAG>/<extra_tag>/``, and under it the ``below`` parts
    (``(name, what)``: ``('ckpt', 'folder')``, an evaluation's names); each name one safe path
    component and the whole path, symlinks resolved, inside ``output_root``
    (:func:`~pcdet_atlas.utils.paths.join_under`): a linked ``ckpt/`` or ``eval/`` that leads
    elsewhere is refused, not written or emptied through."""
    group = [(part, "config folder") for part in str(cfg.EXP_GROUP_PATH).split("/")]
    run = f"{output_root}/{cfg.EXP_GROUP_PATH}/{cfg.TAG}/{extra_tag}"
    return join_under(
        output_root, *group, (cfg.TAG, "config name"), (extra_tag, "extra_tag"), *below,
        source=source or f"the output folder {run}",
    )  # fmt: skip


def folder_name_arg(text: str) -> str:
    """The argparse ``type`` of a flag naming one output folder (``--extra_tag``,
    ``--eval_tag``): anything but one safe name (``../x``, ``..``) is a usage error."""
    try:
        return safe_component(text, "folder name", "the command line")
    except UnsafePathError:
        raise argparse.ArgumentTypeError(f"{text!r} is not {SAFE_COMPONENT_RULE}") from None


def lock_output_folder(folder: Path, held: contextlib.ExitStack, purpose: str) -> None:
    """Hold ``folder``'s one-writer lock (:class:`~pcdet_atlas.utils.locks.FolderLock`) until
    ``held`` closes. A folder another run writes stops the tool with a one-line message naming
    the folder and that run (exit 2)."""
    try:
        held.enter_context(FolderLock(folder, purpose))
    except FolderLockedError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from None


def device_arg(text: str) -> str:
    """The argparse ``type`` of ``--device``: a device that is not there (``cuda`` without a
    GPU) is a one-line usage error naming the flag."""
    try:
        resolve_device(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"{err}; use --device cpu") from None
    return text


def setup_runtime(
    *,
    device: str | None = None,
    launcher: str = "none",
    tcp_port: int = DEFAULT_TCP_PORT,
    threads: int | None = None,
    seed: int = DEFAULT_SEED,
    fix_random_seed: bool = False,
) -> tuple[bool, int, int, torch.device]:
    """Device, process group (``launcher`` ``pytorch`` / ``slurm``), CPU threads and seeds: the
    flags of :func:`add_common_args` of the same names.

    Returns:
        ``(dist, rank, world_size, device)``. Model initialisation uses the global torch RNG,
        which is seeded from ``seed`` so that builds are reproducible.
    """
    # a missing GPU is an error before any process group is joined
    backend = "nccl" if resolve_device(device).type == "cuda" else "gloo"
    if launcher == "pytorch":
        world, rank, local_rank = init_dist_pytorch(backend)
    elif launcher == "slurm":
        world, rank, local_rank = init_dist_slurm(tcp_port, backend)
    else:
        world, rank, local_rank = 1, 0, 0
    resolved = resolve_device(device, local_rank)
    if threads is not None:
        torch.set_num_threads(threads)
    torch.manual_seed(seed)
    if fix_random_seed:
        # cuBLAS is deterministic only with a fixed workspace (read when it first starts)
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True, warn_only=True)
        torch.backends.cudnn.benchmark = False
    return launcher != "none", rank, world, resolved
