"""OpenPCDet-style checkpoints with everything needed for an exact resume.

A checkpoint is a dict ``{'epoch', 'it', 'model_state', 'optimizer_state', 'scheduler_state',
'scaler_state', 'rng_state', 'version'}``; ``epoch`` counts the finished epochs and ``it`` the
optimizer steps taken. ``model_state`` alone is what ``--pretrained_model`` / ``tools/test.py``
load (strictly, with a readable error on mismatch).
"""

from __future__ import annotations

import re
from pathlib import Path

import torch
from torch import nn

from pcdet_atlas.models.detectors.detector3d_template import load_state_dict_checked
from pcdet_atlas.version import __version__

__all__ = [
    "checkpoint_state",
    "save_checkpoint",
    "load_checkpoint",
    "find_latest_checkpoint",
    "export_model_checkpoint",
]


def _unwrap(model: nn.Module) -> nn.Module:
    return model.module if isinstance(model, nn.parallel.DistributedDataParallel) else model


def checkpoint_state(
    model: nn.Module,
    optimizer: torch.optim.Optimizer | None = None,
    scheduler=None,
    scaler: torch.amp.GradScaler | None = None,
    *,
    epoch: int,
    it: int,
) -> dict:
    """The checkpoint dict (tensors moved to CPU)."""
    state = {k: v.detach().cpu() for k, v in _unwrap(model).state_dict().items()}
    return {
        "epoch": int(epoch),
        "it": int(it),
        "model_state": state,
        "optimizer_state": None if optimizer is None else optimizer.state_dict(),
        "scheduler_state": None if scheduler is None else scheduler.state_dict(),
        "scaler_state": None if scaler is None else scaler.state_dict(),
        "rng_state": torch.get_rng_state(),
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
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    state = ckpt["model_state"] if "model_state" in ckpt else ckpt
    load_state_dict_checked(_unwrap(model), state, strict=strict, source=str(path))
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


def find_latest_checkpoint(ckpt_dir: str | Path) -> Path | None:
    """The ``checkpoint_epoch_N.pth`` with the largest N in ``ckpt_dir`` (None if there is none)."""
    found = []
    for p in Path(ckpt_dir).glob("checkpoint_epoch_*.pth"):
        m = re.fullmatch(r"checkpoint_epoch_(\d+)\.pth", p.name)
        if m:
            found.append((int(m.group(1)), p))
    return max(found)[1] if found else None


def export_model_checkpoint(src: str | Path, dst: str | Path) -> Path:
    """Keep only ``epoch``, ``it``, ``model_state`` and ``version`` of a training checkpoint (the
    small file a model zoo ships; ``tools/test.py`` and ``--pretrained_model`` read it)."""
    ckpt = torch.load(src, map_location="cpu", weights_only=False)
    if "model_state" not in ckpt:
        raise KeyError(f"{src} is not a pcdet_atlas checkpoint (no 'model_state')")
    keep = {k: ckpt[k] for k in ("epoch", "it", "model_state", "version") if k in ckpt}
    return save_checkpoint(keep, dst)
