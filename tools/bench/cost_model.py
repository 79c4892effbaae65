"""Device-hours of each model's evaluation suite (clean + attack variants, reusing clean
predictions) on a split of a given size, from measured per-frame costs.

    python tools/bench/cost_model.py --costs bench.json  # written by bench_models.py
    python tools/bench/cost_model.py --cfgs cfgs/atlas/synthetic/centerpoint.yaml \\
        --cost cfgs/atlas/synthetic/centerpoint.yaml=0.011 --frames 39987
    python tools/bench/cost_model.py --cost cfgs/atlas/synthetic/ptt_32f.yaml=0.016+0.174 \\
        --cfgs cfgs/atlas/synthetic/ptt_32f.yaml --processes 8

Per-frame costs: ``--costs`` reads what ``tools/bench/bench_models.py --json`` wrote (its
device and threads with it); ``--cost CFG=SECONDS`` (or ``CFG=RPN+SECOND_STAGE`` for a two-stage
model) gives one by hand, on ``--cost_device`` with ``--cost_threads``; a ``--cost`` wins over
a ``--costs`` file for the same config. Frames each model computes: from the variants' spoof
schedules (``--attacks``, the config's ``ATLAS.ATTACKS`` by default) on ``--frames`` frames cut
into sequences of ``--sequence_frames``, with the model's input reach, in the loader batches of
``--batch_size`` over ``--processes`` (the rule ``tools/test.py`` reuses clean predictions by;
the model is built, random weights, to read its reach; ``--reach CFG=N`` for one that cannot
be built here); or, with ``--results``, from the ``num_recomputed_frames`` a ``results.json``
recorded, scaled from its frames per variant to ``--frames``. A device-hour is a GPU for an
hour, or a CPU's latency times its threads (core-hours). The work is the library's
(:mod:`pcdet_atlas.train_utils.cost_model`).
"""

from __future__ import annotations

import argparse

from pcdet_atlas.config import cfg_from_yaml_file, resolve_cli_path
from pcdet_atlas.evaluation import load_results
from pcdet_atlas.train_utils.cost_model import (
    config_key,
    device_hours,
    parse_cost,
    read_bench_json,
    recorded_frames,
    scheduled_frames,
    sequence_lengths,
)
from pcdet_atlas.utils.cli import add_debug_flag, run_tool

SHIPPED = (
    "cfgs/atlas/synthetic/centerpoint.yaml", "cfgs/atlas/synthetic/cp4f.yaml",
    "cfgs/atlas/synthetic/msf_4f.yaml", "cfgs/atlas/synthetic/msf_8f.yaml",
    "cfgs/atlas/synthetic/ptt_32f.yaml", "cfgs/atlas/synthetic/phim.yaml",
    "cfgs/atlas/synthetic/phim_lot/stage3_finetune.yaml",
)  # fmt: skip


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_debug_flag(p)
    p.add_argument(
        "--cfgs",
        nargs="+",
        default=None,
        help="model configs (default: those of --results, else the 7 shipped ones)",
    )
    costs = p.add_argument_group("per-frame costs")
    costs.add_argument(
        "--costs",
        nargs="+",
        default=[],
        metavar="JSON",
        help="files of tools/bench/bench_models.py --json",
    )
    costs.add_argument(
        "--cost",
        nargs="+",
        default=[],
        metavar="CFG=S",
        help="CFG=SECONDS or CFG=RPN_SECONDS+SECOND_STAGE_SECONDS per frame",
    )
    costs.add_argument("--cost_device", default="cuda", help="device of --cost (default: cuda)")
    costs.add_argument(
        "--cost_threads",
        type=int,
        default=None,
        help="torch threads of a --cost_device cpu latency",
    )
    frames = p.add_argument_group("frames computed")
    frames.add_argument(
        "--frames",
        type=int,
        default=39987,
        help="frames per variant (default: Waymo's val split, 39,987)",
    )
    frames.add_argument(
        "--sequence_frames", type=int, default=198, help="frames per sequence (default: 198)"
    )
    frames.add_argument("--attacks", default="all", help="'all' (ATLAS.ATTACKS) or a comma list")
    frames.add_argument("--batch_size", type=int, default=1, help="total batch over processes")
    frames.add_argument("--processes", type=int, default=1, help="processes of one model's run")
    frames.add_argument(
        "--reach",
        nargs="+",
        default=[],
        metavar="CFG=N",
        help="a model's input reach, for a config that cannot be built here",
    )
    frames.add_argument(
        "--results",
        nargs="+",
        default=[],
        metavar="JSON",
        help="results.json files: frames computed as they recorded them",
    )
    args = p.parse_args(argv)
    if args.cost_device == "cpu" and args.cost and not args.cost_threads:
        p.error("--cost_device cpu needs --cost_threads (core-hours = latency x threads)")
    for flag in ("frames", "sequence_frames", "batch_size", "processes"):
        if getattr(args, flag) < 1:
            p.error(f"--{flag} {getattr(args, flag)}: expected >= 1")
    if args.batch_size % args.processes:
        p.error(f"--batch_size {args.batch_size} is not divisible by {args.processes} processes")
    return args


def _reach(cfg_file: str, overrides: dict[str, int]) -> tuple[int, int, int]:
    """``(input reach, point history, proposal history)`` of a model config."""
    from pcdet_atlas.models import build_network_from_config
    from pcdet_atlas.train_utils.atlas_eval import input_reach, point_history

    cfg = cfg_from_yaml_file(cfg_file)
    history = point_history(cfg.DATA_CONFIG)
    key = config_key(cfg_file)
    if key in overrides:
        return overrides[key], history, max(0, overrides[key] - history)
    try:
        model = build_network_from_config(cfg)
    except (FileNotFoundError, KeyError) as err:
        raise ValueError(
            f"{cfg_file}: cannot build the model ({err}); pass --reach {key}=N"
        ) from None
    reach = input_reach(model, cfg.DATA_CONFIG)
    return reach, history, reach - history


def main(argv=None) -> list[dict]:
    from pcdet_atlas.attacks.base import attack_from_file
    from pcdet_atlas.train_utils.atlas_eval import resolve_variants

    args = parse_args(argv)
    costs = {}
    for path in args.costs:
        costs.update(read_bench_json(resolve_cli_path(path)))
    for text in args.cost:
        key, cost = parse_cost(text, args.cost_device, args.cost_threads)
        costs[key] = cost
    reach_overrides = {}
    for text in args.reach:
        cfg, _, n = text.partition("=")
        if not n.isdigit():
            raise ValueError(f"--reach {text!r}: expected CFG=N (N >= 0 frames)")
        reach_overrides[config_key(cfg)] = int(n)
    recorded = {}
    for path in args.results:
        results = load_results(resolve_cli_path(path))
        recorded[config_key(results["config"])] = recorded_frames(results, path)
    cfg_files = args.cfgs or ([f"cfgs/{k}" for k in recorded] if recorded else list(SHIPPED))
    lengths = sequence_lengths(args.frames, args.sequence_frames)
    print(
        f"{args.frames:,} frames per variant in {len(lengths)} sequences of up to "
        f"{args.sequence_frames}; batch {args.batch_size}, {args.processes} processes per model\n"
    )
    print("| config | variants | per-frame cost | device | frames computed | of all | "
          "device-hours | frames from |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for cfg_file in cfg_files:
        key = config_key(cfg_file)
        if key not in costs:
            raise ValueError(
                f"no per-frame cost for {key} (give --costs <bench_models.py --json file> "
                f"or --cost {key}=SECONDS)"
            )
        cost = costs[key]
        if key in recorded:
            suite = recorded[key]
            n_variants = suite.variants
            scale = (
                args.frames * n_variants / suite.total
            )  # recorded frames per variant -> --frames
        else:
            cfg = cfg_from_yaml_file(cfg_file)
            variants = resolve_variants(args.attacks, cfg.get("ATLAS", {}))
            attacks = {name: attack_from_file(path) for name, path in variants}
            n_variants = len(attacks)
            reach, history, proposals = _reach(cfg_file, reach_overrides)
            suite = scheduled_frames(
                attacks, lengths, reach, rpn_reach=history if proposals else None,
                proposal_history=proposals, batch_size=args.batch_size // args.processes,
                world=args.processes,
            )  # fmt: skip
            scale = 1.0
        hours = device_hours(cost, suite, scale)
        frames = suite.frames * scale
        split = f"{cost.seconds * 1e3:,.0f} ms"
        if cost.rpn_seconds is not None:
            split += (
                f" ({cost.rpn_seconds * 1e3:,.0f} + {(cost.seconds - cost.rpn_seconds) * 1e3:,.0f})"
            )
        device = (
            cost.device if cost.device.startswith("cuda") else f"cpu x {cost.core_factor} threads"
        )
        computed = f"{frames:,.0f}"
        if suite.rpn_frames is not None:
            computed += f" (RPN {suite.rpn_frames * scale:,.0f})"
        print(f"| {key} | {n_variants} | {split} | {device} | {computed} | "
              f"{suite.frames / suite.total:.1%} | {hours:,.1f} | {suite.source} |")  # fmt: skip
        rows.append({"config": key, "hours": hours, "frames": frames, "device": device})
    by_device: dict[str, float] = {}
    for row in rows:
        by_device[row["device"]] = by_device.get(row["device"], 0.0) + row["hours"]
    for device, hours in by_device.items():
        print(f"\ntotal on {device}: {hours:,.1f} device-hours")
    return rows


if __name__ == "__main__":
    run_tool(main)
