"""Coverage and width of the ASR interval and of the paired model comparison on simulated
ATLAS-shaped data (docs/evaluation.md, "ASR interval"): the docs' tables.

Usage: ``python tools/dev/interval_coverage.py [--replicates 2000] [--seed 0]
[--runs_per_sequence 3]``
"""

from __future__ import annotations

import argparse

from pcdet_atlas.evaluation.intervals import (
    coverage_simulation,
    format_coverage_table,
    paired_simulation,
)
from pcdet_atlas.utils.cli import add_debug_flag, run_tool

RATES = (0.02, 0.05, 0.1, 0.3, 0.5, 0.7, 0.9, 0.95, 0.98)
SEQUENCES = (6, 12, 20)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_debug_flag(parser)
    sim = parser.add_argument_group("simulation")
    sim.add_argument("--replicates", type=int, default=2000, help="data sets per scenario")
    sim.add_argument("--seed", type=int, default=0, help="key of every scenario's generator")
    sim.add_argument(
        "--runs_per_sequence", type=int, default=3, help="spoof runs of 32 targets per sequence"
    )
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    common = dict(num_replicates=args.replicates, seed=args.seed,
                  runs_per_sequence=args.runs_per_sequence)  # fmt: skip
    print("ASR interval (asr_interval): coverage of the 95% interval / mean width over")
    print("2 x 1.96 x the ASR's true standard deviation\n")
    print(format_coverage_table(coverage_simulation(RATES, SEQUENCES, **common)))
    print("\nPaired difference of two models (paired_asr_differences): the same\n")
    print(format_coverage_table(paired_simulation(num_sequences=SEQUENCES, **common)))


if __name__ == "__main__":
    run_tool(main)
