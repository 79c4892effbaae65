"""Evaluating one detector on ATLAS variants: Waymo L1/L2 AP/APH and attack metrics per variant.

Each variant is served by an ``AtlasWaymoDataset`` (the clean variant included, so every frame
carries its attack record); predictions of all processes are gathered in dataset order, so a
``torchrun`` evaluation gives the same numbers as one process. Rank 0 computes the metrics.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.distributed as torch_dist
from torch.utils.data import DataLoader

from pcdet_atlas.attacks.base import BaseAttack, build_attack
from pcdet_atlas.config import (
    REPO_ROOT,
    ConfigError,
    cfg_from_yaml_file,
    key_source,
    resolve_repo_path,
    to_plain,
)
from pcdet_atlas.config_values import declared_keys, read_section, setting
from pcdet_atlas.datasets.loader import ContiguousBatchSampler, worker_init_fn
from pcdet_atlas.datasets.multiframe import SequenceConfig
from pcdet_atlas.evaluation import build_variant_result, evaluate_attack
from pcdet_atlas.registry import DATASETS
from pcdet_atlas.train_utils.dist import get_dist_info, unwrap_model
from pcdet_atlas.train_utils.eval_caches import EvalCaches
from pcdet_atlas.train_utils.eval_utils import predict_dataset, write_prediction_files
from pcdet_atlas.utils.common import save_pickle
from pcdet_atlas.utils.hashing import file_sha256
from pcdet_atlas.utils.paths import safe_component
from pcdet_atlas.utils.seeding import torch_generator

__all__ = [
    "ATLAS_KEYS",
    "AtlasSection",
    "atlas_section",
    "trained_checkpoint",
    "resolve_variants",
    "build_variant_attacks",
    "attack_sha256",
    "variant_fingerprints",
    "variant_entry",
    "entry_summary",
    "loader_batches",
    "check_test_split",
    "build_attack_loader",
    "EvalContext",
    "evaluate_variant",
    "frames_to_compute",
    "input_attacked",
    "input_reach",
    "point_history",
]


@dataclass(frozen=True, kw_only=True)
class AtlasSection:
    """The ``ATLAS`` section of a model config: what its evaluation on the variants uses."""

    model_name: str | None = setting(
        None, doc="the model's name in results.json and the report (default: the config's name)"
    )
    attacks: tuple[str, ...] | None = setting(
        None, doc="the variants of --attacks all (names under cfgs/attacks/ or YAML paths)"
    )
    checkpoint: str | None = setting(
        None, doc="the default --ckpt (relative to the repository root)"
    )
    temporal_window: int | None = setting(None, ge=1, doc="the lifecycle window, in frames")
    training_seed: int | None = setting(
        None, doc="the seed of a checkpoint that does not record its own"
    )


#: the ``ATLAS`` section's keys
ATLAS_KEYS = tuple(declared_keys(AtlasSection))


def atlas_section(atlas_cfg: Mapping | None) -> AtlasSection:
    """A model config's ``ATLAS`` section (None or absent: every key at its default), read."""
    return read_section(AtlasSection, atlas_cfg, "ATLAS")


def trained_checkpoint(atlas_cfg: Mapping | None) -> Path | None:
    """The config's ``ATLAS.CHECKPOINT`` (relative to the repository root) when that file is
    there; None when the key is null or the file absent (a model not trained here)."""
    ckpt = atlas_section(atlas_cfg).checkpoint
    return resolve_repo_path(ckpt) if ckpt and resolve_repo_path(ckpt).is_file() else None


ATTACK_DIR = REPO_ROOT / "cfgs" / "attacks"


def resolve_variants(spec: str, atlas_cfg: Mapping) -> list[tuple[str, Path]]:
    """``--attacks`` -> ``[(variant, yaml path)]``, clean first.

    ``spec`` is ``all`` (the config's ``ATLAS.ATTACKS``) or a comma list of variant names (files
    ``cfgs/attacks/<name>.yaml``) and/or YAML paths. A variant names the folder of its results:
    a file name that is not one safe path component (``...yaml``: variant ``..``) is an
    ``UnsafePathError``.
    """
    settings = atlas_section(atlas_cfg)
    if spec == "all":
        if settings.attacks is None:
            raise ConfigError("--attacks all needs ATLAS.ATTACKS in the model config")
        names = list(settings.attacks)
    else:
        names = [s.strip() for s in spec.split(",") if s.strip()]
    if not names:
        raise ConfigError(f"--attacks {spec!r} names no variant")
    out = []
    for name in names:
        path = Path(name) if name.endswith((".yaml", ".yml")) else ATTACK_DIR / f"{name}.yaml"
        where = key_source(atlas_cfg, "ATTACKS") if spec == "all" else "--attacks"
        if not path.is_file():
            known = sorted(p.stem for p in ATTACK_DIR.glob("*.yaml"))
            raise ConfigError(
                f"attack variant {name!r} (from {where}): no file {path}; known variants: "
                f"{', '.join(known)}"
            )
        safe_component(path.stem, "attack variant (its file name)", f"{where}: {path}")
        out.append((path.stem, path.resolve()))
    if len({v for v, _ in out}) != len(out):
        raise ConfigError(f"--attacks {spec!r} names a variant twice")
    return sorted(out, key=lambda item: item[0] != "clean")


def check_test_split(
    data_cfg: Mapping, class_names: Sequence[str], logger: logging.Logger | None = None
) -> Path:
    """Load the test split once, so that a missing dataset or split fails before an evaluation
    writes anything; returns the dataset root (relative trace-library paths resolve under it)."""
    if "DATASET" not in data_cfg:
        raise ConfigError("DATA_CONFIG has no DATASET name")
    dataset = DATASETS.get(data_cfg["DATASET"])(
        dataset_cfg=data_cfg, class_names=class_names, training=False, logger=logger
    )
    return Path(dataset.root_path)


def build_variant_attacks(
    variants: Sequence[tuple[str, Path]], data_root: str | Path
) -> dict[str, BaseAttack]:
    """Load and build every variant's attack, before any inference.

    A variant is named by its file: the YAML's ``VARIANT`` must equal the file name without
    ``.yaml`` (it is the key of ``results.json`` and of the per-frame attack records).

    Raises:
        ConfigError: naming the file of the first variant whose YAML is invalid or whose
            ``VARIANT`` differs from its file name.
    """
    attacks = {}
    for name, path in variants:
        cfg = cfg_from_yaml_file(path)
        if "VARIANT" in cfg and str(cfg["VARIANT"]) != name:
            raise ConfigError(
                f"{path}: VARIANT {cfg['VARIANT']!r} (from {key_source(cfg, 'VARIANT')}) does not "
                f"match the file name; a variant is named by its file: set VARIANT: {name}"
            )
        attacks[name] = build_attack(cfg, data_root=data_root)
    return attacks


def attack_sha256(
    path: str | Path, attack: BaseAttack, *, library_sha256: Callable[[Path], str] = file_sha256
) -> str:
    """Hex SHA-256 of what a variant's predictions depend on besides the model and the data: its
    merged attack config (the YAML at ``path`` with its ``_BASE_CONFIG_`` chain) and, for an
    attack reading a trace library from a file (``attack.library_path``), that file's bytes
    (hashed by ``library_sha256``)."""
    merged = json.dumps(to_plain(cfg_from_yaml_file(path)), sort_keys=True)
    digest = hashlib.sha256(merged.encode())
    library = getattr(attack, "library_path", None)
    if library is not None:
        digest.update(f"\ntrace library {library_sha256(library)}".encode())
    return digest.hexdigest()


def variant_fingerprints(
    variants: Sequence[tuple[str, Path]], attacks: Mapping[str, BaseAttack]
) -> dict[str, str]:
    """``{variant: attack_sha256}`` of :func:`resolve_variants`' list and its built attacks; a
    trace library that several variants share (the injection ones) is hashed once."""
    library_hashes: dict[Path, str] = {}

    def library_sha256(library: Path) -> str:
        if library not in library_hashes:
            library_hashes[library] = file_sha256(library)
        return library_hashes[library]

    return {name: attack_sha256(path, attacks[name], library_sha256=library_sha256)
            for name, path in variants}  # fmt: skip


def input_reach(model: torch.nn.Module, data_cfg: Mapping) -> int:
    """How many frames before the current one a prediction of ``model`` on data of ``data_cfg``
    reads: the point history of a multi-frame input (``SEQUENCE_CONFIG``), plus, for a model
    reading earlier frames' proposals (PTT), those frames and each one's own point history."""
    return point_history(data_cfg) + int(getattr(unwrap_model(model), "proposal_history", 0) or 0)


def point_history(data_cfg: Mapping) -> int:
    """Frames before the current one whose points a sample of ``data_cfg`` holds (its
    ``SEQUENCE_CONFIG``; 0 for a single-frame input)."""
    sequence_cfg = SequenceConfig.from_config(data_cfg.get("SEQUENCE_CONFIG"))
    return sequence_cfg.num_frames - 1 if sequence_cfg is not None else 0


def frames_to_compute(dataset, reach: int) -> np.ndarray:
    """``(len(dataset),)`` booleans: True where the model input of a frame (the frame and the
    ``reach`` frames before it, clipped at the sequence start) holds a frame the variant's
    attack changes (its schedule spoofs it). From the schedule alone: nothing is simulated.
    A False frame's input is bitwise the clean input, so its prediction is the clean one."""
    if reach < 0:
        raise ValueError(f"reach must be >= 0, got {reach}")
    out = np.zeros(len(dataset.infos), dtype=bool)
    for i, info in enumerate(dataset.infos):
        sequence = info["point_cloud"]["lidar_sequence"]
        out[i] = input_attacked(dataset, sequence, int(info["point_cloud"]["sample_idx"]), reach)
    return out


def input_attacked(dataset, sequence_name: str, sample_idx: int, reach: int) -> bool:
    """Whether the variant's attack changes a frame or one of the ``reach`` frames before it
    (clipped at the sequence start), from the schedule alone."""
    num_frames = dataset.sequence_data(sequence_name).num_frames
    return any(
        dataset.attack.needs_simulation(j, num_frames)
        for j in range(max(0, sample_idx - reach), sample_idx + 1)
    )


def loader_batches(num_samples: int, batch_size: int, world_size: int) -> list[list[int]]:
    """The batches (dataset indices) that :func:`build_attack_loader` deals to all
    ``world_size`` processes in a full run, in index order; they do not depend on the workers."""
    return [
        batch
        for rank in range(world_size)
        for batch in ContiguousBatchSampler(num_samples, batch_size, 0, rank, world_size).batches
    ]


def build_attack_loader(
    data_cfg: Mapping,
    class_names: Sequence[str],
    attack: Mapping | Path | BaseAttack,
    *,
    batch_size: int,
    dist: bool,
    workers: int,
    seed: int,
    logger: logging.Logger | None = None,
    reuse_reach: int | None = None,
):
    """``(dataset, loader)`` of the test split under one attack variant (no shuffle; each worker
    and process reads a contiguous run of frames, see ``ContiguousBatchSampler``);
    ``attack`` is a built attack, a loaded attack YAML or the path of one.

    ``reuse_reach``: the model's :func:`input_reach`; the loader then yields only the batches
    holding a frame whose input the attack changes (:func:`frames_to_compute`, kept as
    ``loader.batch_sampler.compute``), in the composition they have in a full run."""
    dataset = DATASETS.get("AtlasWaymoDataset")(
        dataset_cfg=data_cfg, class_names=class_names, attack_cfg=attack, training=False,
        logger=logger,
    )  # fmt: skip
    compute = None if reuse_reach is None else frames_to_compute(dataset, reuse_reach)
    # each worker (and process) reads a contiguous run of frames: the attacked-frame cache then
    # serves a temporal input's history; predict_dataset restores the frame order
    rank, world = (torch_dist.get_rank(), torch_dist.get_world_size()) if dist else (0, 1)
    batch_sampler = ContiguousBatchSampler(
        len(dataset), batch_size, workers, rank, world, compute=compute
    )
    loader = DataLoader(
        dataset, batch_sampler=batch_sampler, num_workers=workers,
        collate_fn=dataset.collate_batch, pin_memory=torch.cuda.is_available(),
        worker_init_fn=functools.partial(worker_init_fn, seed=seed),
        # its own generator: a pass draws nothing from the global RNG (build_dataloader's note)
        generator=torch_generator(0 if seed is None else int(seed), "dataloader"),
    )  # fmt: skip
    return dataset, loader


@dataclass(frozen=True)
class EvalContext:
    """What the variants of one evaluation share: the test split's data config and class names,
    the device and process layout (``batch_size``: per process; ``dist``: under a process
    group), the loader (``workers``, ``seed``), the attack metrics' ``temporal_window``
    (``ATLAS.TEMPORAL_WINDOW``), the progress bar, ``save_to_file`` (one text file per frame,
    :func:`write_prediction_files`) and the logger of the per-variant line."""

    data_cfg: Mapping
    class_names: Sequence[str]
    device: torch.device
    batch_size: int = 1
    dist: bool = False
    workers: int = 0
    seed: int = 0
    temporal_window: int | None = None
    show_progress: bool = True
    save_to_file: bool = False
    logger: logging.Logger | None = None


def variant_entry(
    variant: str,
    dataset,
    det_annos: Sequence[Mapping],
    attack_infos: Sequence[Mapping],
    *,
    class_names: Sequence[str],
    clean_det_annos: Sequence[Mapping] | None,
    temporal_window: int | None,
    timings: dict[str, float],
    num_reused_frames: int | None = None,
    extra: Mapping | None = None,
) -> dict:
    """The ``results.json`` entry of one variant from its per-frame predictions ``det_annos``
    and their attack records, on the variant's ``AtlasWaymoDataset``: the Waymo metric (on a
    labelled split), the attack metrics (for an attack with targets) and their timing, added to
    ``timings``. Whoever made the predictions (a model of this package, or another toolkit's
    files) is scored by this one function."""
    family = attack_infos[0]["family"] if attack_infos else dataset.attack.family
    t1 = time.perf_counter()
    ap_dict = None  # a split without labels (Waymo test) gets attack metrics only
    if any("annos" in info for info in dataset.infos):  # an unlabelled frame among them: error
        _, ap_dict = dataset.evaluation(det_annos, class_names, eval_metric="waymo")
    attack_metrics = None
    if dataset.attack.SUCCESS_IF_DETECTED is not None:  # the attack class decides
        attack_metrics = evaluate_attack(
            det_annos, attack_infos, clean_det_annos=clean_det_annos, window=temporal_window,
            recorded_window=getattr(dataset.attack, "window", None),
        )  # fmt: skip
    timings["metric"] = time.perf_counter() - t1
    return build_variant_result(
        variant, family=family, num_frames=len(det_annos), metrics=ap_dict,
        class_names=class_names, attack=attack_metrics, rank_group=dataset.attack.RANK_GROUP,
        num_reused_frames=num_reused_frames,
        extra={"timing_s": {k: round(v, 3) for k, v in timings.items()},
               "clean_predictions": clean_det_annos is not None, **(extra or {})},
    )  # fmt: skip


def rescore_variant(
    variant: str,
    attack: Mapping | Path | BaseAttack,
    entry: Mapping,
    det_annos: Sequence[Mapping],
    context: EvalContext,
    *,
    clean_det_annos: Sequence[Mapping] | None,
) -> dict:
    """A finished variant's entry scored again from its stored predictions ``det_annos`` (each
    with its ``attack`` record, as ``result.pkl`` holds them) by this version's metric and
    analyses, so that a resumed run's entries are those one uninterrupted call would write
    (:func:`variant_entry`). What only the prediction pass knew is kept from ``entry``: the reuse
    count, the timings, the proposal bank's and prediction store's counts and the files' hashes.

    Raises:
        ValueError: ``det_annos`` do not cover the variant's test split frame for frame.
    """
    dataset = DATASETS.get("AtlasWaymoDataset")(
        dataset_cfg=context.data_cfg, class_names=context.class_names, attack_cfg=attack,
        training=False, logger=context.logger,
    )  # fmt: skip
    frame_ids = [info.get("frame_id") for info in dataset.infos]
    if len(det_annos) != len(frame_ids) or any(
        a.get("frame_id") != f for a, f in zip(det_annos, frame_ids)
    ):
        raise ValueError(
            f"{variant}: its stored predictions ({len(det_annos)} frames) are not the test "
            f"split's {len(frame_ids)} frames in order"
        )
    old = dict(entry.get("extra", {}))
    timing = old.pop("timing_s", {})
    old.pop("clean_predictions", None)
    rescored = variant_entry(
        variant, dataset, det_annos, [a["attack"] for a in det_annos],
        class_names=context.class_names, clean_det_annos=clean_det_annos,
        temporal_window=context.temporal_window, timings={},
        num_reused_frames=entry["num_reused_frames"], extra=old,
    )  # fmt: skip
    return {**rescored, "extra": {**rescored["extra"], "timing_s": timing}}


def entry_summary(variant: str, entry: Mapping) -> str:
    """One log line of a variant's entry: its L2 mAP/mAPH (or ``no labels``) and ASR."""
    asr, l2 = entry["asr"], entry["L2/mAP"]
    return (
        f"{variant}: "
        + ("no labels" if l2 is None else f"L2 mAP {l2:.4f} mAPH {entry['L2/mAPH']:.4f}")
        + ("" if asr is None else f" ASR {asr:.4f} ({entry['num_targets']} targets)")
    )


def evaluate_variant(
    model: torch.nn.Module,
    variant: str,
    attack: Mapping | Path | BaseAttack,
    context: EvalContext,
    *,
    caches: EvalCaches | None = None,
    out_dir: Path | None = None,
) -> tuple[dict | None, list[dict]]:
    """Predict one variant and score it.

    ``caches`` (:class:`~pcdet_atlas.train_utils.eval_caches.EvalCaches`, one per run; None:
    none) hold what the run knows already. With its clean predictions (predicted with the same
    batch size) and ``reuse``, the frames whose whole model input the attack leaves untouched
    (:func:`frames_to_compute` over the model's :func:`input_reach`) take the clean run's
    predictions instead of running the model; only the batches holding an attacked input run,
    in their full-run composition, so the result is bitwise that of a full run
    (docs/evaluation.md "Reusing clean predictions"). The entry's ``num_reused_frames`` /
    ``num_recomputed_frames`` count both kinds. The clean predictions also score the attack's
    confidence. For a model with a proposal history (PTT), the clean variant gives its proposal
    bank's frames to the caches, and a reusing run of another variant seeds its bank with those
    whose whole RPN batch has RPN inputs the attack leaves untouched
    (:meth:`EvalCaches.for_variant`). With the caches' prediction store, the entry's
    ``extra.prediction_store`` counts the batches it served and those it stored (all processes).

    Returns:
        ``(entry, det_annos)``: the ``results.json`` variant entry (None on ranks > 0; its
        ``extra.clean_predictions`` says whether clean predictions were known) and the
        detections (every rank). ``out_dir/result.pkl`` holds the detections with each frame's
        ``attack`` record (rank 0); with ``context.save_to_file`` also one text file per frame
        in ``out_dir/final_result/data/`` (:func:`write_prediction_files`).
    """
    ctx, logger = context, context.logger
    data_cfg, class_names = ctx.data_cfg, ctx.class_names
    rank, _ = get_dist_info()
    clean_det_annos = caches.clean_predictions if caches is not None else None
    reuse = caches is not None and caches.reuses_clean()
    reach = input_reach(model, data_cfg) if reuse else None
    dataset, loader = build_attack_loader(
        data_cfg, class_names, attack, batch_size=ctx.batch_size, dist=ctx.dist,
        workers=ctx.workers, seed=ctx.seed, logger=logger, reuse_reach=reach,
    )  # fmt: skip
    world = torch_dist.get_world_size() if ctx.dist else 1
    batches = loader_batches(len(dataset), ctx.batch_size, world)
    cache = None
    if caches is not None:
        rpn_reach = point_history(data_cfg)  # the RPN reads the sample's points only
        attacked = functools.cache(lambda seq, idx: input_attacked(dataset, seq, idx, rpn_reach))
        cache = caches.for_variant(dataset, batches, attacked)
    timings: dict = {}
    store_before = caches.store_counts() if caches is not None else None
    t0 = time.perf_counter()
    det_annos, extras = predict_dataset(
        model, loader, device=ctx.device, desc=variant, show_progress=ctx.show_progress,
        timings=timings, cache=cache,
    )  # fmt: skip
    timings["predict_wall"] = time.perf_counter() - t0
    bank_stats = timings.pop("bank", None)
    store_stats = caches.store_counts_since(store_before) if caches is not None else None
    if rank != 0:
        return None, det_annos
    reused = np.array([e["reused"] for e in extras], dtype=bool)
    if reuse and np.any(reused & loader.batch_sampler.compute):
        raise RuntimeError(f"{variant}: a frame with an attacked input took a clean prediction")
    attack_infos = [e["attack"] for e in extras]
    for anno, info in zip(det_annos, attack_infos):
        anno["attack"] = info
    entry = variant_entry(
        variant, dataset, det_annos, attack_infos, class_names=class_names,
        clean_det_annos=clean_det_annos, temporal_window=ctx.temporal_window, timings=timings,
        num_reused_frames=int(reused.sum()),
        extra={**({"proposal_bank": bank_stats} if bank_stats is not None else {}),
               **({"prediction_store": store_stats} if store_stats is not None else {})},
    )  # fmt: skip
    if out_dir is not None:
        save_pickle(det_annos, out_dir / "result.pkl")
        if ctx.save_to_file:
            write_prediction_files(det_annos, out_dir / "final_result" / "data")
    if logger is not None:
        logger.info(
            entry_summary(variant, entry)
            + f"  [data {timings.get('data', 0):.1f}s model {timings.get('model', 0):.1f}s "
            f"metric {timings['metric']:.1f}s]"
        )
    return entry, det_annos
