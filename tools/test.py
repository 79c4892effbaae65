"""Evaluate a detector on ATLAS variants: Waymo L2 mAP/mAPH and attack success rate per variant.

    python tools/test.py --cfg cfgs/atlas/synthetic/cp4f.yaml --attacks clean,inj_global_hard,rem_40
    python tools/test.py --cfg cfgs/atlas/synthetic/cp4f.yaml --attacks all
    python tools/test.py --cfg cfgs/atlas/synthetic/cp4f.yaml --eval_all --start_epoch 10
    torchrun --nproc_per_node 2 tools/test.py --cfg ... --launcher pytorch

``--ckpt`` defaults to the config's ``ATLAS.CHECKPOINT``; ``--eval_all`` evaluates every
``checkpoint_epoch_N.pth`` of ``--ckpt_dir`` (default: the run's ``ckpt/``) with
N >= ``--start_epoch``, in epoch order. Output, per checkpoint:
``output/<group>/<tag>/<extra_tag>/eval/<name>/<split>/<eval_tag>/`` with ``results.json``
(schema in docs/evaluation.md; rewritten after each variant, so a failure keeps the variants
done), ``<variant>/result.pkl``, the merged config and a log; the table is printed as the paper
lays it out. While it writes an evaluation directory, a call holds that directory's lock: a
second call into it stops at once, naming the first's PID, host and start time.

The clean variant runs first; under an attack variant, a frame whose whole model input the
attack leaves untouched takes the clean run's prediction, bitwise what the model would return
(docs/evaluation.md "Reusing clean predictions"; ``--no_reuse`` runs every frame). With
``--prediction_store DIR``, an RPN's predictions are kept in DIR by their inputs and read by the
models that feed it the same inputs (docs/evaluation.md "Sharing the RPN between models").
An evaluation directory that already holds files is an error unless ``--overwrite`` (delete it
first) or ``--resume`` (keep the variants an earlier call with the same setting finished there).

The work is the library's (:mod:`pcdet_atlas.train_utils.atlas_run`, whose docstrings state the
folder layout and the resume rules); this file maps the flags onto its ``EvalSettings``. On CPU
the process keeps freed memory for reuse (``--default_malloc``: off; docs/benchmarks.md).
"""

from __future__ import annotations

import argparse

from pcdet_atlas.train_utils.atlas_run import EvalSettings, run_evaluation
from pcdet_atlas.train_utils.cpu_memory import retain_freed_cpu_memory
from pcdet_atlas.train_utils.setup import add_common_args, count_arg, folder_name_arg
from pcdet_atlas.utils.cli import add_debug_flag, add_plugin_flag, import_plugins, run_tool


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_debug_flag(parser)
    add_plugin_flag(parser)
    groups = add_common_args(parser)
    evaluation = parser.add_argument_group("evaluation")
    evaluation.add_argument("--attacks", default="clean", help="'all' or a comma list of variants")
    evaluation.add_argument(
        "--eval_tag", type=folder_name_arg, default="default",
        help="the evaluation's folder under eval/<checkpoint>/<split>/",
    )  # fmt: skip
    evaluation.add_argument(
        "--eval_all", action="store_true", default=False,
        help="evaluate every checkpoint_epoch_N.pth of --ckpt_dir (N >= --start_epoch), in order",
    )  # fmt: skip
    evaluation.add_argument(
        "--ckpt_dir", type=str, default=None,
        help="checkpoints of --eval_all (default: the run's ckpt/)",
    )  # fmt: skip
    evaluation.add_argument(
        "--start_epoch", type=count_arg(0), default=0,
        help="--eval_all: the first epoch evaluated",
    )  # fmt: skip
    evaluation.add_argument(
        "--save_to_file", action="store_true", default=False,
        help="also write <variant>/final_result/data/<frame_id>.txt per frame",
    )  # fmt: skip
    evaluation.add_argument(
        "--overwrite", action="store_true", default=False,
        help="delete an existing evaluation directory first (default: refuse to run)",
    )  # fmt: skip
    evaluation.add_argument(
        "--resume", action="store_true", default=False,
        help="keep the requested variants an earlier call with the same config, checkpoint, "
        "batch size and processes finished in the evaluation directory (with the same attack "
        "config); evaluate the rest",
    )  # fmt: skip
    evaluation.add_argument(
        "--no_reuse", action="store_true", default=False,
        help="run the model on every frame of every variant (default: a frame whose input the "
        "attack leaves untouched takes the clean run's prediction, bitwise the same)",
    )  # fmt: skip
    evaluation.add_argument(
        "--prediction_store", default=None, metavar="DIR",
        help="keep the predictions of a model that serves as an RPN (CenterPoint, CP-4f), or of "
        "a two-stage model's RPN, in DIR, found by their inputs; a later model that feeds the "
        "same RPN the same inputs reads them (docs/evaluation.md 'Sharing the RPN')",
    )  # fmt: skip
    groups["outputs"].add_argument(
        "--no_progress", action="store_true", default=False, help="no tqdm bars"
    )
    args = parser.parse_args(argv)
    try:
        args.settings = settings_of(args)
    except ValueError as err:  # flags that contradict each other
        parser.error(str(err))
    return args


def settings_of(args: argparse.Namespace) -> EvalSettings:
    """The flags, by meaning."""
    return EvalSettings(
        cfg_file=args.cfg_file, set_cfgs=tuple(args.set_cfgs or ()), attacks=args.attacks,
        ckpt=args.ckpt, eval_all=args.eval_all, ckpt_dir=args.ckpt_dir,
        start_epoch=args.start_epoch, output_root=args.output_root, extra_tag=args.extra_tag,
        eval_tag=args.eval_tag, batch_size=args.batch_size, workers=args.workers, seed=args.seed,
        fix_random_seed=args.fix_random_seed, device=args.device, launcher=args.launcher,
        tcp_port=args.tcp_port, threads=args.threads, save_to_file=args.save_to_file,
        overwrite=args.overwrite, resume=args.resume, reuse_clean=not args.no_reuse,
        prediction_store=args.prediction_store, show_progress=not args.no_progress,
    )  # fmt: skip


def main(argv=None) -> dict:
    args = parse_args(argv)
    import_plugins(args.plugin)
    if not args.default_malloc:  # CPU inference reuses freed pages (harmless on a GPU run)
        retain_freed_cpu_memory()
    return run_evaluation(args.settings)


if __name__ == "__main__":
    run_tool(main)
