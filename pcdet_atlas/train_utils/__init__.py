"""Training and evaluation loops behind ``tools/train.py`` and ``tools/test.py``."""

from pcdet_atlas.train_utils.checkpoint import (
    check_resume_settings,
    checkpoint_state,
    export_model_checkpoint,
    find_latest_checkpoint,
    find_resume_checkpoint,
    list_epoch_checkpoints,
    load_checkpoint,
    resume_settings,
    save_checkpoint,
)
from pcdet_atlas.train_utils.cpu_memory import retain_freed_cpu_memory
from pcdet_atlas.train_utils.dist import get_dist_info, init_dist_pytorch, init_dist_slurm
from pcdet_atlas.train_utils.eval_utils import eval_one_epoch, predict_dataset
from pcdet_atlas.train_utils.trainer import (
    TrainState,
    iterations_per_epoch,
    train_model,
    train_one_epoch,
)

__all__ = [
    "TrainState",
    "check_resume_settings",
    "checkpoint_state",
    "eval_one_epoch",
    "export_model_checkpoint",
    "find_latest_checkpoint",
    "find_resume_checkpoint",
    "get_dist_info",
    "init_dist_pytorch",
    "init_dist_slurm",
    "iterations_per_epoch",
    "list_epoch_checkpoints",
    "load_checkpoint",
    "predict_dataset",
    "resume_settings",
    "retain_freed_cpu_memory",
    "save_checkpoint",
    "train_model",
    "train_one_epoch",
]
