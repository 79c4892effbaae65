"""Training proposals of two-stage models: the RPN's detections on the clean train split,
computed once and cached on disk (as the MSF repository's ``result.pkl`` dump).

The cache file's name holds a key of everything that decides its content: the RPN checkpoint's
SHA-256, the RPN's whole resolved config (``CLASS_NAMES`` and ``MODEL``, its ``_BASE_CONFIG_``
files merged in, and its data config on this dataset), the dataset root, the split and the
split's :func:`~pcdet_atlas.datasets.fingerprint.dataset_fingerprint` (its info pkls and frame
files). A changed RPN, RPN setting (``SCORE_THRESH``, say) or dataset therefore never serves
stale proposals: it gets a new file. The file records the same facts and they are checked again
when it is read. Layout: ``<CACHE_DIR>/<rpn config stem>-<key>/<split>.pt``, a torch file of
plain values and tensors read with ``torch.load(weights_only=True)`` (it cannot carry code), with
``{'format', 'rpn_checkpoint_sha256', 'rpn_cfg', 'rpn_model_config', 'rpn_data_config',
'data_path', 'split', 'dataset_fingerprint', 'proposals'}``,
``proposals[frame_id]`` float32 ``(R, 11)`` ``[x, y, z, dx, dy, dz, heading, vx, vy, score,
label]`` (a tensor on disk, a numpy array once read; docs/getting_started.md, two-stage models).
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

from pcdet_atlas.config import cfg_from_yaml_file, key_source, resolve_repo_path, to_plain
from pcdet_atlas.datasets import build_dataloader
from pcdet_atlas.datasets.fingerprint import data_config_fingerprint
from pcdet_atlas.models.detectors.two_stage import TwoStageDetector
from pcdet_atlas.train_utils.dist import get_dist_info
from pcdet_atlas.train_utils.eval_utils import predict_dataset
from pcdet_atlas.utils.common import write_atomic
from pcdet_atlas.utils.paths import safe_component

__all__ = ["PROPOSAL_FORMAT", "proposal_cache_file", "training_proposals"]

PROPOSAL_FORMAT = 3
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


def _identity(model: TwoStageDetector, rpn_cfg: Mapping, rpn_data: Mapping, split: str) -> dict:
    """What decides the cached proposals (module docstring); the dataset fingerprint reads the
    split's info pkls and stats its frame files, once per call."""
    return {
        "rpn_checkpoint_sha256": model.rpn_info["sha256"],
        "rpn_cfg": model.rpn_info["cfg"],
        "rpn_model_config": to_plain({k: rpn_cfg[k] for k in ("CLASS_NAMES", "MODEL")}),
        "rpn_data_config": to_plain(rpn_data),
        "data_path": str(rpn_data["DATA_PATH"]),
        "split": split,
        "dataset_fingerprint": data_config_fingerprint(rpn_data, "train"),
    }


def _cache_file(model: TwoStageDetector, ident: Mapping, split: str,
                cache_dir: str | Path | None = None) -> Path:  # fmt: skip
    key = hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()[:16]
    root = resolve_repo_path(cache_dir or model.rpn_info.get("cache_dir") or DEFAULT_CACHE_DIR)
    name = safe_component(split, "split", "the proposal cache's file name")
    return root / f"{Path(model.rpn_info['cfg']).stem}-{key}" / f"{name}.pt"


def proposal_cache_file(model: TwoStageDetector, data_cfg: Mapping, split: str,
                        cache_dir: str | Path | None = None) -> Path:  # fmt: skip
    """Where the proposals of ``split`` by ``model``'s RPN are cached (module docstring)."""
    rpn_cfg, rpn_data = _rpn_data_config(model, data_cfg, split)
    return _cache_file(model, _identity(model, rpn_cfg, rpn_data, split), split, cache_dir)


def _write(path: Path, ident: Mapping, proposals: Mapping[str, np.ndarray]) -> None:
    tensors = {str(frame_id): torch.from_numpy(boxes) for frame_id, boxes in proposals.items()}
    plain = json.loads(json.dumps(ident))  # numpy floats of the config as Python floats
    data = {"format": PROPOSAL_FORMAT, **plain, "proposals": tensors}
    write_atomic(path, lambda f: torch.save(data, f))


def _read(path: Path, ident: Mapping) -> dict[str, np.ndarray]:
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:  # needs more than tensors and plain values
        raise ValueError(
            f"{path}: not a proposal cache (it needs more than tensors and plain values to load, "
            f"and loading it could run code): {err}"
        ) from err
    except (EOFError, OSError, RuntimeError) as err:
        raise ValueError(f"{path}: cannot be read (delete it to recompute): {err}") from err
    if not isinstance(data, Mapping) or data.get("format") != PROPOSAL_FORMAT:
        raise ValueError(f"{path}: not a proposal cache of format {PROPOSAL_FORMAT}")
    for key, want in ident.items():
        got = data.get(key)
        if got != want:
            if isinstance(want, Mapping) and isinstance(got, Mapping):  # name the keys, not all
                detail = f"cached for another {key}: differs at {', '.join(_differing(got, want))}"
            else:
                detail = f"cached for {key} = {got!r}, this run needs {want!r}"
            raise ValueError(f"{path}: {detail} (delete the file to recompute it)")
    return {frame_id: boxes.numpy() for frame_id, boxes in data["proposals"].items()}


def _differing(a: Mapping, b: Mapping, prefix: str = "") -> list[str]:
    """The dotted keys at which two nested mappings differ."""
    out = []
    for key in sorted(a.keys() | b.keys(), key=str):
        x, y, name = a.get(key), b.get(key), f"{prefix}{key}"
        if isinstance(x, Mapping) and isinstance(y, Mapping):
            out += _differing(x, y, name + ".")
        elif x != y:
            out.append(name)
    return out


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
    safe_component(split, "DATA_SPLIT.train", key_source(data_cfg, "DATA_SPLIT"))
    rpn_cfg, rpn_data = _rpn_data_config(model, data_cfg, split)
    ident = _identity(model, rpn_cfg, rpn_data, split)
    path = _cache_file(model, ident, split)
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
        _write(path, ident, proposals)
    return proposals, path
