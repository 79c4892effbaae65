"""Evaluate a detector on ATLAS variants: Waymo L2 mAP/mAPH and attack success rate per variant.

    python tools/test.py --cfg cfgs/atlas/synthetic/cp4f.yaml --attacks clean,inj_global_hard,rem_40
    python tools/test.py --cfg cfgs/atlas/synthetic/cp4f.yaml --attacks all
    python tools/test.py --cfg cfgs/atlas/synthetic/cp4f.yaml --eval_all --start_epoch 10
    torchrun --nproc_per_node 2 tools/test.py --cfg ... --launcher pytorch

``--ckpt`` defaults to the config's ``ATLAS.CHECKPOINT``; ``--eval_all`` evaluates every
``checkpoint_epoch_N.pth`` of ``--ckpt_dir`` (default: the run's ``ckpt/``) with
N >= ``--start_epoch``, in epoch order. Output, per checkpoint:
``output/<group>/<tag>/<extra_tag>/eval/<name>/<split>/<eval_tag>/`` (``<name>`` is ``epoch_N``
for ``checkpoint_epoch_N.pth``, the file name without ``.pth`` otherwise) with ``results.json``
(schema in docs/evaluation.md; rewritten after each variant, so a failure keeps the variants
done), ``<variant>/result.pkl``, the merged config and a log; the table is printed as the paper
lays it out. ``--extra_tag``, ``--eval_tag``, the checkpoint's and each variant's file name and
the data's frame ids must each be one file or folder name (letters, digits, ``.``, ``_``, ``-``;
not ``..``). While it writes an evaluation directory, a call (its rank 0) holds that directory's
lock (``.<eval_tag>.lock`` beside it): a second call into it stops at once, naming the first's
PID, host and start time.

The clean variant runs first; under an attack variant, a frame whose whole model input (the
frame, its point history and, for PTT, its proposal history) the attack leaves untouched takes
the clean run's prediction, which is bitwise what the model would return
(docs/evaluation.md "Reusing clean predictions"; ``--no_reuse`` runs every frame). With
``--prediction_store DIR``, CP-4f's detections and a two-stage model's proposals are kept in DIR
by their inputs: MSF-4f and PTT, whose RPN is the same CP-4f fed the same points, then read the
proposals CP-4f's own evaluation (or another model's) computed instead of running the RPN again
(docs/evaluation.md "Sharing the RPN between models").

Every variant YAML (its ``VARIANT`` must be its file name), the test split, the (first)
checkpoint and the evaluation directories are checked before anything is written: an evaluation
directory that already holds files is an error unless ``--overwrite`` is given, which deletes it
first, or ``--resume``, which keeps the requested variants an earlier call finished there (its
``results.json`` entry and ``<variant>/result.pkl``) and evaluates the others, provided that call
had the same merged config, checkpoint (SHA-256), batch size and process count. A finished
variant is evaluated again when its merged attack config or trace library changed since
(``extra.attack_sha256`` of its entry; an entry without it too), when its entry has targets but
no per-run counts (a file of schema 4 or older), or when it was evaluated without the clean
predictions that this call has (``extra.clean_predictions``); every finished variant is evaluated
again when the test split's info pkls or frame files changed since (``extra.dataset_fingerprint``
of ``results.json``, :func:`pcdet_atlas.datasets.fingerprint.dataset_fingerprint`; a file
without it too); the results are those of one uninterrupted call.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import shutil
from collections.abc import Mapping
from pathlib import Path

import torch.distributed as torch_dist
import yaml

from pcdet_atlas.config import (
    ConfigError,
    resolve_cli_path,
    resolve_repo_path,
    save_config,
    to_plain,
)
from pcdet_atlas.datasets.fingerprint import data_config_fingerprint
from pcdet_atlas.evaluation import build_results, format_table, load_results, save_results
from pcdet_atlas.models import build_network_from_config
from pcdet_atlas.models.detectors.two_stage import file_sha256
from pcdet_atlas.models.prediction_store import PredictionStore, use_prediction_store
from pcdet_atlas.train_utils.atlas_eval import (
    build_variant_attacks,
    check_test_split,
    evaluate_variant,
    resolve_variants,
    variant_fingerprints,
)
from pcdet_atlas.train_utils.checkpoint import (
    CHECKPOINT_NAME,
    list_epoch_checkpoints,
    model_config_sha256,
)
from pcdet_atlas.train_utils.checkpoint import training_seed as checkpoint_training_seed
from pcdet_atlas.train_utils.eval_utils import write_prediction_files
from pcdet_atlas.train_utils.setup import (
    add_common_args,
    count_arg,
    folder_name_arg,
    load_cfg,
    lock_output_folder,
    output_dir_for,
    require_dataset,
    setup_runtime,
)
from pcdet_atlas.utils.common import create_logger, save_pickle
from pcdet_atlas.utils.paths import join_under
from pcdet_atlas.utils.safe_pickle import load_pickle


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_common_args(parser)
    parser.add_argument("--attacks", default="clean", help="'all' or a comma list of variants")
    parser.add_argument(
        "--eval_tag", type=folder_name_arg, default="default",
        help="the evaluation's folder under eval/<checkpoint>/<split>/",
    )  # fmt: skip
    parser.add_argument(
        "--eval_all", action="store_true", default=False,
        help="evaluate every checkpoint_epoch_N.pth of --ckpt_dir (N >= --start_epoch), in order",
    )  # fmt: skip
    parser.add_argument(
        "--ckpt_dir", type=str, default=None,
        help="checkpoints of --eval_all (default: the run's ckpt/)",
    )  # fmt: skip
    parser.add_argument(
        "--start_epoch", type=count_arg(0), default=0,
        help="--eval_all: the first epoch evaluated",
    )  # fmt: skip
    parser.add_argument(
        "--save_to_file", action="store_true", default=False,
        help="also write <variant>/final_result/data/<frame_id>.txt per frame",
    )  # fmt: skip
    parser.add_argument(
        "--overwrite", action="store_true", default=False,
        help="delete an existing evaluation directory first (default: refuse to run)",
    )  # fmt: skip
    parser.add_argument(
        "--resume", action="store_true", default=False,
        help="keep the requested variants an earlier call with the same config, checkpoint, "
        "batch size and processes finished in the evaluation directory (with the same attack "
        "config); evaluate the rest",
    )  # fmt: skip
    parser.add_argument(
        "--no_reuse", action="store_true", default=False,
        help="run the model on every frame of every variant (default: a frame whose input the "
        "attack leaves untouched takes the clean run's prediction, bitwise the same)",
    )  # fmt: skip
    parser.add_argument(
        "--prediction_store", default=None, metavar="DIR",
        help="keep the predictions of a model that serves as an RPN (CenterPoint, CP-4f), or of "
        "a two-stage model's RPN, in DIR, found by their inputs; a later model that feeds the "
        "same RPN the same inputs reads them (docs/evaluation.md 'Sharing the RPN')",
    )  # fmt: skip
    parser.add_argument("--no_progress", action="store_true", default=False, help="no tqdm bars")
    args = parser.parse_args(argv)
    if args.eval_all and args.ckpt is not None:
        parser.error("--eval_all evaluates the checkpoints of --ckpt_dir; drop --ckpt")
    if not args.eval_all and (args.ckpt_dir is not None or args.start_epoch):
        parser.error("--ckpt_dir and --start_epoch apply to --eval_all only")
    if args.resume and args.overwrite:
        parser.error("--resume keeps an earlier call's variants, --overwrite deletes them")
    return args


def resolve_checkpoint(arg: str | None, atlas_cfg) -> Path:
    """``--ckpt`` as typed (relative to the working directory), else the config's
    ``ATLAS.CHECKPOINT`` (relative to the repository root)."""
    if arg is not None:
        ckpt, path = arg, resolve_cli_path(arg)
    elif atlas_cfg.get("CHECKPOINT") is not None:
        ckpt = atlas_cfg.CHECKPOINT
        path = resolve_repo_path(ckpt)
    else:
        raise ConfigError("no checkpoint: pass --ckpt (the config's ATLAS.CHECKPOINT is null)")
    if not path.is_file():
        raise FileNotFoundError(
            f"checkpoint {ckpt} not found (train one with tools/train.py, or pass --ckpt)"
        )
    return path


def eval_name(ckpt: Path) -> str:
    """The ``eval/`` folder of a checkpoint: ``epoch_N`` for ``checkpoint_epoch_N.pth`` (as
    OpenPCDet names it), the file name without ``.pth`` otherwise."""
    m = CHECKPOINT_NAME.fullmatch(ckpt.name)
    return f"epoch_{m.group(1)}" if m else ckpt.stem


def eval_dir(cfg, output_root: str, extra_tag: str, ckpt: Path, eval_tag: str) -> Path:
    """Where one checkpoint's evaluation is written (module docstring):
    ``<output_root>/<group>/<tag>/<extra_tag>/eval/<name>/<split>/<eval_tag>/``."""
    split = cfg.DATA_CONFIG.DATA_SPLIT["test"]
    return join_under(
        output_dir_for(cfg, output_root, extra_tag) / "eval",
        (eval_name(ckpt), "checkpoint name"), (split, "DATA_CONFIG.DATA_SPLIT.test"),
        (eval_tag, "eval_tag"), source=f"the evaluation folder of checkpoint {ckpt}",
    )  # fmt: skip


def checkpoints_to_evaluate(args, cfg, atlas_cfg) -> list[Path]:
    """The one checkpoint of ``--ckpt``, or those of ``--eval_all`` in epoch order."""
    if not args.eval_all:
        return [resolve_checkpoint(args.ckpt, atlas_cfg)]
    ckpt_dir = Path(args.ckpt_dir or output_dir_for(cfg, args.output_root, args.extra_tag) / "ckpt")
    found = [path for epoch, path in list_epoch_checkpoints(ckpt_dir) if epoch >= args.start_epoch]
    if not found:
        raise FileNotFoundError(
            f"--eval_all: no checkpoint_epoch_N.pth with N >= {args.start_epoch} in {ckpt_dir}"
        )
    return found


def check_eval_dir(out_dir: Path, overwrite: bool) -> None:
    """Refuse an evaluation directory that already holds files, unless ``--overwrite``."""
    if overwrite or not out_dir.is_dir() or not any(out_dir.iterdir()):
        return
    held = sorted(p.name for p in out_dir.iterdir())
    raise FileExistsError(
        f"evaluation directory {out_dir} already holds {', '.join(held[:5])}"
        + (" ..." if len(held) > 5 else "")
        + ": pass --overwrite to replace it, or another --eval_tag / --extra_tag"
    )


def finished_variants(
    out_dir: Path,
    cfg,
    ckpt_sha256: str,
    requested: Mapping[str, str],
    *,
    batch_size: int,
    world: int,
    device: str,
    dataset_fingerprint: str,
) -> tuple[dict[str, dict], dict[str, str]]:
    """``--resume``: the ``results.json`` entries of the requested variants an earlier call
    finished in ``out_dir`` that this call keeps. That call must have had the same merged config,
    checkpoint bytes, batch size, process count and device, or this is an error naming what
    differs.

    ``requested``: ``{variant: attack_sha256}`` of this call. A finished variant (entry and
    ``<variant>/result.pkl`` both there) is kept unless its entry's ``extra.attack_sha256``
    differs (or is missing), or it has targets but no per-run counts (``runs``: a file of
    schema 4 or older), or it is an attack variant evaluated without the clean predictions
    while this call evaluates ``clean``, or it is ``clean`` and a process's
    ``clean/proposals_rank<r>.pkl`` is missing where another's is there: each of those is
    evaluated again, as one uninterrupted call would. Every finished variant is evaluated again
    when ``dataset_fingerprint`` (this call's test split) differs from the file's
    ``extra.dataset_fingerprint``, or the file has none. Returns the kept entries and
    ``{variant: reason}`` of those evaluated again.
    """
    path = out_dir / "results.json"
    if not path.is_file():
        return {}, {}
    earlier = load_results(path)
    extra = earlier.get("extra", {})
    config_file = out_dir / f"{cfg.TAG}.yaml"
    now = {"checkpoint_sha256": ckpt_sha256, "batch_size": batch_size, "processes": world,
           "device": device}  # fmt: skip
    differs = [f"{key} {extra.get(key)!r} (now {value!r})"
               for key, value in now.items() if extra.get(key) != value]  # fmt: skip
    if not config_file.is_file():
        differs.append(f"merged config: {config_file} is missing")
    elif config_file.read_text() != yaml.safe_dump(to_plain(cfg), sort_keys=False):
        differs.append(f"merged config ({config_file} differs from this call's)")
    if differs:
        raise ValueError(
            f"--resume: {path} was written by a call with another setting: {'; '.join(differs)}; "
            "pass --overwrite to evaluate again, or another --eval_tag / --extra_tag"
        )
    data_changed = None
    if "dataset_fingerprint" not in extra:
        data_changed = "results.json has no extra.dataset_fingerprint (an older version wrote it)"
    elif extra["dataset_fingerprint"] != dataset_fingerprint:
        data_changed = (
            "the test split's info pkls or frame files changed (dataset_fingerprint "
            f"{extra['dataset_fingerprint']}, now {dataset_fingerprint})"
        )
    kept, again = {}, {}
    for name, entry in earlier["variants"].items():
        if name not in requested or not (out_dir / name / "result.pkl").is_file():
            continue
        recorded = entry.get("extra", {})
        if data_changed is not None:
            again[name] = data_changed
        elif "attack_sha256" not in recorded:
            again[name] = "its entry has no extra.attack_sha256 (written by an older version)"
        elif recorded["attack_sha256"] != requested[name]:
            again[name] = (
                "its attack config or trace library changed (attack_sha256 "
                f"{recorded['attack_sha256']}, now {requested[name]})"
            )
        elif entry["runs"] is None and entry["num_targets"] > 0:
            again[name] = "its entry has no per-run counts (results.json schema 4 or older)"
        elif name != "clean" and "clean" in requested and not recorded.get("clean_predictions"):
            again[name] = "it was evaluated without the clean predictions this call has"
        elif name == "clean" and (missing := missing_proposal_parts(out_dir / name, world)):
            again[name] = f"{missing[0]} is missing (the clean proposals of its process)"
        else:  # without targets there are no runs: an older file's null is []
            kept[name] = entry if entry["runs"] is not None else {**entry, "runs": []}
    return kept, again


def missing_proposal_parts(variant_dir: Path, world: int) -> list[Path]:
    """The ``proposals_rank<r>.pkl`` files of ``world`` processes that are missing beside
    another process's (none when no process wrote one: a model without a proposal bank)."""
    parts = [variant_dir / f"proposals_rank{rank}.pkl" for rank in range(world)]
    if not any(part.is_file() for part in parts):
        return []
    return [part for part in parts if not part.is_file()]


def main(argv=None) -> dict:
    with contextlib.ExitStack() as held:  # the evaluation folders' locks, released at the end
        return evaluate(parse_args(argv), held)


def evaluate(args, held: contextlib.ExitStack) -> dict:
    """The work of :func:`main`; rank 0 holds each evaluation folder's one-writer lock in
    ``held`` from its first write on."""
    cfg = load_cfg(args.cfg_file, args.set_cfgs)
    require_dataset(cfg, args.cfg_file)  # before anything is built or written
    atlas_cfg = cfg.get("ATLAS", {})
    variants = resolve_variants(args.attacks, atlas_cfg)
    checkpoints = checkpoints_to_evaluate(args, cfg, atlas_cfg)
    dist, rank, world, device = setup_runtime(args)
    logger = create_logger(rank=rank)
    data_root = check_test_split(cfg.DATA_CONFIG, cfg.CLASS_NAMES, logger)
    attacks = build_variant_attacks(variants, data_root)
    fingerprints = variant_fingerprints(variants, attacks)
    data_fingerprint = data_config_fingerprint(cfg.DATA_CONFIG, "test")  # once per call
    batch_size = args.batch_size or world
    if batch_size % world:
        raise ValueError(f"--batch_size {batch_size} is not divisible by {world} processes")

    out_dirs = [eval_dir(cfg, args.output_root, args.extra_tag, ckpt, args.eval_tag)
                for ckpt in checkpoints]  # fmt: skip
    ckpt_sha256 = {ckpt: file_sha256(ckpt) for ckpt in checkpoints}
    finished, again = {}, {}
    for ckpt, out_dir in zip(checkpoints, out_dirs):
        check_eval_dir(out_dir, args.overwrite or args.resume)
        if args.resume:
            finished[out_dir], again[out_dir] = finished_variants(
                out_dir, cfg, ckpt_sha256[ckpt], fingerprints, batch_size=batch_size, world=world,
                device=str(device), dataset_fingerprint=data_fingerprint,
            )  # fmt: skip
    if dist:  # every rank has checked before rank 0 writes
        torch_dist.barrier()
    model = build_network_from_config(cfg)
    store = None
    if args.prediction_store is not None:
        store = PredictionStore(args.prediction_store)
        users = use_prediction_store(model, store)
        logger.info(f"prediction store {args.prediction_store}: used by "
                    + (" and ".join(users) if users else "nothing of this model"))  # fmt: skip
        store = store if users else None
    runs = []
    for ckpt, out_dir in zip(checkpoints, out_dirs):
        state = model.load_params_from_file(ckpt)  # strict: CheckpointMismatchError names it
        seed = checkpoint_training_seed(state, cfg.get("ATLAS", {}).get("TRAINING_SEED"), ckpt)
        if file_sha256(ckpt) != ckpt_sha256[ckpt]:  # results.json records the hash taken above
            raise RuntimeError(
                f"checkpoint {ckpt} changed since this call started (a training run rewriting "
                "it?); evaluate a copy, or an epoch checkpoint"
            )
        model.to(device).eval()
        if rank == 0:
            lock_output_folder(out_dir, held, f"tools/test.py evaluating {ckpt.name}")
            check_eval_dir(out_dir, args.overwrite or args.resume)  # again: a run since the check?
            if out_dir.exists() and not args.resume:  # --overwrite: no stale file survives
                shutil.rmtree(out_dir)
            save_config(cfg, out_dir / f"{cfg.TAG}.yaml")
        stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
        log_file = out_dir / f"log_eval_{stamp}.txt" if rank == 0 else None
        logger = create_logger(log_file, rank=rank)
        logger.info(f"{args.cfg_file}  checkpoint {ckpt}  variants {[v for v, _ in variants]}")
        logger.info(f"processes: {world}  device: {device}  batch: {batch_size}  output: {out_dir}")
        for variant, reason in again.get(out_dir, {}).items():
            logger.info(f"{variant}: finished by an earlier call, evaluated again: {reason}")
        runs.append(
            evaluate_checkpoint(
                model, ckpt, out_dir, args, cfg, attacks, dist=dist, rank=rank, world=world,
                device=device, batch_size=batch_size, logger=logger,
                finished=finished.get(out_dir, {}), ckpt_sha256=ckpt_sha256[ckpt],
                fingerprints=fingerprints, store=store, dataset_fingerprint=data_fingerprint,
                training_seed=seed,
            )
        )  # fmt: skip
    if rank != 0:
        return {}
    return {**runs[-1], "runs": runs}


def evaluate_checkpoint(
    model, ckpt, out_dir, args, cfg, attacks, *, dist, rank, world, device, batch_size, logger,
    finished, ckpt_sha256, fingerprints, dataset_fingerprint, store=None, training_seed=None
) -> dict:  # fmt: skip
    """Every variant of one checkpoint; ``results.json`` is rewritten after each variant.
    ``finished``: the entries of the variants an earlier call finished (``--resume``), kept.
    ``fingerprints``: ``{variant: attack_sha256}``, recorded in each new entry's ``extra``;
    ``dataset_fingerprint``: the test split's, recorded in the file's ``extra``.
    ``store``: the model's ``PredictionStore`` (counted per variant), or None.
    ``training_seed``: the checkpoint's (``results.json``'s ``training_seed``), or None."""
    atlas_cfg = cfg.get("ATLAS", {})
    entries: dict = {}
    clean_annos = None
    clean_proposals: dict = {}  # the clean run's proposal bank (PTT), seeding the others'
    path = None
    for variant, attack in attacks.items():
        if variant in finished:
            entry = finished[variant]
            write_files = args.save_to_file and rank == 0  # the earlier call may have run without
            if variant == "clean" or write_files:
                kept_annos = load_pickle(out_dir / variant / "result.pkl")
            if write_files:
                write_prediction_files(kept_annos, out_dir / variant / "final_result" / "data")
            if variant == "clean":  # its predictions are reused, its proposals seed (below)
                clean_annos = kept_annos
                part = out_dir / variant / f"proposals_rank{rank}.pkl"  # this process's frames
                if part.is_file():
                    clean_proposals.update(load_pickle(part))
            logger.info(f"{variant}: kept from an earlier call (--resume)")
        else:
            entry, det_annos = evaluate_variant(
                model, variant, attack, data_cfg=cfg.DATA_CONFIG, class_names=cfg.CLASS_NAMES,
                device=device, batch_size=batch_size // world, dist=dist, workers=args.workers,
                seed=args.seed, temporal_window=atlas_cfg.get("TEMPORAL_WINDOW"),
                clean_det_annos=clean_annos, out_dir=out_dir / variant, logger=logger,
                show_progress=not args.no_progress, save_to_file=args.save_to_file,
                reuse_clean=not args.no_reuse, clean_proposals=clean_proposals,
                prediction_store=store,
            )  # fmt: skip
            if variant == "clean":
                clean_annos = det_annos
                if clean_proposals:  # each rank's part, for a later --resume
                    save_pickle(clean_proposals, out_dir / variant / f"proposals_rank{rank}.pkl")
        if rank != 0:
            continue
        # a kept entry holds this fingerprint already (finished_variants compared it)
        entries[variant] = {**entry, "extra": {**entry.get("extra", {}),
                                               "attack_sha256": fingerprints[variant]}}  # fmt: skip
        results = build_results(
            model=atlas_cfg.get("MODEL_NAME", cfg.TAG), config=str(args.cfg_file),
            checkpoint=str(ckpt), class_names=cfg.CLASS_NAMES, variants=entries,
            training_seed=training_seed, model_sha256=model_config_sha256(cfg),
            extra={"processes": world, "device": str(device), "batch_size": batch_size,
                   "checkpoint_sha256": ckpt_sha256, "variants_requested": list(attacks),
                   "dataset_fingerprint": dataset_fingerprint},
        )  # fmt: skip
        path = save_results(results, out_dir / "results.json")  # atomic: temp file + rename
    if rank != 0:
        return {}
    print("\n" + format_table(results))
    logger.info(f"results: {path}")
    return {"results": results, "output_dir": out_dir, "checkpoint": ckpt}


if __name__ == "__main__":
    main()
