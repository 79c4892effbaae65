"""Train a detector (OpenPCDet's tools/train.py, for pcdet_atlas).

    python tools/train.py --cfg cfgs/atlas/synthetic/cp4f.yaml
    torchrun --nproc_per_node 2 tools/train.py --cfg ... --launcher pytorch

Output: ``output/<group>/<tag>/<extra_tag>/`` with ``ckpt/checkpoint_epoch_N.pth`` (and, during
an epoch, ``ckpt/latest_model.pth``, rewritten every ``--ckpt_save_time_interval`` seconds),
``train_*.log``, the merged ``<tag>.yaml`` (with the ``NUM_EPOCHS`` and ``BATCH_SIZE_PER_GPU`` that
``--epochs`` / ``--batch_size`` put in effect) and ``tensorboard/``. Training resumes from
``--ckpt`` or, if absent, from the newest checkpoint in ``ckpt/``, mid-epoch included (exactly:
optimizer, schedule, RNG state and the epoch's position in its shuffled order included); a
checkpoint trained with other settings (``OPTIMIZATION``, epochs, total batch size, process
count, ``--seed``, ``--use_amp``, ``--sync_bn``, ``--merge_all_iters_to_one_epoch``, or another
merged ``CLASS_NAMES`` / ``DATA_CONFIG`` / ``MODEL`` / ``STAGE``) is refused, naming what changed,
before any of its state is loaded. Counts below their minimum (``--epochs 0``) are usage errors;
a bad ``OPTIMIZATION`` value and a missing ``--ckpt`` / ``--pretrained_model`` file are errors
before anything is built or written. ``--extra_tag`` must be one folder name (letters, digits,
``.``, ``_``, ``-``; not ``..``). A run (its rank 0) holds the output folder's lock
(``.<extra_tag>.lock`` beside it) while it trains: a second run into that folder stops at once,
naming the first's PID, host and start time.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
from pathlib import Path

import torch
from tensorboardX import SummaryWriter

from pcdet_atlas.config import (
    log_config_to_file,
    require_keys,
    save_config,
)
from pcdet_atlas.datasets import build_dataloader
from pcdet_atlas.models import build_network_from_config
from pcdet_atlas.models.detectors import TwoStageDetector
from pcdet_atlas.models.optimization import (
    build_optimizer,
    build_scheduler,
    check_optimization_config,
)
from pcdet_atlas.train_utils import (
    TrainState,
    eval_one_epoch,
    find_resume_checkpoint,
    iterations_per_epoch,
    load_checkpoint,
    resume_settings,
    retain_freed_cpu_memory,
    train_model,
)
from pcdet_atlas.train_utils.proposals import training_proposals
from pcdet_atlas.train_utils.setup import (
    add_common_args,
    count_arg,
    load_cfg,
    lock_output_folder,
    output_dir_for,
    require_dataset,
    setup_runtime,
)
from pcdet_atlas.train_utils.stages import (
    apply_stage_freezing,
    load_stage_init,
    stage_from_config,
    stage_init_checkpoint,
)
from pcdet_atlas.utils.cli import add_debug_flag, add_plugin_flag, import_plugins, run_tool
from pcdet_atlas.utils.common import create_logger


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_debug_flag(parser)
    add_plugin_flag(parser)
    groups = add_common_args(parser)
    train = parser.add_argument_group("training")
    train.add_argument(
        "--epochs",
        type=count_arg(1),
        default=None,
        help="epochs (default: the config's OPTIMIZATION.NUM_EPOCHS)",
    )
    train.add_argument("--pretrained_model", type=str, default=None, help="weights to start from")
    train.add_argument(
        "--allow_partial_stage_init",
        action="store_true",
        default=False,
        help="a STAGE config: start from the predecessor's newest checkpoint even when it is "
        "short of the predecessor's configured epochs (default: refuse, naming it)",
    )
    train.add_argument(
        "--sync_bn",
        action="store_true",
        default=False,
        help="synchronised BatchNorm across processes",
    )
    train.add_argument(
        "--merge_all_iters_to_one_epoch",
        action="store_true",
        default=False,
        help="run all epochs' iterations as one epoch (OpenPCDet's flag)",
    )
    train.add_argument(
        "--use_amp", action="store_true", default=False, help="mixed precision (CUDA)"
    )
    train.add_argument(
        "--num_epochs_to_eval", type=count_arg(0), default=0, help=">0: evaluate at the end"
    )
    ckpts = groups["outputs"]
    ckpts.add_argument(
        "--ckpt_save_interval",
        type=count_arg(1),
        default=1,
        help="epochs between checkpoints (default: 1)",
    )
    ckpts.add_argument(
        "--max_ckpt_save_num",
        type=count_arg(1),
        default=30,
        help="epoch checkpoints kept, oldest deleted first (default: 30)",
    )
    ckpts.add_argument(
        "--ckpt_save_time_interval",
        type=count_arg(0),
        default=300,
        help="seconds between rewrites of ckpt/latest_model.pth inside an epoch (0: every step)",
    )
    ckpts.add_argument(
        "--logger_iter_interval",
        type=count_arg(1),
        default=50,
        help="iterations between log lines (default: 50)",
    )
    ckpts.add_argument("--no_progress", action="store_true", default=False, help="no tqdm bars")
    groups["runtime"].add_argument(
        "--trim_every",
        type=count_arg(0),
        default=20,
        help="on CPU, give the heap's free memory back to the OS every N steps (0: once per "
        "epoch); bounds the memory a long run holds (default: %(default)s)",
    )
    return parser.parse_args(argv)


def main(argv=None) -> dict:
    args = parse_args(argv)
    import_plugins(args.plugin)
    with contextlib.ExitStack() as held:  # the output folder's lock, released at the end
        return train(args, held)


def train(args, held: contextlib.ExitStack) -> dict:
    """The work of :func:`main`; rank 0 holds the output folder's one-writer lock in ``held``
    from its first write on (one lock per run, however many processes train)."""
    cfg = load_cfg(args.cfg_file, args.set_cfgs)
    # before anything is built or written
    require_dataset(cfg, args.cfg_file)
    require_keys(cfg, ["OPTIMIZATION"], "the detector config")
    optim_cfg = cfg.OPTIMIZATION
    check_optimization_config(optim_cfg)
    for flag, path in (("--ckpt", args.ckpt), ("--pretrained_model", args.pretrained_model)):
        if path is not None and not Path(path).is_file():
            raise FileNotFoundError(f"{flag} {path}: no such checkpoint file")
    dist, rank, world, device = setup_runtime(
        device=args.device, launcher=args.launcher, tcp_port=args.tcp_port, threads=args.threads,
        seed=args.seed, fix_random_seed=args.fix_random_seed,
    )  # fmt: skip
    retained = device.type == "cpu" and not args.default_malloc and retain_freed_cpu_memory()
    batch_size = (
        args.batch_size if args.batch_size is not None else optim_cfg.BATCH_SIZE_PER_GPU * world
    )
    if batch_size % world:
        raise ValueError(f"--batch_size {batch_size} is not divisible by {world} processes")
    epochs = args.epochs if args.epochs is not None else optim_cfg.NUM_EPOCHS
    # the saved config and the checkpoints state the schedule in effect, flags included
    optim_cfg.NUM_EPOCHS, optim_cfg.BATCH_SIZE_PER_GPU = epochs, batch_size // world
    train_settings = resume_settings(
        cfg, batch_size=batch_size, processes=world, seed=args.seed, use_amp=args.use_amp,
        sync_bn=args.sync_bn, merge_all_iters_to_one_epoch=args.merge_all_iters_to_one_epoch,
    )  # fmt: skip

    out_dir = output_dir_for(cfg, args.output_root, args.extra_tag)
    ckpt_dir = output_dir_for(cfg, args.output_root, args.extra_tag, ("ckpt", "folder"))
    if rank == 0:
        lock_output_folder(out_dir, held, "tools/train.py training")
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    logger = create_logger(out_dir / f"train_{stamp}.log", rank=rank)
    logger.info(f"output: {out_dir}  processes: {world}  device: {device}  batch: {batch_size}")
    if retained:
        logger.info("CPU: freed memory is kept for reuse (glibc mallopt; --default_malloc: off)")
    if device.type == "cpu":
        logger.info(f"CPU: {torch.get_num_threads()} torch threads")

    dataset, loader, sampler = build_dataloader(
        cfg.DATA_CONFIG, cfg.CLASS_NAMES, batch_size // world, dist, workers=args.workers,
        seed=args.seed, logger=logger, training=True,
        merge_all_iters_to_one_epoch=args.merge_all_iters_to_one_epoch, total_epochs=epochs,
    )  # fmt: skip
    model = build_network_from_config(cfg)
    if args.sync_bn:
        model = torch.nn.SyncBatchNorm.convert_sync_batchnorm(model)
    model.to(device)
    if isinstance(model, TwoStageDetector):  # the frozen RPN's clean proposals, cached on disk
        table, source = training_proposals(
            model, cfg.DATA_CONFIG, cfg.CLASS_NAMES, device=device, workers=args.workers,
            logger=logger,
        )  # fmt: skip
        dataset.set_proposals(table, str(source), history=model.proposal_history)
    stage = stage_from_config(cfg)
    if stage is not None:  # before the optimizer: it takes only the stage's trainable parameters
        trainable = apply_stage_freezing(model, stage)
        logger.info(
            f"stage {stage.name}: training {', '.join(stage.train)} ({len(trainable)} tensors), "
            f"freezing the rest"
        )
    optimizer = build_optimizer(model, optim_cfg)
    steps_per_epoch = iterations_per_epoch(loader, epochs, args.merge_all_iters_to_one_epoch)
    scheduler = build_scheduler(
        optimizer, optim_cfg, iters_per_epoch=steps_per_epoch, total_epochs=epochs
    )
    scaler = torch.amp.GradScaler("cuda") if args.use_amp and device.type == "cuda" else None

    state = TrainState()
    resume = args.ckpt or find_resume_checkpoint(ckpt_dir)
    if resume is not None:
        total_steps = getattr(scheduler, "total_steps", None)
        ckpt = load_checkpoint(
            resume, model, optimizer, scheduler, scaler, train_settings=train_settings
        )
        if total_steps is not None and scheduler.total_steps != total_steps:
            raise ValueError(
                f"{resume} was trained on a {scheduler.total_steps}-step schedule; this run has "
                f"{total_steps} steps ({epochs} epochs x {steps_per_epoch} iterations): the "
                "training set or its sampling differs from the checkpoint's"
            )
        state = TrainState(
            epoch=ckpt["epoch"], it=ckpt["it"], epoch_it=ckpt.get("epoch_it", 0),
            epoch_loss_sums=dict(ckpt.get("epoch_loss_sums") or {}),
            runs=list(ckpt.get("train_runs") or []),
        )  # fmt: skip
        if state.it != state.epoch * steps_per_epoch + state.epoch_it:
            raise ValueError(
                f"{resume}: {state.it} iterations do not make {state.epoch} epochs of "
                f"{steps_per_epoch} plus {state.epoch_it}: the training set or batch size differs"
            )
        into = f"; {state.epoch_it} batches into epoch {state.epoch + 1}" if state.epoch_it else ""
        logger.info(f"resumed from {resume} (epoch {state.epoch}, iteration {state.it}{into})")
    elif stage is not None:
        try:
            init = stage_init_checkpoint(
                stage, output_root=args.output_root, extra_tag=args.extra_tag,
                pretrained_model=args.pretrained_model,
                allow_partial=args.allow_partial_stage_init,
            )  # fmt: skip
            new = load_stage_init(model, stage, init)
        except (FileNotFoundError, ValueError) as err:
            raise SystemExit(str(err)) from None
        modules = sorted({k.rsplit(".", 2)[0] for k in new})
        logger.info(f"stage {stage.name}: initialised from {init}; new in this stage: {modules}")
    elif args.pretrained_model is not None:
        model.load_params_from_file(args.pretrained_model)
        logger.info(f"initialised from {args.pretrained_model}")
    if rank == 0:  # only once the resumed checkpoint agrees with it
        save_config(cfg, out_dir / f"{cfg.TAG}.yaml")
        log_config_to_file(cfg, logger)
    tb_dir = output_dir_for(cfg, args.output_root, args.extra_tag, ("tensorboard", "folder"))
    tb_log = SummaryWriter(log_dir=str(tb_dir)) if rank == 0 else None
    if dist:
        model = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None
        )
    merged = " (one pass over the merged epochs)" if args.merge_all_iters_to_one_epoch else ""
    logger.info(
        f"training epochs {state.epoch + 1}..{epochs}, {steps_per_epoch} iterations each{merged}"
    )
    train_model(
        model, optimizer, scheduler, loader, sampler, state=state, total_epochs=epochs,
        device=device, seed=args.seed, grad_norm_clip=optim_cfg.GRAD_NORM_CLIP, ckpt_dir=ckpt_dir,
        ckpt_save_interval=args.ckpt_save_interval, max_ckpt_save_num=args.max_ckpt_save_num,
        scaler=scaler, use_amp=args.use_amp, tb_log=tb_log, logger=logger,
        logger_iter_interval=args.logger_iter_interval, show_progress=not args.no_progress,
        train_settings=train_settings, ckpt_save_time_interval=args.ckpt_save_time_interval,
        merge_all_iters_to_one_epoch=args.merge_all_iters_to_one_epoch,
        cpu_trim_every=args.trim_every or None,
    )  # fmt: skip
    result = {"output_dir": out_dir, "state": state}
    if args.num_epochs_to_eval > 0:
        _, test_loader, _ = build_dataloader(
            cfg.DATA_CONFIG, cfg.CLASS_NAMES, batch_size // world, dist, workers=args.workers,
            seed=args.seed, logger=logger, training=False,
        )  # fmt: skip
        ap_dict, _ = eval_one_epoch(
            model, test_loader, device=device, logger=logger, show_progress=not args.no_progress
        )
        result["ap_dict"] = ap_dict
        if tb_log is not None:
            for k, v in ap_dict.items():
                tb_log.add_scalar(f"eval/{k}", float(v), state.epoch)
    if tb_log is not None:
        tb_log.close()
    logger.info("training done")
    return result


if __name__ == "__main__":
    run_tool(main)
