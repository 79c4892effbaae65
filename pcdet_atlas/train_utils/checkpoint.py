"""OpenPCDet-style checkpoints with everything needed for an exact resume.

A checkpoint is a dict ``{'epoch', 'it', 'epoch_it', 'epoch_loss_sums', 'model_state',
'optimizer_state', 'scheduler_state', 'scaler_state', 'rng_state', 'train_settings', 'version'}``;
``epoch`` counts the finished epochs and ``it`` the optimizer steps taken; ``epoch_it`` the
batches of the next epoch already trained (0 at an epoch's end; a ``latest_model.pth`` written
mid-epoch has more) and ``epoch_loss_sums`` their summed losses; ``train_settings`` holds the
optimization settings in effect (:func:`check_resume_settings` compares them on resume).
``model_state`` alone is what ``--pretrained_model`` / ``tools/test.py`` load (strictly, with a
readable error on mismatch).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path

import torch
from torch import nn

from pcdet_atlas.models.detectors.detector3d_template import (
    load_state_dict_checked,
    read_checkpoint,
)
from pcdet_atlas.train_utils.dist import unwrap_model
from pcdet_atlas.version import __version__

__all__ = [
    "checkpoint_state",
    "save_checkpoint",
    "load_checkpoint",
    "find_latest_checkpoint",
    "find_resume_checkpoint",
    "list_epoch_checkpoints",
    "check_resume_settings",
    "export_model_checkpoint",
]

CHECKPOINT_NAME = re.compile(r"checkpoint_epoch_(\d+)\.pth")
LATEST_NAME = "latest_model.pth"  # the mid-epoch checkpoint (OpenPCDet's name)


def checkpoint_state(
    model: nn.Module,
    optimizer: torch.optim.Optimizer | None = None,
    scheduler=None,
    scaler: torch.amp.GradScaler | None = None,
    *,
    epoch: int,
    it: int,
    epoch_it: int = 0,
    epoch_loss_sums: Mapping[str, float] | None = None,
    train_settings: Mapping | None = None,
) -> dict:
    """The checkpoint dict (tensors moved to CPU)."""
    state = {k: v.detach().cpu() for k, v in unwrap_model(model).state_dict().items()}
    info = getattr(unwrap_model(model), "checkpoint_info", None)
    return {
        "epoch": int(epoch),
        "it": int(it),
        "epoch_it": int(epoch_it),
        "epoch_loss_sums": dict(epoch_loss_sums or {}),
        "model_state": state,
        "model_info": info() if info is not None else {},  # e.g. a two-stage model's RPN
        "optimizer_state": None if optimizer is None else optimizer.state_dict(),
        "scheduler_state": None if scheduler is None else scheduler.state_dict(),
        "scaler_state": None if scaler is None else scaler.state_dict(),
        "rng_state": torch.get_rng_state(),
        "train_settings": None if train_settings is None else dict(train_settings),
        "version": f"pcdet_atlas+{__version__}",
    }


def save_checkpoint(state: dict, path: str | Path) -> Path:
    """Write atomically (a temporary file renamed into place)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(state, tmp)
    tmp.replace(path)
    return path


def load_checkpoint(
    path: str | Path,
    model: nn.Module,
    optimizer: torch.optim.Optimizer | None = None,
    scheduler=None,
    scaler: torch.amp.GradScaler | None = None,
    *,
    strict: bool = True,
) -> dict:
    """Restore what ``path`` holds into the given objects; returns the checkpoint dict.

    Raises:
        CheckpointMismatchError: the parameters do not fit ``model``.
        KeyError: an optimizer/scheduler is given but the checkpoint has no state for it.
    """
    ckpt = read_checkpoint(path)
    state = ckpt["model_state"] if "model_state" in ckpt else ckpt
    load_state_dict_checked(unwrap_model(model), state, strict=strict, source=str(path))
    check_info = getattr(unwrap_model(model), "check_checkpoint_info", None)
    if check_info is not None:  # e.g. a two-stage model resumed with another RPN
        check_info(ckpt, path)
    for obj, key in ((optimizer, "optimizer_state"), (scheduler, "scheduler_state")):
        if obj is not None:
            if ckpt.get(key) is None:
                raise KeyError(f"checkpoint {path} has no {key!r} to resume from")
            obj.load_state_dict(ckpt[key])
    if scaler is not None and ckpt.get("scaler_state"):
        scaler.load_state_dict(ckpt["scaler_state"])
    if ckpt.get("rng_state") is not None:
        torch.set_rng_state(ckpt["rng_state"])
    return ckpt


def list_epoch_checkpoints(ckpt_dir: str | Path) -> list[tuple[int, Path]]:
    """``[(N, path)]`` of the ``checkpoint_epoch_N.pth`` files in ``ckpt_dir``, by epoch."""
    found = []
    for p in Path(ckpt_dir).glob("checkpoint_epoch_*.pth"):
        m = CHECKPOINT_NAME.fullmatch(p.name)
        if m:
            found.append((int(m.group(1)), p))
    return sorted(found)


def find_latest_checkpoint(ckpt_dir: str | Path) -> Path | None:
    """The ``checkpoint_epoch_N.pth`` with the largest N in ``ckpt_dir`` (None if there is none)."""
    found = list_epoch_checkpoints(ckpt_dir)
    return found[-1][1] if found else None


def find_resume_checkpoint(ckpt_dir: str | Path) -> Path | None:
    """Where an interrupted training run goes on from: ``latest_model.pth`` (written mid-epoch)
    when it is ahead of every ``checkpoint_epoch_N.pth``, else the newest of those (None if
    ``ckpt_dir`` holds neither)."""
    newest = find_latest_checkpoint(ckpt_dir)
    latest = Path(ckpt_dir) / LATEST_NAME
    if latest.is_file():
        ckpt = read_checkpoint(latest)
        ahead = (ckpt["epoch"], ckpt.get("epoch_it", 0))
        if newest is None or ahead > (int(CHECKPOINT_NAME.fullmatch(newest.name).group(1)), 0):
            return latest
    return newest


def _flatten(node, prefix: str = "") -> dict:
    if not isinstance(node, Mapping):
        return {prefix: node}
    out: dict = {}
    for key, value in node.items():
        out.update(_flatten(value, f"{prefix}.{key}" if prefix else str(key)))
    return out


def check_resume_settings(ckpt: Mapping, settings: Mapping, path: str | Path) -> None:
    """Refuse to resume a checkpoint trained with other optimization settings.

    Raises:
        ValueError: naming every setting that differs, with the checkpoint's and this run's
            values (a changed schedule or optimizer would silently mix two trainings).
    """
    saved = ckpt.get("train_settings")
    if saved is None:
        return  # written before settings were recorded: only the step count can be checked
    old, new = _flatten(saved), _flatten(settings)
    differ = sorted(k for k in old.keys() | new.keys() if old.get(k) != new.get(k))
    if differ:
        changes = ", ".join(f"{k}: {old.get(k)!r} -> {new.get(k)!r}" for k in differ)
        raise ValueError(
            f"cannot resume {path}: it was trained with other settings ({changes}); resume with "
            "the checkpoint's settings, or start a new run (another --extra_tag)"
        )


def export_model_checkpoint(src: str | Path, dst: str | Path) -> Path:
    """Keep only ``epoch``, ``it``, ``model_state``, ``model_info`` and ``version`` of a training
    checkpoint (the small file a model zoo ships; ``tools/test.py`` and ``--pretrained_model``
    read it)."""
    ckpt = read_checkpoint(src)
    if "model_state" not in ckpt:
        raise KeyError(f"{src} is not a pcdet_atlas checkpoint (no 'model_state')")
    keep = {
        k: ckpt[k] for k in ("epoch", "it", "model_state", "model_info", "version") if k in ckpt
    }
    return save_checkpoint(keep, dst)
