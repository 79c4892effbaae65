"""Inference over a dataset and its Waymo evaluation, single process or distributed."""

from __future__ import annotations

import copy
import logging
import time
from collections.abc import Sequence
from pathlib import Path

import torch
import tqdm
from torch import nn

from pcdet_atlas.models.batch import load_data_to_device
from pcdet_atlas.train_utils.cpu_memory import trim_cpu_memory
from pcdet_atlas.train_utils.dist import all_gather_objects, get_dist_info, unwrap_model
from pcdet_atlas.train_utils.eval_caches import VariantCache
from pcdet_atlas.train_utils.proposal_bank import ProposalBank
from pcdet_atlas.utils.files import write_atomic
from pcdet_atlas.utils.paths import join_under, safe_component

__all__ = ["predict_dataset", "eval_one_epoch", "write_prediction_files"]

#: on CPU, free heap memory goes back to the OS every this many batches (a process that keeps
#: freed memory for reuse, as tools/test.py does, would otherwise grow by fragmentation)
TRIM_EVERY_BATCHES = 20


@torch.no_grad()
def predict_dataset(
    model: nn.Module,
    dataloader,
    *,
    device: torch.device,
    desc: str = "eval",
    show_progress: bool = True,
    timings: dict | None = None,
    cache: VariantCache | None = None,
) -> tuple[list[dict], list[dict]]:
    """Run the model over the loader; gather every rank's results in dataset order.

    ``cache``: what the run's caches give this loader
    (:meth:`~pcdet_atlas.train_utils.eval_caches.EvalCaches.for_variant`). Its ``reused``
    predictions (anno dicts with ``frame_id``) stand for the frames the loader does not yield,
    as the clean run's do for the frames an attack leaves untouched
    (``ContiguousBatchSampler(compute=...)``): each such frame gets a copy of its reused
    prediction and, from an ``AtlasWaymoDataset``, its attack record (no simulation: the frame
    is clean). A frame neither yielded nor reused is an error. For a model reading earlier
    frames' proposals (its :class:`ProposalBank`), the bank proposes each frame with the frames
    of its batch in ``cache.batches`` (``ProposalBank(batches=...)``), starts from
    ``cache.proposal_seed`` (:meth:`ProposalBank.seed`) and gives its frames back at the end
    (``cache.proposals_out``, :meth:`ProposalBank.seedable`).

    Returns:
        ``(det_annos, extras)``: one OpenPCDet anno dict per frame of ``dataloader.dataset``
        (``frame_id`` order of ``dataset.infos``), and per frame ``{'frame_id', 'attack',
        'reused'}`` (the attack record of an ``AtlasWaymoDataset`` sample, None for a clean
        dataset; whether the prediction came from ``reuse``).
        ``timings`` (if given) accumulates seconds under ``'data'`` (loading, attack
        simulation included) and ``'model'`` (for a model with a proposal history, PTT, the
        proposal bank's RPN passes included: :class:`ProposalBank`), and then gets the bank's
        ``stats()`` under ``'bank'``.
    """
    dataset = dataloader.dataset
    rank, world = get_dist_info()
    model.eval()
    core = unwrap_model(model)
    bank = (  # models reading earlier frames' proposals: each frame's computed once
        ProposalBank(core, dataset, device=device, batches=cache.batches if cache else None)
        if getattr(core, "proposal_history", 0) else None
    )  # fmt: skip
    if bank is not None and cache is not None:
        cache.seed(bank)
    local: list[tuple[str, dict, dict]] = []
    bar = tqdm.tqdm(
        total=len(dataloader), desc=desc, leave=False, dynamic_ncols=True,
        disable=not show_progress or rank != 0,
    )  # fmt: skip
    t_end = time.perf_counter()
    for i, batch in enumerate(dataloader, 1):
        t0 = time.perf_counter()
        batch_dev = load_data_to_device(batch, device)
        if bank is not None:
            batch_dev = bank.attach(batch, batch_dev)
        pred_dicts = core.stored_predict(batch_dev)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t1 = time.perf_counter()
        annos = dataset.generate_prediction_dicts(batch, pred_dicts, dataset.class_names)
        attacks = batch.get("attack", [None] * len(annos))
        for anno, attack in zip(annos, attacks):
            extra = {"frame_id": anno["frame_id"], "attack": attack, "reused": False}
            local.append((anno["frame_id"], anno, extra))
        if timings is not None:
            timings["data"] = timings.get("data", 0.0) + (t0 - t_end)
            timings["model"] = timings.get("model", 0.0) + (t1 - t0)
        bar.update()
        if device.type == "cpu" and i % TRIM_EVERY_BATCHES == 0:
            trim_cpu_memory()  # bound a heap that retain_freed_cpu_memory keeps
        t_end = time.perf_counter()
    bar.close()
    if bank is not None and cache is not None:
        cache.keep(bank)
    if bank is not None and timings is not None:
        timings["bank"] = bank.stats()
    gathered = all_gather_objects(local) if world > 1 else [local]
    by_frame: dict[str, tuple[dict, dict]] = {}
    for part in gathered:
        for frame_id, anno, extra in part:
            by_frame.setdefault(frame_id, (anno, extra))  # DistributedSampler pads by repeating
    order = [info["frame_id"] for info in dataset.infos]
    if cache is not None and cache.reused is not None:
        _fill_reused(dataset, by_frame, cache.reused)
    missing = [f for f in order if f not in by_frame]
    if missing:
        raise RuntimeError(f"no predictions for {len(missing)} frames, e.g. {missing[:3]}")
    return [by_frame[f][0] for f in order], [by_frame[f][1] for f in order]


def _fill_reused(dataset, by_frame: dict, reuse: Sequence[dict]) -> None:
    """Put a copy of the reused prediction of every frame the loader did not yield into
    ``by_frame`` (with the frame's attack record when the dataset has an attack)."""
    reused = {str(anno["frame_id"]): anno for anno in reuse}
    for info in dataset.infos:
        frame_id = info["frame_id"]
        if frame_id in by_frame or frame_id not in reused:
            continue
        anno = copy.deepcopy({k: v for k, v in reused[frame_id].items() if k != "attack"})
        attack = None
        if hasattr(dataset, "frame_attack_meta"):
            point_cloud = info["point_cloud"]
            attack = dataset.frame_attack_meta(
                point_cloud["lidar_sequence"], int(point_cloud["sample_idx"])
            )
        by_frame[frame_id] = (anno, {"frame_id": frame_id, "attack": attack, "reused": True})


def eval_one_epoch(
    model: nn.Module,
    dataloader,
    *,
    device: torch.device,
    logger: logging.Logger | None = None,
    show_progress: bool = True,
) -> tuple[dict, list[dict]]:
    """Predict the whole split and compute Waymo L1/L2 AP/APH (every rank gets the result)."""
    det_annos, _ = predict_dataset(model, dataloader, device=device, show_progress=show_progress)
    dataset = dataloader.dataset
    _, ap_dict = dataset.evaluation(det_annos, dataset.class_names, eval_metric="waymo")
    if logger is not None:
        logger.info(
            "Waymo: " + ", ".join(f"{k} {float(v):.4f}" for k, v in ap_dict.items() if "/" in k)
        )
    return ap_dict, det_annos


def write_prediction_files(det_annos: Sequence[dict], out_dir: str | Path) -> Path:
    """``--save_to_file``: one ``<frame_id>.txt`` per frame in ``out_dir``, one line per box:
    ``name x y z dx dy dz heading [vx vy] score`` (LiDAR frame, metres and radians, the
    columns of ``boxes_lidar``; ``%.4f``). A frame without detections gets an empty file. A
    ``frame_id`` that is not one safe file name (``../x``), or a ``<frame_id>.txt`` already there
    that leads out of ``out_dir`` (a symlink), is an ``UnsafePathError``, before any file is
    written; each file is written whole (:func:`~pcdet_atlas.utils.files.write_atomic`), replacing
    a symlink inside ``out_dir`` rather than writing through it."""
    out_dir = Path(out_dir)
    paths = []
    for i, anno in enumerate(det_annos):
        frame_id = safe_component(anno["frame_id"], "frame_id", f"prediction {i}")
        paths.append(join_under(out_dir, (f"{frame_id}.txt", "prediction file"),
                                source=f"prediction {i}"))  # fmt: skip
    out_dir.mkdir(parents=True, exist_ok=True)
    for path, anno in zip(paths, det_annos):
        lines = [
            " ".join([str(name), *(f"{v:.4f}" for v in box), f"{score:.4f}"])
            for name, box, score in zip(anno["name"], anno["boxes_lidar"], anno["score"])
        ]
        text = "".join(f"{line}\n" for line in lines)
        write_atomic(path, lambda f, text=text: f.write(text.encode()), sync=False)
    return out_dir
