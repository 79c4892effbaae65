"""The evaluation run behind ``tools/test.py``: one detector's checkpoints on ATLAS variants, each
variant's Waymo L2 mAP/mAPH and attack metrics written to ``results.json``.

:class:`EvalSettings` says what a call asks for (the tool's flags, by meaning).
:func:`run_evaluation` checks everything before anything is written (every variant YAML, the
test split, the first checkpoint and the evaluation folders: :mod:`.eval_folder`), then
evaluates each checkpoint's variants in turn, the clean one first, rewriting ``results.json``
after each (a failure keeps the variants done). The run's caches (:class:`.EvalCaches`: the
clean run's predictions and proposals, the prediction store) are built once and consulted by
each variant. With ``resume``, the variants an earlier call finished are kept
(:func:`.finished_variants`): their predictions are read back and scored again by this version
(:func:`~.atlas_eval.rescore_variant`), and the clean one's proposals are read back for the
others.
"""

from __future__ import annotations

import contextlib
import datetime
import hashlib
import logging
import shutil
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.distributed as torch_dist

from pcdet_atlas.attacks.base import BaseAttack
from pcdet_atlas.config import REPO_ROOT, repo_relative, save_config
from pcdet_atlas.datasets.fingerprint import data_config_fingerprint
from pcdet_atlas.evaluation import build_results, format_table, save_results
from pcdet_atlas.models import build_network_from_config
from pcdet_atlas.models.prediction_store import PredictionStore, use_prediction_store
from pcdet_atlas.train_utils.atlas_eval import (
    EvalContext,
    atlas_section,
    build_variant_attacks,
    check_test_split,
    evaluate_variant,
    rescore_variant,
    resolve_variants,
    variant_fingerprints,
)
from pcdet_atlas.train_utils.checkpoint import (
    list_epoch_checkpoints,
    model_config_sha256,
    training_seed,
)
from pcdet_atlas.train_utils.dist import all_gather_objects
from pcdet_atlas.train_utils.eval_caches import EvalCaches
from pcdet_atlas.train_utils.eval_folder import (
    check_eval_dir,
    eval_dir,
    finished_variants,
    proposal_hashes,
    proposal_part,
    resolve_checkpoint,
)
from pcdet_atlas.train_utils.eval_utils import write_prediction_files
from pcdet_atlas.train_utils.setup import (
    DEFAULT_SEED,
    DEFAULT_TCP_PORT,
    DEFAULT_WORKERS,
    load_cfg,
    lock_output_folder,
    output_dir_for,
    require_dataset,
    setup_runtime,
)
from pcdet_atlas.utils.common import create_logger, save_pickle
from pcdet_atlas.utils.hashing import file_sha256
from pcdet_atlas.utils.provenance import source_revision
from pcdet_atlas.utils.safe_pickle import loads

__all__ = [
    "EvalRun",
    "EvalSettings",
    "checkpoints_to_evaluate",
    "evaluate_checkpoint",
    "run_evaluation",
]


@dataclass(frozen=True)
class EvalSettings:
    """What one evaluation asks for: the flags of ``tools/test.py`` (named after them but for
    the negated ones: ``--no_reuse`` is ``reuse_clean=False``, ``--no_progress``
    ``show_progress=False``), with their defaults.

    ``cfg_file`` and ``set_cfgs``: the model config and its ``KEY VALUE`` overrides; ``attacks``:
    ``all`` or a comma list of variants; ``ckpt``: the checkpoint (default: the config's
    ``ATLAS.CHECKPOINT``), or with ``eval_all`` every ``checkpoint_epoch_N.pth`` of ``ckpt_dir``
    (default: the run's ``ckpt/``) with N >= ``start_epoch``; ``output_root``, ``extra_tag``
    and ``eval_tag`` place the evaluation folder; ``batch_size`` is the total over processes
    (default: one per process); ``overwrite`` deletes an earlier evaluation folder, ``resume``
    keeps its finished variants; ``prediction_store``: the folder of a shared prediction store.

    Raises:
        ValueError: flags that contradict each other, naming them.
    """

    cfg_file: str
    set_cfgs: tuple[str, ...] = ()
    attacks: str = "clean"
    ckpt: str | None = None
    eval_all: bool = False
    ckpt_dir: str | None = None
    start_epoch: int = 0
    output_root: str = str(REPO_ROOT / "output")
    extra_tag: str = "default"
    eval_tag: str = "default"
    batch_size: int | None = None
    workers: int = DEFAULT_WORKERS
    seed: int = DEFAULT_SEED
    fix_random_seed: bool = False
    device: str | None = None
    launcher: str = "none"
    tcp_port: int = DEFAULT_TCP_PORT
    threads: int | None = None
    save_to_file: bool = False
    overwrite: bool = False
    resume: bool = False
    reuse_clean: bool = True
    prediction_store: str | None = None
    show_progress: bool = True

    def __post_init__(self):
        object.__setattr__(self, "set_cfgs", tuple(self.set_cfgs))
        if self.eval_all and self.ckpt is not None:
            raise ValueError("--eval_all evaluates the checkpoints of --ckpt_dir; drop --ckpt")
        if not self.eval_all and (self.ckpt_dir is not None or self.start_epoch):
            raise ValueError("--ckpt_dir and --start_epoch apply to --eval_all only")
        if self.resume and self.overwrite:
            raise ValueError("--resume keeps an earlier call's variants, --overwrite deletes them")


@dataclass(frozen=True)
class EvalRun:
    """One call's resolved state, shared by its checkpoints: the settings, the merged config,
    the built attacks and their ``{variant: attack_sha256}``, the test split's fingerprint, the
    process layout and device, the total batch size and the run's caches."""

    settings: EvalSettings
    cfg: Mapping
    attacks: Mapping[str, BaseAttack]
    fingerprints: Mapping[str, str]
    dataset_fingerprint: str | None
    device: torch.device
    batch_size: int
    caches: EvalCaches
    dist: bool = False
    rank: int = 0
    world: int = 1

    def context(self, logger: logging.Logger | None) -> EvalContext:
        """What every variant of the run shares (:class:`EvalContext`)."""
        return EvalContext(
            data_cfg=self.cfg.DATA_CONFIG, class_names=self.cfg.CLASS_NAMES, device=self.device,
            batch_size=self.batch_size // self.world, dist=self.dist,
            workers=self.settings.workers, seed=self.settings.seed,
            temporal_window=atlas_section(self.cfg.get("ATLAS")).temporal_window,
            show_progress=self.settings.show_progress, save_to_file=self.settings.save_to_file,
            logger=logger,
        )  # fmt: skip


def checkpoints_to_evaluate(settings: EvalSettings, cfg, atlas_cfg) -> list[Path]:
    """The one checkpoint of ``ckpt``, or those of ``eval_all`` in epoch order."""
    if not settings.eval_all:
        return [resolve_checkpoint(settings.ckpt, atlas_cfg)]
    ckpt_dir = Path(
        settings.ckpt_dir
        or output_dir_for(cfg, settings.output_root, settings.extra_tag, ("ckpt", "folder"))
    )
    start = settings.start_epoch
    found = [path for epoch, path in list_epoch_checkpoints(ckpt_dir) if epoch >= start]
    if not found:
        raise FileNotFoundError(
            f"--eval_all: no checkpoint_epoch_N.pth with N >= {start} in {ckpt_dir}"
        )
    return found


def run_evaluation(settings: EvalSettings) -> dict:
    """Evaluate (module docstring). Rank 0 holds each evaluation folder's one-writer lock from
    its first write to the end.

    Returns:
        On rank 0 the last checkpoint's ``{'results', 'output_dir', 'checkpoint'}`` with
        ``runs``, one such dict per checkpoint; ``{}`` on other ranks.
    """
    with contextlib.ExitStack() as held:
        return _run(settings, held)


def _run(settings: EvalSettings, held: contextlib.ExitStack) -> dict:
    cfg = load_cfg(settings.cfg_file, list(settings.set_cfgs))
    require_dataset(cfg, settings.cfg_file)  # before anything is built or written
    atlas_cfg = cfg.get("ATLAS", {})
    variants = resolve_variants(settings.attacks, atlas_cfg)
    checkpoints = checkpoints_to_evaluate(settings, cfg, atlas_cfg)
    dist, rank, world, device = setup_runtime(
        device=settings.device, launcher=settings.launcher, tcp_port=settings.tcp_port,
        threads=settings.threads, seed=settings.seed, fix_random_seed=settings.fix_random_seed,
    )  # fmt: skip
    logger = create_logger(rank=rank)
    data_root = check_test_split(cfg.DATA_CONFIG, cfg.CLASS_NAMES, logger)
    attacks = build_variant_attacks(variants, data_root)
    fingerprints = variant_fingerprints(variants, attacks)
    data_fingerprint = data_config_fingerprint(cfg.DATA_CONFIG, "test")  # once per call
    batch_size = settings.batch_size or world
    if batch_size % world:
        raise ValueError(f"--batch_size {batch_size} is not divisible by {world} processes")

    out_dirs = [eval_dir(cfg, settings.output_root, settings.extra_tag, ckpt, settings.eval_tag)
                for ckpt in checkpoints]  # fmt: skip
    ckpt_sha256 = {ckpt: file_sha256(ckpt) for ckpt in checkpoints}
    keep_earlier = settings.overwrite or settings.resume
    finished, again = {}, {}
    for ckpt, out_dir in zip(checkpoints, out_dirs):
        check_eval_dir(out_dir, keep_earlier)
        if settings.resume:
            finished[out_dir], again[out_dir] = finished_variants(
                out_dir, cfg, ckpt_sha256[ckpt], fingerprints, batch_size=batch_size, world=world,
                device=str(device), dataset_fingerprint=data_fingerprint,
            )  # fmt: skip
    if dist:  # every rank has checked before rank 0 writes
        torch_dist.barrier()
    model = build_network_from_config(cfg)
    store = _prediction_store(settings, model, logger)
    run = EvalRun(
        settings=settings, cfg=cfg, attacks=attacks, fingerprints=fingerprints,
        dataset_fingerprint=data_fingerprint, device=device, batch_size=batch_size,
        caches=EvalCaches(reuse=settings.reuse_clean, store=store), dist=dist, rank=rank,
        world=world,
    )  # fmt: skip
    runs = []
    for ckpt, out_dir in zip(checkpoints, out_dirs):
        state = model.load_params_from_file(ckpt)  # strict: CheckpointMismatchError names it
        seed = training_seed(state, atlas_section(cfg.get("ATLAS")).training_seed, ckpt)
        if file_sha256(ckpt) != ckpt_sha256[ckpt]:  # results.json records the hash taken above
            raise RuntimeError(
                f"checkpoint {ckpt} changed since this call started (a training run rewriting "
                "it?); evaluate a copy, or an epoch checkpoint"
            )
        model.to(device).eval()
        if rank == 0:
            lock_output_folder(out_dir, held, f"tools/test.py evaluating {ckpt.name}")
            check_eval_dir(out_dir, keep_earlier)  # again: a run since the check?
            if out_dir.exists() and not settings.resume:  # overwrite: no stale file survives
                shutil.rmtree(out_dir)
            save_config(cfg, out_dir / f"{cfg.TAG}.yaml")
        stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
        log_file = out_dir / f"log_eval_{stamp}.txt" if rank == 0 else None
        logger = create_logger(log_file, rank=rank)
        logger.info(f"{settings.cfg_file}  checkpoint {ckpt}  variants {[v for v, _ in variants]}")
        logger.info(f"processes: {world}  device: {device}  batch: {batch_size}  output: {out_dir}")
        for variant, reason in again.get(out_dir, {}).items():
            logger.info(f"{variant}: finished by an earlier call, evaluated again: {reason}")
        runs.append(
            evaluate_checkpoint(
                run, model, ckpt, out_dir, finished=finished.get(out_dir, {}),
                ckpt_sha256=ckpt_sha256[ckpt], logger=logger, training_seed=seed,
            )
        )  # fmt: skip
    if rank != 0:
        return {}
    return {**runs[-1], "runs": runs}


def _save_proposals(caches: EvalCaches, variant_dir: Path, rank: int) -> dict[str, str]:
    """Write this process's clean proposals (if any; an earlier call's part is removed
    otherwise), for a later resume; every process calls it. Returns the entry's
    ``proposals_sha256`` (:func:`.proposal_hashes`)."""
    part = proposal_part(variant_dir, rank)
    if caches.clean_proposals:
        save_pickle(caches.clean_proposals, part)
    else:
        part.unlink(missing_ok=True)
    mine = file_sha256(part) if caches.clean_proposals else None
    return proposal_hashes(variant_dir, all_gather_objects(mine))


def _read_kept(path: Path, sha256: str | None) -> object:
    """Unpickle a finished variant's file (restricted unpickler) from the bytes whose SHA-256
    is checked against ``sha256``, the one its entry recorded (None: an older version's entry,
    which records none)."""
    data = path.read_bytes()
    if sha256 is not None and (now := hashlib.sha256(data).hexdigest()) != sha256:
        raise RuntimeError(
            f"{path} changed since this call checked it (SHA-256 {now}, its entry recorded "
            f"{sha256}); run --resume again to evaluate its variant again"
        )
    return loads(data, source=str(path))


def _prediction_store(
    settings: EvalSettings, model: torch.nn.Module, logger: logging.Logger
) -> PredictionStore | None:
    """The store of ``prediction_store`` if the model (or its RPN) can use it, else None."""
    if settings.prediction_store is None:
        return None
    store = PredictionStore(settings.prediction_store)
    users = use_prediction_store(model, store)
    logger.info(f"prediction store {settings.prediction_store}: used by "
                + (" and ".join(users) if users else "nothing of this model"))  # fmt: skip
    return store if users else None


def evaluate_checkpoint(
    run: EvalRun,
    model: torch.nn.Module,
    ckpt: Path,
    out_dir: Path,
    *,
    finished: Mapping[str, dict],
    ckpt_sha256: str,
    logger: logging.Logger,
    training_seed: int | None = None,
) -> dict:
    """Every variant of one checkpoint; ``results.json`` is rewritten after each variant.
    ``finished``: the entries of the variants an earlier call finished (``resume``), kept; the
    clean one's predictions (and this process's clean proposals) are read back for the others,
    each file checked against the SHA-256 its entry recorded. Each new entry's ``extra`` records
    its ``attack_sha256`` and ``result_sha256`` (the clean one's also ``proposals_sha256``:
    :func:`.proposal_hashes`), the file's the test split's fingerprint; ``training_seed``: the
    checkpoint's (``results.json``'s), or None."""
    settings, cfg, rank, caches = run.settings, run.cfg, run.rank, run.caches
    atlas_cfg = cfg.get("ATLAS", {})
    context = run.context(logger)
    caches.new_checkpoint()
    entries: dict = {}
    path = None
    source = source_revision()
    for variant, attack in run.attacks.items():
        if variant in finished:
            entry = finished[variant]
            recorded = entry["extra"]  # the hashes finished_variants compared
            write_files = settings.save_to_file and rank == 0  # the earlier call may not have
            clean_annos = caches.clean_predictions  # what scores it (None for clean itself)
            # this version's metric and analyses on the kept predictions, unless the entry was
            # scored with clean predictions that this call (not evaluating clean) lacks
            rescore = clean_annos is not None or not recorded.get("clean_predictions")
            if variant == "clean" or write_files or (rank == 0 and rescore):
                kept_annos = _read_kept(
                    out_dir / variant / "result.pkl", recorded.get("result_sha256")
                )
            if write_files:
                write_prediction_files(kept_annos, out_dir / variant / "final_result" / "data")
            if variant == "clean":  # its predictions are reused, its proposals seed the banks
                part = proposal_part(out_dir / variant, rank)  # this process's frames
                hashes = recorded.get("proposals_sha256")
                if hashes is None:  # an older version's entry: the parts there, unverified
                    proposals = _read_kept(part, None) if part.is_file() else None
                else:
                    sha = hashes.get(part.name)
                    proposals = _read_kept(part, sha) if sha is not None else None
                caches.keep_clean(kept_annos, proposals, source=str(part))
            if rank == 0 and rescore:
                entry = rescore_variant(
                    variant, attack, entry, kept_annos, context, clean_det_annos=clean_annos
                )
            logger.info(
                f"{variant}: kept from an earlier call (--resume), "
                + ("scored again" if rescore else "as scored then (no clean predictions here)")
            )
        else:
            entry, det_annos = evaluate_variant(
                model, variant, attack, context, caches=caches, out_dir=out_dir / variant
            )
            files = {}  # the hashes a resumed call checks before it reuses them
            if variant == "clean":
                caches.keep_clean(det_annos)
                files["proposals_sha256"] = _save_proposals(caches, out_dir / variant, rank)
            if rank == 0:  # result.pkl is rank 0's
                files["result_sha256"] = file_sha256(out_dir / variant / "result.pkl")
                entry = {**entry, "extra": {**entry.get("extra", {}), **files}}
        if rank != 0:
            continue
        # a kept entry holds this fingerprint and its files' hashes already (finished_variants
        # compared them)
        extra = {**entry.get("extra", {}), "attack_sha256": run.fingerprints[variant]}
        entries[variant] = {**entry, "extra": extra}
        results = build_results(
            model=atlas_section(atlas_cfg).model_name or cfg.TAG, config=str(settings.cfg_file),
            checkpoint=str(repo_relative(ckpt)), class_names=cfg.CLASS_NAMES, variants=entries,
            training_seed=training_seed, model_sha256=model_config_sha256(cfg), source=source,
            extra={"processes": run.world, "device": str(run.device),
                   "batch_size": run.batch_size, "checkpoint_sha256": ckpt_sha256,
                   "variants_requested": list(run.attacks),
                   "dataset_fingerprint": run.dataset_fingerprint},
        )  # fmt: skip
        path = save_results(results, out_dir / "results.json")  # atomic: temp file + rename
    if rank != 0:
        return {}
    print("\n" + format_table(results))
    logger.info(f"results: {path}")
    return {"results": results, "output_dir": out_dir, "checkpoint": ckpt}
