"""Training proposals of two-stage models: the RPN's detections on the clean train split,
computed once and cached on disk (as the MSF repository's ``result.pkl`` dump).

The cache file's name holds a key of everything that decides its content: the RPN checkpoint's
SHA-256, the RPN's resolved config, the dataset root and the split. A changed RPN therefore
never serves stale proposals: it gets a new file. The file records the same facts and they are
checked again when it is read. Layout: ``<CACHE_DIR>/<rpn config stem>-<key>/<split>.pkl`` with
``{'format', 'rpn_checkpoint_sha256', 'rpn_cfg', 'data_path', 'split', 'proposals'}``,
``proposals[frame_id]`` float32 ``(R, 11)`` ``[x, y, z, dx, dy, dz, heading, vx, vy, score,
label]`` (docs/getting_started.md, two-stage models).
"""

from __future__ import annotations

import copy
import hashlib
import json
import logging
import pickle
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from pcdet_atlas.config import cfg_from_yaml_file, resolve_repo_path, to_plain
from pcdet_atlas.datasets import build_dataloader
from pcdet_atlas.models.detectors.two_stage import TwoStageDetector
from pcdet_atlas.train_utils.dist import get_dist_info
from pcdet_atlas.train_utils.eval_utils import predict_dataset
from pcdet_atlas.utils.common import save_pickle

__all__ = ["PROPOSAL_FORMAT", "proposal_cache_file", "training_proposals"]

PROPOSAL_FORMAT = 1
DEFAULT_CACHE_DIR = "output/rpn_proposals"


def _rpn_data_config(model: TwoStageDetector, data_cfg: Mapping, split: str):
    """The RPN's own data config (its frames, features and processors) on this model's data
    root and ``split``, every frame (interval 1), test mode (no augmentation)."""
    rpn_cfg = cfg_from_yaml_file(resolve_repo_path(model.rpn_info["cfg"]))
    rpn_data = copy.deepcopy(rpn_cfg.DATA_CONFIG)
    rpn_data.DATA_PATH = str(resolve_repo_path(data_cfg.DATA_PATH))
    rpn_data.DATA_SPLIT = {"train": split, "test": split}
    rpn_data.SAMPLED_INTERVAL = {"train": 1, "test": 1}
    return rpn_cfg, rpn_data


def _identity(model: TwoStageDetector, rpn_data: Mapping, split: str) -> dict:
    return {
        "rpn_checkpoint_sha256": model.rpn_info["sha256"],
        "rpn_cfg": model.rpn_info["cfg"],
        "rpn_data_config": to_plain(rpn_data),
        "data_path": str(rpn_data["DATA_PATH"]),
        "split": split,
    }


def proposal_cache_file(model: TwoStageDetector, data_cfg: Mapping, split: str,
                        cache_dir: str | Path | None = None) -> Path:  # fmt: skip
    """Where the proposals of ``split`` by ``model``'s RPN are cached (module docstring)."""
    _, rpn_data = _rpn_data_config(model, data_cfg, split)
    ident = _identity(model, rpn_data, split)
    key = hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()[:16]
    root = resolve_repo_path(cache_dir or model.rpn_info.get("cache_dir") or DEFAULT_CACHE_DIR)
    return root / f"{Path(model.rpn_info['cfg']).stem}-{key}" / f"{split}.pkl"


def _read(path: Path, ident: Mapping) -> dict[str, np.ndarray]:
    with open(path, "rb") as fh:
        data = pickle.load(fh)
    if not isinstance(data, Mapping) or data.get("format") != PROPOSAL_FORMAT:
        raise ValueError(f"{path}: not a proposal cache of format {PROPOSAL_FORMAT}")
    for key, want in ident.items():
        if data.get(key) != want:
            raise ValueError(
                f"{path}: cached for {key} = {data.get(key)!r}, this run needs {want!r} (delete "
                "the file to recompute it)"
            )
    return data["proposals"]


@torch.no_grad()
def training_proposals(
    model: TwoStageDetector,
    data_cfg: Mapping,
    class_names,
    *,
    device: torch.device,
    batch_size: int = 1,
    workers: int = 0,
    logger: logging.Logger | None = None,
) -> tuple[dict[str, np.ndarray], Path]:
    """The RPN's proposals for every frame of the train split (``DATA_SPLIT.train``), read from
    the cache or computed (all ranks compute their share; rank 0 writes) and cached.

    Returns ``(proposals by frame_id, cache file)``.
    """
    logger = logger or logging.getLogger(__name__)
    split = str(data_cfg.DATA_SPLIT["train"])
    rpn_cfg, rpn_data = _rpn_data_config(model, data_cfg, split)
    ident = _identity(model, rpn_data, split)
    path = proposal_cache_file(model, data_cfg, split)
    if path.is_file():
        logger.info(f"training proposals: {path} (cached)")
        return _read(path, ident), path
    rank, world = get_dist_info()
    logger.info(
        f"training proposals: running the RPN ({model.rpn_info['cfg']}, checkpoint sha256 "
        f"{model.rpn_info['sha256'][:12]}) on the clean {split} split -> {path}"
    )
    _, loader, _ = build_dataloader(
        rpn_data, class_names, batch_size, world > 1, workers=workers, logger=logger,
        training=False,
    )  # fmt: skip
    det_annos, _ = predict_dataset(model.rpn, loader, device=device, desc="proposals")
    proposals = {}
    for anno in det_annos:
        boxes = np.asarray(anno["boxes_lidar"], dtype=np.float32).reshape(len(anno["score"]), -1)
        if boxes.shape[1] < 9:
            raise ValueError(
                f"RPN {model.rpn_info['cfg']} predicts no velocity (boxes {boxes.shape})"
            )
        proposals[anno["frame_id"]] = np.concatenate(
            [boxes[:, :9], anno["score"].reshape(-1, 1), anno["pred_labels"].reshape(-1, 1)], 1
        ).astype(np.float32)
    if rank == 0:
        save_pickle({"format": PROPOSAL_FORMAT, **ident, "proposals": proposals}, path)
    return proposals, path
