"""Shared set-up of the train/test tools: config + ``--set``, output tree, device, seed."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import torch

from pcdet_atlas.config import REPO_ROOT, cfg_from_list, cfg_from_yaml_file
from pcdet_atlas.train_utils.dist import init_dist_pytorch

__all__ = ["add_common_args", "load_cfg", "exp_group_and_tag", "output_dir_for", "setup_runtime"]

DEFAULT_SEED = 666  # OpenPCDet's fixed seed
#: OpenPCDet's default of 4 loader workers, capped at this machine's CPU count
DEFAULT_WORKERS = min(4, os.cpu_count() or 1)


def add_common_args(parser: argparse.ArgumentParser) -> None:
    """The arguments ``train.py`` and ``test.py`` share (OpenPCDet's names)."""
    parser.add_argument("--cfg_file", "--cfg", dest="cfg_file", required=True, help="model YAML")
    parser.add_argument("--batch_size", type=int, default=None, help="total over processes")
    parser.add_argument(
        "--workers", type=int, default=DEFAULT_WORKERS,
        help=f"dataloader workers per process (default: {DEFAULT_WORKERS}, OpenPCDet's 4 capped "
        "at the CPU count)",
    )  # fmt: skip
    parser.add_argument("--extra_tag", type=str, default="default")
    parser.add_argument("--ckpt", type=str, default=None)
    parser.add_argument("--launcher", choices=["none", "pytorch"], default="none")
    parser.add_argument("--tcp_port", type=int, default=18888, help="unused: torchrun sets it")
    parser.add_argument("--local_rank", type=int, default=None, help="unused: from LOCAL_RANK")
    parser.add_argument("--fix_random_seed", action="store_true", default=False)
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED, help="seed of every draw")
    parser.add_argument("--device", type=str, default=None, help="cpu / cuda (default: auto)")
    parser.add_argument(
        "--output_root", type=str, default=str(REPO_ROOT / "output"),
        help="root of the output/<group>/<tag>/<extra_tag>/ tree",
    )  # fmt: skip
    parser.add_argument(
        "--set", dest="set_cfgs", default=None, nargs=argparse.REMAINDER,
        help="KEY VALUE pairs overriding the config",
    )  # fmt: skip


def load_cfg(cfg_file: str, set_cfgs: list[str] | None):
    """The merged config with ``--set`` applied, plus ``TAG`` and ``EXP_GROUP_PATH``."""
    cfg = cfg_from_yaml_file(cfg_file)
    if set_cfgs:
        cfg_from_list(set_cfgs, cfg)
    group, tag = exp_group_and_tag(cfg_file)
    cfg.TAG, cfg.EXP_GROUP_PATH = tag, group
    return cfg


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


def output_dir_for(cfg, output_root: str | Path, extra_tag: str) -> Path:
    """``<output_root>/<EXP_GROUP_PATH>/<TAG>/<extra_tag>/``."""
    return Path(output_root) / cfg.EXP_GROUP_PATH / cfg.TAG / extra_tag


def setup_runtime(args) -> tuple[bool, int, int, torch.device]:
    """Process group (if ``--launcher pytorch``), device and seeds.

    Returns:
        ``(dist, rank, world_size, device)``. Model initialisation uses the global torch RNG,
        which is seeded from ``--seed`` (plus the rank) so that builds are reproducible.
    """
    if args.launcher == "pytorch":
        world, rank, local_rank = init_dist_pytorch()
        dist = True
    else:
        world, rank, local_rank, dist = 1, 0, 0, False
    if args.device is not None:
        device = torch.device(args.device)
    elif torch.cuda.is_available():
        device = torch.device("cuda", local_rank % torch.cuda.device_count())
    else:
        device = torch.device("cpu")
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", local_rank % torch.cuda.device_count())
    torch.manual_seed(args.seed)
    if args.fix_random_seed:
        torch.use_deterministic_algorithms(True, warn_only=True)
        torch.backends.cudnn.benchmark = False
    return dist, rank, world, device
