"""Detector3DTemplate: OpenPCDet's stage container, with explicit ``loss`` and ``predict``.

A detector is a sequence of stages in :attr:`Detector3DTemplate.module_topology` order; each stage
reads and writes keys of a per-call copy of the batch dict, so nothing is cached on ``self``
between ``forward`` and ``loss``. Each stage is registered in ``MODEL_STAGES`` and built from its
config section by ``Stage.from_config(section_cfg, model_info)``, where ``model_info`` carries
what earlier stages determined (feature widths, grid, strides).
"""

from __future__ import annotations

import pickle
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from pcdet_atlas.config import ConfigError, key_source
from pcdet_atlas.config_values import (
    config_files,
    config_value,
    read_section,
    section,
    setting,
    unsupported,
)
from pcdet_atlas.models.model_utils.polar_grid import PolarGrid
from pcdet_atlas.registry import MODEL_STAGES
from pcdet_atlas.utils.safe_pickle import RefusedGlobalError

# stage attribute -> its section in MODEL (OpenPCDet's names)
STAGE_CFG_KEYS = {
    "vfe": "VFE",
    "lot": "LOT",
    "backbone_3d": "BACKBONE_3D",
    "map_to_bev_module": "MAP_TO_BEV",
    "pfe": "PFE",
    "backbone_2d": "BACKBONE_2D",
    "dense_head": "DENSE_HEAD",
    "point_head": "POINT_HEAD",
    "roi_head": "ROI_HEAD",
}


def _text(value) -> str:
    if not isinstance(value, str):
        raise TypeError(value)
    return value


def _unset(value: float | None) -> bool:
    return value is None


@dataclass(frozen=True, kw_only=True)
class PostProcessingConfig:
    """``MODEL.POST_PROCESSING`` of a one-stage detector: OpenPCDet's keys, none of which
    changes its detections (its dense head's ``POST_PROCESSING`` does)."""

    recall_thresh_list: tuple[float, ...] = setting(
        (0.3, 0.5, 0.7), ge=0, le=1,
        doc="OpenPCDet's recall IoU thresholds; accepted, no recall is computed",
    )  # fmt: skip
    eval_metric: str = setting("waymo", choices=("waymo",), doc="waymo (the only one)")
    score_thresh: float | None = setting(
        None, check=_unset,
        expected="null (a one-stage detector's threshold is its DENSE_HEAD.POST_PROCESSING's)",
        doc="not read: set DENSE_HEAD.POST_PROCESSING.SCORE_THRESH",
    )  # fmt: skip
    output_raw_score: bool = unsupported("scores are output as probabilities")


@dataclass(frozen=True, kw_only=True)
class DetectorConfig:
    """The keys of ``MODEL`` besides its stage sections (``VFE``, ``DENSE_HEAD``, ...)."""

    name: str = setting(doc="registered detector class")
    post_processing: PostProcessingConfig = section(PostProcessingConfig)


class CheckpointMismatchError(RuntimeError):
    """A checkpoint whose parameters do not fit the model built from the config."""


def read_checkpoint(
    filename: str | Path, map_location: str = "cpu", *, safe_globals: Sequence = ()
) -> dict:
    """``torch.load(weights_only=True)`` a checkpoint file: tensors and plain values only, so
    that loading never runs code. ``safe_globals``: extra globals the file may name (as
    ``torch.serialization.safe_globals`` takes them), for formats known to need them.

    Raises:
        RefusedGlobalError: the file needs a global outside torch's allow-list (named).
        ValueError: a truncated or corrupt file (named).
    """
    path = Path(filename)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} not found")
    try:
        with torch.serialization.safe_globals(list(safe_globals)):
            ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except (EOFError, OSError, RuntimeError, pickle.UnpicklingError) as err:
        refused = _weights_only_refusal(err)
        if refused is not None:
            name, reason = refused
            raise RefusedGlobalError(
                f"checkpoint {path} refused: it needs {name} to load, and checkpoints are read "
                "with torch.load(weights_only=True), tensors and plain values only (loading "
                f"it could run code); torch: {reason}",
                path=str(path),
                name=name,
            ) from err
        raise ValueError(
            f"checkpoint {path} cannot be read ({path.stat().st_size} bytes; truncated or "
            f"corrupt?): {type(err).__name__}: {err}"
        ) from err
    if not isinstance(ckpt, Mapping):
        raise ValueError(f"checkpoint {path} holds a {type(ckpt).__name__}, not a dict of states")
    return ckpt


def model_state_of(ckpt: Mapping, source: str | Path) -> Mapping[str, torch.Tensor]:
    """A checkpoint's ``model_state`` (the checkpoint itself for a bare ``state_dict``).

    Raises:
        ValueError: ``model_state`` is not a mapping of names to tensors.
    """
    state = ckpt["model_state"] if "model_state" in ckpt else ckpt
    if not isinstance(state, Mapping):
        raise ValueError(
            f"checkpoint {source}: 'model_state' is a {type(state).__name__}, expected a "
            "mapping of parameter names to tensors (a model's state_dict())"
        )
    return state


def _weights_only_refusal(err: BaseException) -> tuple[str, str] | None:
    """``(what was refused, torch's reason)`` when ``err`` is torch's weights-only refusal
    (None for any other error)."""
    text = str(err)
    if not isinstance(err, pickle.UnpicklingError) or "Weights only load failed" not in text:
        return None
    found = re.search(r"WeightsUnpickler error: (.*)", text)
    reason = found.group(1).split(". Please use")[0].strip() if found else text.strip()
    named = re.search(r"GLOBAL (\S+)", reason) or re.search(r"got <class '([^']+)'>", reason)
    return (named.group(1) if named else "an object torch does not allow"), reason


def stage_model_info(stage: nn.Module, name: str, info: dict) -> None:
    """Update ``info`` in place with what ``stage`` (built as ``name``) tells later stages."""
    if name == "vfe":
        info["num_point_features"] = stage.get_output_feature_dim()
        if isinstance(stage.grid, PolarGrid):  # a polar VFE: the BEV grid comes later
            info["polar_grid"] = stage.grid
        else:
            info["voxel_size"] = stage.grid.voxel_size
            info["grid_size"] = stage.grid.grid_size
    if name == "backbone_3d" and hasattr(stage, "num_point_features"):
        info["num_point_features"] = stage.num_point_features
    if hasattr(stage, "bev_grid"):  # a stage that leaves polar cells for the Cartesian BEV
        info["voxel_size"] = stage.bev_grid.voxel_size
        info["grid_size"] = stage.bev_grid.grid_size
    if hasattr(stage, "num_bev_features"):
        info["num_bev_features"] = stage.num_bev_features
    if hasattr(stage, "output_stride"):
        # strides compose: a 2D backbone runs on the grid a 3D backbone leaves (8x for the
        # voxel backbones), so ``backbone_stride`` counts voxels per cell of the last map
        info["backbone_stride"] = info.get("backbone_stride", 1) * stage.output_stride


class Detector3DTemplate(nn.Module):
    """Base class: holds the stages and runs them in topology order.

    Subclasses implement :meth:`loss` and :meth:`predict` and list the stages they need in
    ``required_stages``.
    """

    module_topology = list(STAGE_CFG_KEYS)
    required_stages: tuple[str, ...] = ()
    #: the declaration of the ``MODEL`` keys besides the stage sections (a subclass that reads
    #: more declares a subclass of :class:`DetectorConfig`)
    CONFIG: type = DetectorConfig
    #: every batch key besides ``batch_size`` that :meth:`predict` reads; a detector that
    #: declares them can keep its predictions in a ``PredictionStore`` (``prediction_store``)
    prediction_inputs: tuple[str, ...] | None = None

    def __init__(self, *, class_names: Sequence[str], **stages: nn.Module | None):
        """
        Args:
            class_names: names of the classes, index ``i`` is label ``i + 1``.
            stages: modules keyed by the names in :attr:`module_topology` (missing ones are None).
        """
        super().__init__()
        unknown = set(stages) - set(self.module_topology)
        if unknown:
            raise ValueError(f"{type(self).__name__}: unknown stages {sorted(unknown)}")
        for name in self.required_stages:
            if stages.get(name) is None:
                raise ValueError(f"{type(self).__name__} needs a {name!r} stage")
        self.class_names = list(class_names)
        self.num_class = len(self.class_names)
        for name in self.module_topology:
            setattr(self, name, stages.get(name))
        #: module names that train (a training stage's ``STAGE.TRAIN``); None: all of them.
        #: The others stay in eval mode under ``train()``.
        self.trainable_modules: tuple[str, ...] | None = None
        #: where :meth:`stored_predict` keeps and finds predictions (a ``PredictionStore``)
        self.prediction_store = None

    @property
    def module_list(self) -> list[nn.Module]:
        """The built stages, in execution order."""
        return [m for m in (getattr(self, n) for n in self.module_topology) if m is not None]

    @classmethod
    def from_config(
        cls,
        model_cfg: Mapping,
        *,
        class_names: Sequence[str],
        point_cloud_range: Sequence[float],
        num_point_features: int,
        voxel_size: Sequence[float] | None = None,
        **extra,
    ) -> Detector3DTemplate:
        """Build the detector from a ``MODEL`` config section.

        Args:
            model_cfg: the ``MODEL`` section (``NAME``, one section per stage, ``POST_PROCESSING``).
            class_names: ``CLASS_NAMES``.
            point_cloud_range: ``DATA_CONFIG.POINT_CLOUD_RANGE`` (6 values, metres).
            num_point_features: point columns after the batch index (5, or 6 with time lag).
            extra: further keyword arguments of the subclass's constructor.
        """
        cls.read_config(model_cfg)
        info: dict = {
            "class_names": list(class_names),
            "num_rawpoint_features": int(num_point_features),
            "num_point_features": int(num_point_features),
            "point_cloud_range": tuple(float(v) for v in point_cloud_range),
        }
        if voxel_size is not None:  # OpenPCDet's DATA_PROCESSOR placeholder states it
            info["voxel_size"] = tuple(float(v) for v in voxel_size)
        stages: dict[str, nn.Module] = {}
        for name in cls.module_topology:
            stage_cfg = model_cfg.get(STAGE_CFG_KEYS[name])
            if stage_cfg is None:
                continue
            stage_name = config_value(
                stage_cfg, "NAME", _text, f"MODEL.{STAGE_CFG_KEYS[name]}",
                expected="a registered stage name",
            )  # fmt: skip
            stage_cls = MODEL_STAGES.get(stage_name)
            try:
                stages[name] = stage_cls.from_config(stage_cfg, info)
            except ConfigError:
                raise
            except ValueError as err:  # a value the stage rejects: say which section and file
                files = sorted({key_source(stage_cfg, k) for k in stage_cfg} - {"<unknown>"})
                raise ConfigError(
                    f"MODEL.{STAGE_CFG_KEYS[name]} ({', '.join(files) or 'built in code'}): {err}"
                ) from err
            stage_model_info(stages[name], name, info)
        return cls(class_names=class_names, **extra, **stages)

    @classmethod
    def read_config(cls, model_cfg: Mapping) -> DetectorConfig:
        """The ``MODEL`` section's own keys read into :attr:`CONFIG` (its stage sections are
        read by their stages); a required stage's section missing is an error."""
        stage_keys = sorted({STAGE_CFG_KEYS[n] for n in cls.module_topology})
        settings = read_section(cls.CONFIG, model_cfg, "MODEL", ignore=stage_keys)
        for name in cls.required_stages:
            if STAGE_CFG_KEYS[name] not in model_cfg:
                raise ConfigError(
                    f"missing required key MODEL.{STAGE_CFG_KEYS[name]} (a {cls.__name__} needs "
                    f"its {name} stage; in {config_files(model_cfg)})"
                )
        return settings

    def train(self, mode: bool = True) -> Detector3DTemplate:
        """``nn.Module.train``, keeping every module outside :attr:`trainable_modules` (and not
        containing one) in eval mode, so frozen batch norms keep their statistics."""
        super().train(mode)
        if mode and self.trainable_modules is not None:
            for name, module in self.named_modules():
                keep = not name or any(  # the detector itself, a trained module, or one above it
                    name == t or name.startswith(t + ".") or t.startswith(name + ".")
                    for t in self.trainable_modules
                )
                if not keep:
                    module.training = False
        return self

    # --------------------------------------------------------------------- running
    def run_stages(self, batch_dict: Mapping) -> dict:
        """Run every stage on a shallow copy of ``batch_dict`` and return the copy."""
        batch = dict(batch_dict)
        for stage in self.module_list:
            batch = stage(batch)
        return batch

    def loss(self, batch_dict: Mapping) -> dict[str, torch.Tensor]:
        raise NotImplementedError

    def predict(self, batch_dict: Mapping) -> list[dict[str, torch.Tensor]]:
        raise NotImplementedError

    def stored_predict(self, batch_dict: Mapping) -> list[dict[str, torch.Tensor]]:
        """:meth:`predict`, through ``prediction_store`` when one is set (the stored prediction
        of the same inputs, or a new one stored)."""
        if self.prediction_store is None:
            return self.predict(batch_dict)
        return self.prediction_store.predict(self, batch_dict)

    def forward(self, batch_dict: Mapping):
        """OpenPCDet's contract: training -> ``(ret_dict{'loss'}, tb_dict, disp_dict)``;
        eval -> ``(pred_dicts, recall_dict)`` (the recall dict is empty here)."""
        if self.training:
            losses = self.loss(batch_dict)
            tb_dict = {k: float(v.detach()) for k, v in losses.items()}
            return {"loss": losses["loss"]}, tb_dict, {}
        return self.predict(batch_dict), {}

    # ----------------------------------------------------------------- checkpoints
    def load_params_from_file(
        self, filename: str | Path, *, strict: bool = True, map_location: str = "cpu"
    ) -> dict:
        """Load ``model_state`` from an OpenPCDet-style checkpoint; returns the checkpoint dict.

        Raises:
            CheckpointMismatchError: naming missing, unexpected and wrongly shaped parameters
                (with ``strict=False`` only the shape mismatches raise, and a checkpoint that
                shares no parameter name with the model).
            ValueError: NaN/inf weights (naming them), or a file that is corrupt or not a
                plain checkpoint (:func:`read_checkpoint`).
        """
        ckpt = read_checkpoint(filename, map_location)
        state = model_state_of(ckpt, filename)
        load_state_dict_checked(self, state, strict=strict, source=str(filename))
        return ckpt


def load_state_dict_checked(
    model: nn.Module, state: Mapping[str, torch.Tensor], *, strict: bool, source: str
) -> None:
    """``model.load_state_dict`` with one readable error listing every mismatch; non-finite
    weights are refused (:func:`check_finite_state`)."""
    own = model.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    bad_shape = [
        f"{k}: checkpoint {tuple(state[k].shape)} vs model {tuple(own[k].shape)}"
        for k in sorted(set(own) & set(state))
        if tuple(state[k].shape) != tuple(own[k].shape)
    ]
    if not strict and own and not set(own) & set(state):
        raise CheckpointMismatchError(
            f"checkpoint {source} shares no parameter name with {type(model).__name__} built "
            f"from the config (its first keys: {sorted(state)[:5]}): nothing would load"
        )
    problems = (
        bad_shape
        + ([] if not strict else [f"missing {k}" for k in missing])
        + ([] if not strict else [f"unexpected {k}" for k in unexpected])
    )
    if problems:
        head = "; ".join(problems[:10]) + (
            f"; ... ({len(problems)} in all)" if len(problems) > 10 else ""
        )
        raise CheckpointMismatchError(
            f"checkpoint {source} does not match {type(model).__name__} built from the "
            f"config: {head}"
        )
    loaded = {k: v for k, v in state.items() if k in own}
    check_finite_state(loaded, source)
    model.load_state_dict(loaded, strict=strict)


def check_finite_state(state: Mapping[str, torch.Tensor], source: str) -> None:
    """Refuse floating-point tensors holding NaN or inf: the model would load and then detect
    nothing (a diverged or corrupt training), scoring 0 without an error.

    Raises:
        ValueError: naming ``source`` and each such tensor with its count of bad values.
    """
    bad = [
        f"{k} ({int((~torch.isfinite(v)).sum())} of {v.numel()} values)"
        for k, v in state.items()
        if isinstance(v, torch.Tensor)
        and (v.is_floating_point() or v.is_complex())
        and not bool(torch.isfinite(v).all())
    ]
    if bad:
        head = ", ".join(bad[:10]) + (f", ... ({len(bad)} tensors in all)" if len(bad) > 10 else "")
        raise ValueError(
            f"checkpoint {source} holds non-finite (NaN/inf) weights in {head}: a diverged or "
            "corrupt training; expected finite values (use an earlier checkpoint)"
        )
