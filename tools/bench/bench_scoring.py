"""Benchmark of scoring predictions made anywhere beside the metric tools/test.py runs.

    python tools/bench/bench_scoring.py --cfg cfgs/atlas/synthetic/cp4f.yaml \\
        --eval_dir output/atlas/synthetic/cp4f/default/eval/cp4f_synthetic/val/default

Input: the evaluation folder of a ``tools/test.py`` run (its ``results.json`` and each variant's
``<variant>/result.pkl``, whose frames carry the attack records the run served). In one process,
on the same files, alternately (``--repeats`` rounds; the load average printed beside each):

- **metric**: what ``tools/test.py`` runs after predicting a variant, the Waymo metric and the
  attack metrics (``atlas_eval.variant_entry`` on the file's frames and records; its
  ``timing_s.metric``), the variant's dataset built beforehand as ``tools/test.py`` has it;
- **scoring, records drawn**: ``tools/evaluate_predictions.py``'s whole work on the same files
  with the variants named (``score_predictions``: reading and checking every file, the split,
  each variant's attack records drawn from the attack, a spoofed frame simulated, the same
  metric, ``results.json``), timed end to end, with its per-variant ``attack_records`` and
  ``metric`` parts;
- **scoring, records read**: the same with each variant named by a folder holding what
  ``tools/data/generate_atlas.py`` writes for scoring (``atlas_attack_metadata.pkl``, written here
  from the run's records, and ``atlas_attack.yaml``), so no frame is simulated.

Prints a table per variant, the totals and the ratios to the metric, and whether the scored
entries equal the run's (ASR, targets, successes; AP within 1e-9).
"""

from __future__ import annotations

import argparse
import copy
import math
import os
import tempfile
import time
from pathlib import Path

import torch

from pcdet_atlas.attacks.atlas_dataset import AtlasWaymoDataset
from pcdet_atlas.config import (
    cfg_from_list,
    cfg_from_yaml_file,
    resolve_cli_path,
    save_config,
    to_plain,
)
from pcdet_atlas.evaluation import load_results
from pcdet_atlas.evaluation.results.schema import METRIC_KEYS
from pcdet_atlas.train_utils.atlas_eval import (
    build_variant_attacks,
    resolve_variants,
    variant_entry,
)
from pcdet_atlas.train_utils.score_predictions import (
    ATLAS_ATTACK_YAML,
    ATLAS_METADATA,
    score_predictions,
)
from pcdet_atlas.utils.cli import add_debug_flag, add_set_flag, run_tool
from pcdet_atlas.utils.common import save_pickle
from pcdet_atlas.utils.safe_pickle import load_pickle


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_debug_flag(parser)
    parser.add_argument("--cfg", required=True, help="the model config the run evaluated")
    parser.add_argument("--eval_dir", required=True, help="the tools/test.py evaluation folder")
    parser.add_argument("--data_path", default=None, help="the dataset root (its DATA_PATH)")
    parser.add_argument("--repeats", type=int, default=1, help="rounds of both sides")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    add_set_flag(
        parser, help="KEY VALUE ... overrides of --cfg, as the run had them (last on the line)"
    )
    return parser.parse_args(argv)


def load() -> str:
    return f"{os.getloadavg()[0]:.1f}"


def metric_pass(cfg, data_cfg, variants, attacks, annos) -> dict[str, float]:
    """``tools/test.py``'s metric time per variant: ``variant_entry`` on the run's frames."""
    times, clean = {}, None
    for name, _ in variants:
        dataset = AtlasWaymoDataset(data_cfg, cfg.CLASS_NAMES, attacks[name], training=False)
        timings: dict[str, float] = {}
        variant_entry(
            name, dataset, annos[name], [a["attack"] for a in annos[name]],
            class_names=cfg.CLASS_NAMES, clean_det_annos=clean,
            temporal_window=cfg.ATLAS.TEMPORAL_WINDOW, timings=timings,
        )  # fmt: skip
        times[name] = timings["metric"]
        if name == "clean":
            clean = annos[name]
    return times


def write_recorded_variants(root: Path, variants, annos) -> dict[str, Path]:
    """Per variant, a folder with what ``tools/data/generate_atlas.py`` writes for scoring (its
    ``atlas_attack_metadata.pkl`` and ``atlas_attack.yaml``), from the records the run served
    (the records generate_atlas writes are these: tests/train_utils/test_score_predictions.py)."""
    folders = {}
    for name, yaml_path in variants:
        folder = root / name
        records = {a["frame_id"]: {k: v for k, v in a["attack"].items() if k != "sequence_name"}
                   for a in annos[name]}  # fmt: skip
        attack_cfg = cfg_from_yaml_file(yaml_path)
        save_pickle({"variant": name, "attack_cfg": to_plain(attack_cfg), "frames": records},
                    folder / ATLAS_METADATA)  # fmt: skip
        save_config(attack_cfg, folder / ATLAS_ATTACK_YAML)
        folders[name] = folder
    return folders


def one_round(cfg, data_cfg, variants, attacks, annos, files, recorded, args, tmp) -> dict:
    """The three sides once each, in turn: the metric, scoring with the records drawn, scoring
    with the records read."""
    out = {"metric": {"load": load(), "s": metric_pass(cfg, data_cfg, variants, attacks, annos)}}
    for side, keys in (("drawn", {name: name for name, _ in variants}),
                       ("read", {name: str(recorded[name]) for name, _ in variants})):  # fmt: skip
        load_now, t0 = load(), time.perf_counter()
        results = score_predictions(
            data_cfg, cfg.CLASS_NAMES, {keys[name]: files[name] for name, _ in variants},
            Path(tmp) / side, model="bench", config=args.cfg, atlas_cfg=cfg.ATLAS,
            temporal_window=cfg.ATLAS.TEMPORAL_WINDOW,
        )  # fmt: skip
        out[side] = {"s": time.perf_counter() - t0, "load": load_now, "results": results}
    return out


def same_entries(got: dict, want: dict) -> bool:
    if any(got[key] != want[key] for key in ("asr", "num_targets", "num_success")):
        return False
    return all(got[k] == want[k] if want[k] is None else math.isclose(got[k], want[k], abs_tol=1e-9)
               for k in METRIC_KEYS)  # fmt: skip


def main(argv=None) -> dict:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    cfg = cfg_from_yaml_file(args.cfg)
    if args.set_cfgs:
        cfg_from_list(args.set_cfgs, cfg)
    data_cfg = copy.deepcopy(cfg.DATA_CONFIG)
    if args.data_path is not None:
        data_cfg.DATA_PATH = str(resolve_cli_path(args.data_path))
    eval_dir = resolve_cli_path(args.eval_dir)
    run = load_results(eval_dir / "results.json")
    names = list(run["variants"])
    variants = resolve_variants(",".join(names), cfg.ATLAS)
    files = {name: eval_dir / name / "result.pkl" for name, _ in variants}
    annos = {name: load_pickle(path) for name, path in files.items()}
    attacks = build_variant_attacks(variants, resolve_cli_path(data_cfg.DATA_PATH))
    num_frames = len(next(iter(annos.values())))
    print(f"{len(variants)} variants x {num_frames} frames of {args.eval_dir}; torch "
          f"{torch.__version__}, {args.threads} thread(s)")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        recorded = write_recorded_variants(Path(tmp) / "recorded", variants, annos)
        rounds = [one_round(cfg, data_cfg, variants, attacks, annos, files, recorded, args, tmp)
                  for _ in range(args.repeats)]  # fmt: skip
    best = min(rounds, key=lambda r: r["drawn"]["s"])
    metric = best["metric"]
    print("\n| variant | test.py metric s | scoring, records drawn: attack records s | metric s |"
          " scoring, records read: attack records s | metric s |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for name, _ in variants:
        drawn = best["drawn"]["results"]["variants"][name]["extra"]["timing_s"]
        read = best["read"]["results"]["variants"][name]["extra"]["timing_s"]
        cells = [metric["s"][name], drawn["attack_records"], drawn["metric"],
                 read["attack_records"], read["metric"]]  # fmt: skip
        print(f"| {name} | " + " | ".join(f"{c:.2f}" for c in cells) + " |")
    total_metric = sum(metric["s"].values())
    print(f"\ntools/test.py's metric, all variants: {total_metric:.1f} s (load {metric['load']})")
    for side, what in (("drawn", "the attack records drawn on the fly"),
                       ("read", "the records a generate_atlas output holds")):  # fmt: skip
        took, ratio = best[side]["s"], best[side]["s"] / total_metric
        print(f"tools/evaluate_predictions.py, {what}: {took:.1f} s (load "
              f"{best[side]['load']}), {ratio:.2f}x the metric")  # fmt: skip
    equal = all(same_entries(best[side]["results"]["variants"][n], run["variants"][n])
                for side in ("drawn", "read") for n, _ in variants)  # fmt: skip
    print(f"scored entries equal the run's (ASR, targets, successes; AP within 1e-9): {equal}")
    scoring_s = best["drawn"]["s"]
    return {"metric_s": total_metric, "scoring_s": scoring_s, "read_s": best["read"]["s"],
            "equal": equal}  # fmt: skip


if __name__ == "__main__":
    run_tool(main)
