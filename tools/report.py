"""Write the paper's report (tables and figures) from results.json files of tools/test.py.

    python tools/report.py --results output/atlas/synthetic --out_dir report/
    python tools/report.py --results a/results.json b/results.json --out_dir report/ --latex
    python tools/report.py --results docs/results/results --out_dir /tmp/report  # the committed one

``--results`` (alias ``--results_dir``) takes results files and/or folders (below a folder every
``results.json`` and ``<model>.results.json`` is read, and each of them gzip-compressed as
``.gz``, as ``tools/reproduce.py`` archives the results its report was made from in the report's
``results/``); each model must appear once. ``--out`` (alias ``--out_dir``) receives
``report.md``, the figures (each a PNG and a PDF beside it) and, with ``--latex``,
``report.tex`` (booktabs tables). What each table and figure shows: docs/evaluation.md
"Report".
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from pcdet_atlas.config import repo_relative
from pcdet_atlas.evaluation.results.report import (
    DEFAULT_LOT_CONTROL,
    DEFAULT_LOT_PAIR,
    collect_results,
    write_report,
)
from pcdet_atlas.utils.cli import (
    RenamedFlag,
    add_debug_flag,
    add_plugin_flag,
    import_plugins,
    run_tool,
)


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_debug_flag(p)
    add_plugin_flag(p)
    p.add_argument("--results", "--results_dir", dest="results", nargs="+", required=True,
                   help="results files (.json, .json.gz) or folders holding them")  # fmt: skip
    p.add_argument("--out_dir", "--out", action=RenamedFlag, old=("--out",), required=True,
                   help="output folder")  # fmt: skip
    p.add_argument("--latex", action="store_true", help="also write report.tex")
    p.add_argument(
        "--lot_pair", nargs=2, default=list(DEFAULT_LOT_PAIR), metavar=("BASE", "DEFENDED"),
        help="model names of the LOT ablation (default: %(default)s)",
    )  # fmt: skip
    p.add_argument(
        "--lot_control", default=DEFAULT_LOT_CONTROL, metavar="NAME",
        help="model name of the ablation's no-LOT control, compared with DEFENDED where the "
        "results have it (default: %(default)s)",
    )  # fmt: skip
    args = p.parse_args(argv)
    if Path(args.out_dir).exists() and not Path(args.out_dir).is_dir():
        p.error(
            f"--out_dir {args.out_dir}: an existing file, expected a folder (or a path to create "
            "one)"
        )
    return args


def main(argv=None) -> dict:
    args = parse_args(argv)
    import_plugins(args.plugin)
    found = collect_results(args.results)
    command = "python tools/report.py " + shlex.join(sys.argv[1:] if argv is None else argv)
    out = write_report(
        [r for _, r in found], args.out_dir, sources=[str(repo_relative(p)) for p, _ in found],
        latex=args.latex, lot_pair=tuple(args.lot_pair), lot_control=args.lot_control,
        command=command,
    )  # fmt: skip
    print(f"report: {out['report']}" + (f"  latex: {out['latex']}" if out["latex"] else ""))
    for name, result in out["figures"].items():
        print(f"  {name}: " + ("written" if isinstance(result, Path) else f"not drawn ({result})"))
    return out


if __name__ == "__main__":
    run_tool(main)
