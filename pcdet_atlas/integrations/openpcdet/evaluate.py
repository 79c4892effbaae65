"""An OpenPCDet checkpoint on ATLAS variants, scored into ``results.json``
(``tools/openpcdet_test.py``).

The model is OpenPCDet's own (``pcdet.models.build_network`` from the config's ``MODEL``; its
weights read once with ``weights_only=True`` and loaded as ``load_params_from_file`` loads
them), fed by OpenPCDet's own loader (``pcdet.datasets.build_dataloader``)
over :class:`~pcdet_atlas.integrations.openpcdet.dataset.AtlasWaymoDataset`, and run as
OpenPCDet's ``eval_one_epoch`` runs it (``load_data_to_gpu``, ``model(batch_dict)`` under
``no_grad``, ``generate_prediction_dicts``). Each variant's predictions and the attack records
the loader served with them are then scored by
:func:`pcdet_atlas.train_utils.score_predictions.score_variant`, the scoring of
``tools/evaluate_predictions.py``, on the same split read by this package's ``WaymoDataset``.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from pcdet.datasets import build_dataloader
from pcdet.models import build_network, load_data_to_gpu

from pcdet_atlas.attacks.base import BaseAttack
from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.evaluation import build_results, save_results
from pcdet_atlas.integrations.openpcdet.dataset import RECORD_KEY, attack_data_cfg
from pcdet_atlas.models.detectors.detector3d_template import read_checkpoint
from pcdet_atlas.models.openpcdet_checkpoint import OPENPCDET_SAFE_GLOBALS
from pcdet_atlas.train_utils.atlas_eval import (
    ATTACK_DIR,
    build_variant_attacks,
    resolve_variants,
    variant_fingerprints,
)
from pcdet_atlas.train_utils.score_predictions import score_variant
from pcdet_atlas.utils.common import save_pickle

__all__ = [
    "SPLIT_KEYS",
    "default_temporal_window",
    "evaluate_openpcdet",
    "load_checkpoint_weights",
    "predict_variant",
    "split_data_cfg",
]

#: the OpenPCDet DATA_CONFIG keys that decide the split's frames and labels, copied onto this
#: package's Waymo DATA_CONFIG for scoring
SPLIT_KEYS = ("DATA_PATH", "PROCESSED_DATA_TAG", "DATA_SPLIT", "SAMPLED_INTERVAL",
              "POINT_CLOUD_RANGE", "DISABLE_NLZ_FLAG_ON_POINTS")  # fmt: skip
WAYMO_DATA_CFG = REPO_ROOT / "cfgs" / "dataset_configs" / "waymo_dataset.yaml"


def load_checkpoint_weights(
    model: torch.nn.Module, checkpoint: Mapping, source: str, logger: logging.Logger
) -> None:
    """Load an OpenPCDet checkpoint's ``model_state`` (already read, ``weights_only``) into
    ``model`` as OpenPCDet's ``load_params_from_file`` does after its own ``torch.load``: through
    the detector's ``_load_state_dict(state, strict=False)`` (which lays out spconv weights
    for the installed spconv), logging the weights the file does not update."""
    state = checkpoint.get("model_state") if isinstance(checkpoint, Mapping) else None
    if not isinstance(state, Mapping):
        raise ValueError(
            f"checkpoint {source}: no 'model_state' mapping (an OpenPCDet checkpoint holds the "
            "weights under 'model_state')"
        )
    if not hasattr(model, "_load_state_dict"):
        raise TypeError(
            f"{type(model).__name__} has no _load_state_dict: OpenPCDet's detectors inherit it "
            "from Detector3DTemplate, which tools/openpcdet_test.py expects"
        )
    if checkpoint.get("version") is not None:
        logger.info(f"==> Checkpoint trained from version: {checkpoint['version']}")
    state_dict, updated = model._load_state_dict(dict(state), strict=False)
    for key in state_dict:
        if key not in updated:
            logger.info(f"Not updated weight {key}: {tuple(state_dict[key].shape)}")
    logger.info(f"==> {source}: loaded {len(updated)}/{len(state_dict)}")


def split_data_cfg(data_cfg: Mapping, root_path: str | Path | None = None):
    """This package's Waymo ``DATA_CONFIG`` reading the split an OpenPCDet ``DATA_CONFIG``
    reads (its :data:`SPLIT_KEYS`; ``root_path``: the data root, as OpenPCDet's
    ``build_dataloader`` takes it)."""
    out = cfg_from_yaml_file(WAYMO_DATA_CFG)
    for key in SPLIT_KEYS:
        if key in data_cfg:
            out[key] = copy.deepcopy(data_cfg[key])
    if root_path is not None:
        out["DATA_PATH"] = str(root_path)
    return out


def default_temporal_window(data_cfg: Mapping) -> int:
    """Input frames of an OpenPCDet ``DATA_CONFIG``: ``SEQUENCE_CONFIG.SAMPLE_OFFSET`` span + 1
    where the sequence input is enabled, else 1 (the lifecycle analysis' window)."""
    sequence_cfg = data_cfg.get("SEQUENCE_CONFIG")
    if sequence_cfg is None or not sequence_cfg.get("ENABLED", False):
        return 1
    first, last = sequence_cfg["SAMPLE_OFFSET"]
    return int(last - first) + 1


def _variants(spec: str) -> list[tuple[str, Path]]:
    """``--attacks``: ``all`` is every ``cfgs/attacks/*.yaml`` (clean and the 12 attacks)."""
    if spec == "all":
        spec = ",".join(sorted(p.stem for p in ATTACK_DIR.glob("*.yaml")))
    return resolve_variants(spec, {})


def predict_variant(
    model: torch.nn.Module,
    loader,
    class_names: Sequence[str],
) -> tuple[list[dict], dict[str, dict]]:
    """Run an OpenPCDet model over one variant's loader as OpenPCDet's ``eval_one_epoch``
    does; its per-frame prediction dicts (``generate_prediction_dicts``) and attack records
    by ``frame_id``."""
    det_annos, records = [], {}
    dataset = loader.dataset
    for batch_dict in loader:
        batch_records = batch_dict.pop(RECORD_KEY)
        load_data_to_gpu(batch_dict)
        with torch.no_grad():
            pred_dicts, _ = model(batch_dict)
        annos = dataset.generate_prediction_dicts(batch_dict, pred_dicts, class_names, None)
        for anno, record in zip(annos, batch_records):
            records[anno["frame_id"]] = record
        det_annos += annos
    return det_annos, records


def evaluate_openpcdet(
    cfg: Mapping,
    ckpt: str | Path,
    attacks: str,
    out_dir: str | Path,
    *,
    config: str,
    model_name: str,
    batch_size: int = 1,
    workers: int = 0,
    root_path: str | Path | None = None,
    device: str = "cuda",
    temporal_window: int | None = None,
    logger: logging.Logger | None = None,
) -> dict:
    """Run an OpenPCDet checkpoint on every variant of ``attacks`` (``all`` or a comma list,
    as ``tools/test.py --attacks``) and write ``out_dir/results.json`` (rewritten after each
    variant, clean first) and ``out_dir/<variant>/result.pkl``.

    Args:
        cfg: an OpenPCDet model config (loaded by OpenPCDet's ``cfg_from_yaml_file``):
            ``CLASS_NAMES``, ``DATA_CONFIG`` (of OpenPCDet's ``WaymoDataset``), ``MODEL``.
        config, model_name: the ``results.json`` ``config`` and ``model`` fields.
        temporal_window: the lifecycle window; None: :func:`default_temporal_window`.
    """
    logger = logger or logging.getLogger("pcdet_atlas")
    # read once, with weights_only=True, before anything else is built: a file that could run
    # code is refused (named), and the weights loaded below are the ones read here (OpenPCDet's
    # load_params_from_file would unpickle the file again, as torch.load does by default)
    checkpoint = read_checkpoint(ckpt, safe_globals=OPENPCDET_SAFE_GLOBALS)
    class_names = list(cfg["CLASS_NAMES"])
    variants = _variants(attacks)
    split_cfg = split_data_cfg(cfg["DATA_CONFIG"], root_path)
    built: dict[str, BaseAttack] = build_variant_attacks(variants, split_cfg["DATA_PATH"])
    fingerprints = variant_fingerprints(variants, built)
    window = (
        default_temporal_window(cfg["DATA_CONFIG"]) if temporal_window is None else temporal_window
    )
    out_dir = Path(out_dir)
    model = None
    entries: dict = {}
    clean = None
    results: dict = {}
    for name, _ in variants:
        _, loader, _ = build_dataloader(
            dataset_cfg=attack_data_cfg(cfg["DATA_CONFIG"], built[name]), class_names=class_names,
            batch_size=batch_size, dist=False, root_path=root_path, workers=workers,
            logger=logger, training=False,
        )  # fmt: skip
        if model is None:  # OpenPCDet's test.py builds it once, on the test set
            model = build_network(
                model_cfg=cfg["MODEL"], num_class=len(class_names), dataset=loader.dataset
            )
            load_checkpoint_weights(model, checkpoint, str(ckpt), logger)
            model.to(torch.device(device))
            model.eval()
        det_annos, records = predict_variant(model, loader, class_names)
        result_pkl = save_pickle(det_annos, out_dir / name / "result.pkl")
        entry, scored = score_variant(
            split_cfg, class_names, name, built[name], det_annos, source=str(result_pkl),
            clean_det_annos=clean, temporal_window=window, records=records,
            records_source="the OpenPCDet loader", logger=logger,
        )  # fmt: skip
        if name == "clean":
            clean = scored
        entries[name] = {**entry, "extra": {**entry["extra"], "attack_sha256": fingerprints[name]}}
        results = build_results(
            model=model_name, config=config, checkpoint=str(ckpt), class_names=class_names,
            variants=entries, extra={"scored_from": "openpcdet",
                                     "variants_requested": [n for n, _ in variants]},
        )  # fmt: skip
        save_results(results, out_dir / "results.json")
    return results
