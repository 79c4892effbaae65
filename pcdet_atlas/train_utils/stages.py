"""Staged training: a config's ``STAGE`` section says where a stage starts and what it trains.

::

    STAGE:
      NAME: stage2_ssm
      INIT_FROM: stage1_score.yaml   # the predecessor's config, relative to this file
      TRAIN: [lot.convssm]           # the only modules that train
      FREEZE: [vfe, lot.score_mlp]   # taken from the predecessor's checkpoint and kept fixed

A stage starts from the newest checkpoint its predecessor's run left under the same
``--extra_tag`` (``--pretrained_model`` names another file); that checkpoint must have finished
the predecessor's configured epochs (``OPTIMIZATION.NUM_EPOCHS`` as that run had it in effect),
unless ``allow_partial`` (``tools/train.py --allow_partial_stage_init``). Every parameter outside
``TRAIN`` has ``requires_grad`` off and its module stays in eval mode while training, so
batch-norm statistics do not move either. A missing predecessor checkpoint, or one without the
parameters of a module the stage freezes, stops the run with an error naming the stage and the
checkpoint.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from torch import nn

from pcdet_atlas.config import ConfigError, key_source
from pcdet_atlas.config_values import read_section, setting
from pcdet_atlas.models.detectors.detector3d_template import (
    load_state_dict_checked,
    read_checkpoint,
)
from pcdet_atlas.train_utils.checkpoint import find_latest_checkpoint
from pcdet_atlas.train_utils.setup import load_cfg, output_dir_for

__all__ = [
    "StageSection",
    "TrainingStage",
    "apply_stage_freezing",
    "load_stage_init",
    "stage_from_config",
    "stage_init_checkpoint",
]


@dataclass(frozen=True, kw_only=True)
class StageSection:
    """The ``STAGE`` section of a staged config."""

    name: str = setting(doc="the stage's name")
    init_from: str | None = setting(
        None, doc="the predecessor's config, relative to the file that sets it"
    )
    train: tuple[str, ...] = setting(
        check=bool, expected="a non-empty list of module names (a stage must train something)",
        doc="the only modules that train (dotted names, e.g. lot.convssm)",
    )  # fmt: skip
    freeze: tuple[str, ...] = setting(
        (), doc="modules taken from the predecessor's checkpoint and kept fixed"
    )


@dataclass(frozen=True)
class TrainingStage:
    """A parsed ``STAGE`` section (``source``: the file that set it)."""

    name: str
    init_from: Path | None
    train: tuple[str, ...]
    freeze: tuple[str, ...]
    source: str


def stage_from_config(cfg: Mapping) -> TrainingStage | None:
    """The config's ``STAGE`` (None when it has none); ``INIT_FROM`` resolved against the file
    that set it."""
    sec = cfg.get("STAGE")
    if sec is None:
        return None
    settings = read_section(StageSection, sec, "STAGE")
    source = key_source(sec, "TRAIN")
    init_from = None
    if settings.init_from is not None:
        base = Path(key_source(sec, "INIT_FROM")).parent
        init_from = (base / settings.init_from).resolve()
        if not init_from.is_file():
            raise ConfigError(
                f"STAGE.INIT_FROM = {settings.init_from!r} (from {key_source(sec, 'INIT_FROM')}):"
                f" expected a config file; there is none at {init_from}"
            )
    train, freeze = settings.train, settings.freeze
    clash = [(t, f) for t in train for f in freeze if _under(t, f) or _under(f, t)]
    if clash:
        raise ConfigError(f"STAGE (from {source}): modules both trained and frozen: {clash}")
    return TrainingStage(settings.name, init_from, train, freeze, source)


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def stage_init_checkpoint(
    stage: TrainingStage,
    *,
    output_root: str | Path,
    extra_tag: str,
    pretrained_model: str | None,
    allow_partial: bool = False,
) -> Path:
    """The checkpoint the stage starts from: ``pretrained_model`` if given, else the newest
    checkpoint of the ``INIT_FROM`` config's run under ``extra_tag``, which must have trained
    that run's configured epochs unless ``allow_partial``.

    Raises:
        FileNotFoundError: no such checkpoint.
        ValueError: the predecessor's newest checkpoint is short of its configured epochs (naming
            the checkpoint, its epoch and the configured epochs).
    """
    if pretrained_model is not None:
        path = Path(pretrained_model)
        if not path.is_file():
            raise FileNotFoundError(
                f"stage {stage.name} ({stage.source}): --pretrained_model {path} does not exist"
            )
        return path
    if stage.init_from is None:
        raise ValueError(
            f"stage {stage.name} ({stage.source}) starts from a trained model: give "
            "STAGE.INIT_FROM or --pretrained_model"
        )
    predecessor = load_cfg(str(stage.init_from), None)
    ckpt_dir = output_dir_for(predecessor, output_root, extra_tag, ("ckpt", "folder"))
    found = find_latest_checkpoint(ckpt_dir)
    if found is None:
        raise FileNotFoundError(
            f"stage {stage.name} ({stage.source}) starts from its predecessor "
            f"{stage.init_from.name}, but {ckpt_dir} holds no checkpoint: train "
            f"{stage.init_from} with --extra_tag {extra_tag} first, or pass --pretrained_model"
        )
    if not allow_partial:
        epoch, configured, source = _predecessor_progress(found, predecessor, stage.init_from)
        if epoch < configured:
            raise ValueError(
                f"stage {stage.name} ({stage.source}) would start from {found}, trained "
                f"{epoch} of its {configured} configured epochs ({source}): finish "
                f"{stage.init_from} with --extra_tag {extra_tag} first, or pass "
                "--allow_partial_stage_init to start from it anyway"
            )
    return found


def _predecessor_progress(ckpt_path: Path, predecessor: Mapping, cfg_file: Path) -> tuple:
    """``(epochs trained, epochs configured, where the configured count comes from)`` of a
    predecessor's checkpoint: the ``NUM_EPOCHS`` its run had in effect (its ``train_settings``,
    ``--epochs`` included), else that of the predecessor's config file."""
    ckpt = read_checkpoint(ckpt_path)
    if type(ckpt.get("epoch")) is not int:
        raise ValueError(f"checkpoint {ckpt_path}: 'epoch' is {ckpt.get('epoch')!r}, not an int")
    recorded = ((ckpt.get("train_settings") or {}).get("OPTIMIZATION") or {}).get("NUM_EPOCHS")
    if recorded is not None:
        return ckpt["epoch"], int(recorded), "as its run had them in effect"
    configured = predecessor.get("OPTIMIZATION", {}).get("NUM_EPOCHS")
    if configured is None:
        raise ValueError(
            f"checkpoint {ckpt_path} records no NUM_EPOCHS and {cfg_file} sets no "
            "OPTIMIZATION.NUM_EPOCHS: cannot tell whether it finished its training (pass "
            "--allow_partial_stage_init to start from it anyway)"
        )
    return ckpt["epoch"], int(configured), f"OPTIMIZATION.NUM_EPOCHS of {cfg_file}"


def load_stage_init(model: nn.Module, stage: TrainingStage, checkpoint: str | Path) -> list[str]:
    """Load ``checkpoint`` into ``model`` for ``stage``; returns the parameters it did not hold
    (modules new in this stage, left at their initialisation).

    Raises:
        ValueError: a module of ``stage.freeze`` has parameters the checkpoint lacks (naming the
            stage, the module, the checkpoint and the missing keys).
        CheckpointMismatchError: unexpected or wrongly shaped parameters.
    """
    ckpt = read_checkpoint(checkpoint)
    state = ckpt["model_state"] if "model_state" in ckpt else ckpt
    own = model.state_dict()
    for name in stage.freeze:
        need = [k for k in own if _under(k, name)]
        missing = [k for k in need if k not in state]
        if missing:
            raise ValueError(
                f"stage {stage.name} ({stage.source}) freezes {name}, but checkpoint {checkpoint} "
                f"lacks {len(missing)} of its {len(need)} tensors (e.g. {missing[:3]}): it must "
                "come from the stage before"
            )
    unexpected = sorted(set(state) - set(own))
    if unexpected:
        load_state_dict_checked(model, state, strict=True, source=str(checkpoint))  # names them
    load_state_dict_checked(model, state, strict=False, source=str(checkpoint))
    return sorted(set(own) - set(state))


def apply_stage_freezing(model: nn.Module, stage: TrainingStage) -> list[str]:
    """Turn gradients off outside ``stage.train`` and keep those modules in eval mode while
    training; returns the names of the trainable parameters."""
    names = dict(model.named_modules())
    for name in (*stage.train, *stage.freeze):
        if name not in names:
            raise ConfigError(
                f"STAGE (from {stage.source}): {name!r} is not a module of "
                f"{type(model).__name__} (top-level: {[n for n in names if n and '.' not in n]})"
            )
    model.requires_grad_(False)
    for name in stage.train:
        names[name].requires_grad_(True)
    model.trainable_modules = stage.train
    model.train(model.training)
    return [n for n, p in model.named_parameters() if p.requires_grad]
