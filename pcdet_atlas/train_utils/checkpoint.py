"""OpenPCDet-style checkpoints with everything needed for an exact resume.

A checkpoint is a dict ``{'epoch', 'it', 'epoch_it', 'epoch_loss_sums', 'model_state',
'optimizer_state', 'scheduler_state', 'scaler_state', 'rng_state', 'cuda_rng_state',
'train_settings', 'train_runs', 'version'}``, plus ``model_info`` (the model's class names and
point features) where the model gives it; ``epoch`` counts the finished epochs and ``it``
the optimizer steps taken; ``epoch_it`` the batches of the next epoch already trained (0 at an
epoch's end; a ``latest_model.pth`` written mid-epoch has more) and ``epoch_loss_sums`` their
summed losses; ``rng_state`` is torch's CPU generator and ``cuda_rng_state`` the CUDA generators
(None when the process never used CUDA); ``train_settings`` holds the settings in effect
(:func:`resume_settings`; :func:`check_resume_settings` compares them on resume) and
``train_runs`` the training calls that produced it, each with the iteration it started from and
its runtime and code (``trainer.run_record``: device, threads, versions, source commit).
Checkpoints written before ``cuda_rng_state``, ``train_runs`` or a setting was recorded lack
them: nothing is restored or compared for what is absent. ``model_state`` alone is what
``--pretrained_model`` / ``tools/test.py`` load (strictly, with a readable error on mismatch).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from torch import nn

from pcdet_atlas.config import to_plain
from pcdet_atlas.models.detectors.detector3d_template import (
    load_state_dict_checked,
    read_checkpoint,
)
from pcdet_atlas.train_utils.dist import unwrap_model
from pcdet_atlas.utils.files import write_atomic
from pcdet_atlas.version import __version__

__all__ = [
    "resume_settings",
    "checkpoint_state",
    "save_checkpoint",
    "load_checkpoint",
    "find_latest_checkpoint",
    "find_resume_checkpoint",
    "list_epoch_checkpoints",
    "check_resume_settings",
    "export_model_checkpoint",
    "model_config_sha256",
    "training_seed",
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
    train_runs: Sequence[Mapping] = (),
) -> dict:
    """The checkpoint dict (the model's tensors moved to CPU; the optimizer, scheduler and
    scaler states as they are)."""
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
        # e.g. GPU dropout masks: without it they would restart after a resume
        "cuda_rng_state": torch.cuda.get_rng_state_all() if torch.cuda.is_initialized() else None,
        "train_settings": None if train_settings is None else dict(train_settings),
        "train_runs": [dict(run) for run in train_runs],
        "version": f"pcdet_atlas+{__version__}",
    }


def save_checkpoint(state: dict, path: str | Path) -> Path:
    """Write atomically and durably: a temporary file of its own (a name no other process and
    no planted symlink holds: :func:`~pcdet_atlas.utils.files.write_atomic`), flushed to disk,
    renamed into place, and the folder flushed too (where the platform can), so that neither a
    crash nor a power loss leaves a truncated or empty file under ``path``."""
    path = write_atomic(path, lambda f: torch.save(state, f))
    if hasattr(os, "O_DIRECTORY"):  # POSIX: the rename is durable once the folder is synced
        fd = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    return path


def load_checkpoint(
    path: str | Path,
    model: nn.Module,
    optimizer: torch.optim.Optimizer | None = None,
    scheduler=None,
    scaler: torch.amp.GradScaler | None = None,
    *,
    strict: bool = True,
    train_settings: Mapping | None = None,
) -> dict:
    """Restore what ``path`` holds into the given objects; returns the checkpoint dict. With
    ``train_settings`` (this run's :func:`resume_settings`), they are compared with the
    checkpoint's first (:func:`check_resume_settings`), before anything is restored.

    Raises:
        ValueError: ``train_settings`` differ from the checkpoint's.
        CheckpointMismatchError: the parameters do not fit ``model``.
        KeyError: an optimizer/scheduler is given but the checkpoint has no state for it.
    """
    ckpt = read_checkpoint(path)
    if train_settings is not None:
        check_resume_settings(ckpt, train_settings, path)
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
    cuda_states = ckpt.get("cuda_rng_state")
    if cuda_states is not None and torch.cuda.is_available():
        # the GPUs beyond this machine's are not there to draw from (a CPU run uses none)
        torch.cuda.set_rng_state_all(list(cuda_states)[: torch.cuda.device_count()])
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
        if "epoch" not in ckpt:
            raise ValueError(f"checkpoint {latest} has no 'epoch': not a training state to resume")
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


def _sha256(node) -> str:
    text = json.dumps(to_plain(node), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def resume_settings(
    cfg: Mapping,
    *,
    batch_size: int,
    processes: int,
    seed: int,
    use_amp: bool,
    sync_bn: bool,
    merge_all_iters_to_one_epoch: bool,
) -> dict:
    """What a training run must share with a checkpoint to go on with the checkpoint's training
    (stored as its ``train_settings``): the ``OPTIMIZATION`` section (``NUM_EPOCHS`` as in effect;
    the per-process batch aside), the total ``batch_size``, the number of ``processes``, the
    ``seed`` (shuffle and augmentation draws), ``use_amp``, ``sync_bn``,
    ``merge_all_iters_to_one_epoch``, and SHA-256 digests of the merged ``CLASS_NAMES``,
    ``DATA_CONFIG`` (without ``DATA_PATH``, so a moved dataset still resumes), ``MODEL`` and, when
    the config has one, ``STAGE``."""
    data = {k: v for k, v in to_plain(cfg["DATA_CONFIG"]).items() if k != "DATA_PATH"}
    digests = {
        "CLASS_NAMES": _sha256(cfg["CLASS_NAMES"]),
        "DATA_CONFIG": _sha256(data),
        "MODEL": _sha256(cfg["MODEL"]),
    }
    if cfg.get("STAGE") is not None:
        digests["STAGE"] = _sha256(cfg["STAGE"])
    optim = to_plain(cfg["OPTIMIZATION"])
    return {
        "OPTIMIZATION": {k: v for k, v in optim.items() if k != "BATCH_SIZE_PER_GPU"},
        "batch_size": int(batch_size),  # total over processes: the schedule does not see the split
        "processes": int(processes),
        "seed": int(seed),
        "use_amp": bool(use_amp),
        "sync_bn": bool(sync_bn),
        "merge_all_iters_to_one_epoch": bool(merge_all_iters_to_one_epoch),
        "config_sha256": digests,
    }


def check_resume_settings(ckpt: Mapping, settings: Mapping, path: str | Path) -> None:
    """Refuse to resume a checkpoint trained with other settings (:func:`resume_settings`).

    Only the settings the checkpoint records are compared: one written before a setting was
    recorded (e.g. without ``seed``) is not checked for it, and one without any
    ``train_settings`` only by the caller's step count.

    Raises:
        ValueError: naming every setting that differs, with the checkpoint's and this run's
            values and the checkpoint file (a changed schedule, data order or model would
            silently mix two trainings).
    """
    saved = ckpt.get("train_settings")
    if saved is None:
        return  # written before settings were recorded: only the step count can be checked
    old = _flatten(saved)
    new = _flatten({k: v for k, v in settings.items() if k in saved})
    differ = sorted(k for k in old.keys() | new.keys() if old.get(k) != new.get(k))
    if differ:
        changes = ", ".join(f"{k}: {old.get(k)!r} -> {new.get(k)!r}" for k in differ)
        raise ValueError(
            f"cannot resume {path}: it was trained with other settings ({changes}); resume with "
            "the checkpoint's settings, or start a new run (another --extra_tag)"
        )


def model_config_sha256(cfg: Mapping) -> str:
    """SHA-256 of what makes a model and its training apart from the seed: the merged config's
    ``CLASS_NAMES``, ``MODEL``, ``OPTIMIZATION`` and ``DATA_CONFIG`` without ``DATA_PATH``
    (``ATLAS``, naming the checkpoint and the display name, is left out). Two evaluations with
    the same digest and different training seeds are the same model retrained
    (``results.json``'s ``model_sha256``)."""
    data = {k: v for k, v in to_plain(cfg["DATA_CONFIG"]).items() if k != "DATA_PATH"}
    parts = {key: to_plain(cfg[key]) for key in ("CLASS_NAMES", "MODEL", "OPTIMIZATION")}
    return _sha256({**parts, "DATA_CONFIG": data})


def training_seed(ckpt: Mapping, declared: int | None, path: str | Path) -> int | None:
    """The seed a checkpoint's weights were trained with: its ``train_settings['seed']``
    (``tools/train.py`` records it), else ``declared`` (the config's ``ATLAS.TRAINING_SEED``,
    for a checkpoint written before the record was kept), else None (unknown).

    Raises:
        ValueError: a ``declared`` seed that is not an integer, or that contradicts the one the
            checkpoint records, naming the file.
    """
    if declared is not None and (isinstance(declared, bool) or not isinstance(declared, int)):
        raise ValueError(f"ATLAS.TRAINING_SEED {declared!r}: expected an integer (for {path})")
    recorded = (ckpt.get("train_settings") or {}).get("seed")
    if recorded is not None and declared is not None and int(recorded) != declared:
        raise ValueError(
            f"{path}: trained with seed {recorded} (its train_settings), but the config's "
            f"ATLAS.TRAINING_SEED says {declared}; remove the key or correct it"
        )
    return int(recorded) if recorded is not None else declared


def export_model_checkpoint(src: str | Path, dst: str | Path) -> Path:
    """Keep only ``epoch``, ``it``, ``model_state``, ``model_info``, ``train_settings`` (the
    seed and schedule the weights were trained with: :func:`training_seed`), ``train_runs`` (the
    runtime and code of each training call) and ``version`` of a training checkpoint (the small
    file a model zoo ships; ``tools/test.py`` and ``--pretrained_model`` read it)."""
    ckpt = read_checkpoint(src)
    if "model_state" not in ckpt:
        raise KeyError(f"{src} is not a pcdet_atlas checkpoint (no 'model_state')")
    names = ("epoch", "it", "model_state", "model_info", "train_settings", "train_runs", "version")
    keep = {k: ckpt[k] for k in names if k in ckpt}
    return save_checkpoint(keep, dst)
