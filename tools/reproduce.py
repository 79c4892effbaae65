"""Evaluate every shipped synthetic model on all 13 ATLAS variants and write the paper's report.

    python tools/reproduce.py                                   # make reproduce
    python tools/reproduce.py --data_path data/synthetic_waymo_val6 --out docs/results
    python tools/reproduce.py --cfgs cfgs/atlas/synthetic/cp4f.yaml --out /tmp/cp4f --device cuda

For each model config (default: every config under ``cfgs/atlas/synthetic/`` whose
``ATLAS.CHECKPOINT`` file exists) this runs ``tools/test.py --attacks all`` on the dataset at
``--data_path`` (clean predictions reused where an attack leaves a frame's input untouched), then
``tools/report.py`` over the results into ``--out``, with the wall time of each model and of the
whole run appended to ``report.md`` and written to ``run.json``. The injection variants' trace
library is built from the dataset's train split first if it is missing. The dataset:
docs/synthetic.md "A larger validation split".
"""

from __future__ import annotations

import argparse
import json
import platform
import shlex
import sys
import time
from pathlib import Path

import torch

from pcdet_atlas.attacks.trace_library import TraceFilter, build_trace_library
from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.evaluation.results import collect_results, write_report
from pcdet_atlas.train_utils.atlas_eval import resolve_variants
from pcdet_atlas.utils.common import load_tool

DEFAULT_DATA = REPO_ROOT / "data" / "synthetic_waymo_val6"
DEFAULT_OUT = REPO_ROOT / "docs" / "results"
TAG = "reproduce"


def shipped_configs() -> list[Path]:
    """Synthetic model configs whose checkpoint ships (stage configs without one are skipped)."""
    out = []
    for path in sorted((REPO_ROOT / "cfgs" / "atlas" / "synthetic").rglob("*.yaml")):
        ckpt = cfg_from_yaml_file(path).get("ATLAS", {}).get("CHECKPOINT")
        if ckpt and (REPO_ROOT / ckpt).is_file():
            out.append(path)
    return out


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data_path", default=str(DEFAULT_DATA), help="synthetic dataset root")
    p.add_argument("--out", default=str(DEFAULT_OUT), help="report folder")
    p.add_argument("--cfgs", nargs="+", default=None, help="model configs (default: shipped)")
    p.add_argument("--device", default=None, help="cpu / cuda (default: auto)")
    p.add_argument("--workers", default="2", help="loader workers of tools/test.py")
    p.add_argument("--output_root", default=None, help="tools/test.py's output root")
    p.add_argument("--no_reuse", action="store_true", help="run the model on every frame")
    p.add_argument("--attacks", default="all", help="variants of tools/test.py (default: all)")
    p.add_argument("--set", nargs=argparse.REMAINDER, default=[], dest="set_cfgs",
                   help="KEY VALUE pairs passed on to tools/test.py's --set")  # fmt: skip
    return p.parse_args(argv)


def ensure_trace_libraries(root: Path, cfgs: list[Path], attacks: str) -> None:
    """Build the trace library of every requested injection variant that lacks one."""
    for cfg_path in cfgs:
        atlas_cfg = cfg_from_yaml_file(cfg_path).get("ATLAS", {})
        for _, attack_path in resolve_variants(attacks, atlas_cfg):
            library = cfg_from_yaml_file(attack_path).get("TRACE_LIBRARY")
            if library is None:
                continue
            path = Path(library.PATH)
            path = path if path.is_absolute() else root / path
            if not path.is_file():
                print(f"building the trace library {path}", flush=True)
                build_trace_library(root, TraceFilter.from_config(library)).save(path)


def main(argv=None) -> dict:
    args = parse_args(argv)
    root = Path(args.data_path)
    if not (root / "ImageSets").is_dir():
        raise FileNotFoundError(
            f"{root}: no synthetic dataset there (generate it: see docs/synthetic.md "
            "'A larger validation split', or run make reproduce)"
        )
    cfgs = [Path(c) for c in args.cfgs] if args.cfgs else shipped_configs()
    ensure_trace_libraries(root, cfgs, args.attacks)
    test = load_tool("test")
    start = time.perf_counter()
    runs = []
    for cfg in cfgs:
        t0 = time.perf_counter()
        argv_test = [
            "--cfg",
            str(cfg),
            "--attacks",
            args.attacks,
            "--extra_tag",
            TAG,
            "--eval_tag",
            TAG,
            "--overwrite",
            "--no_progress",
            "--workers",
            args.workers,
        ]
        if args.output_root:
            argv_test += ["--output_root", args.output_root]
        if args.device:
            argv_test += ["--device", args.device]
        if args.no_reuse:
            argv_test.append("--no_reuse")
        argv_test += ["--set", "DATA_CONFIG.DATA_PATH", str(root), *args.set_cfgs]
        print("$ python tools/test.py " + shlex.join(argv_test), flush=True)
        ret = test.main(argv_test)
        runs.append({"config": str(cfg), "results": str(ret["output_dir"] / "results.json"),
                     "wall_s": round(time.perf_counter() - t0, 1)})  # fmt: skip
    total = round(time.perf_counter() - start, 1)
    found = collect_results([r["results"] for r in runs])
    results = [r for _, r in found]
    device = str(results[0].get("extra", {}).get("device", "?"))
    frames = next(iter(results[0]["variants"].values()))["num_frames"]
    command = shlex.join(sys.argv[1:] if argv is None else argv)
    lines = [
        "## How these results were produced",
        "",
        f"`python tools/reproduce.py {command}` on `{root.name}` ({frames} val frames), device "
        f"{device}, {torch.get_num_threads()} torch threads, {platform.machine()}; total wall "
        f"time **{total / 60:.1f} min**.",
        "",
        "| Model | Wall time (min) | Frames recomputed | Frames reused |",
        "|:---|---:|---:|---:|",
    ]
    for run, r in zip(runs, results):
        recomputed = sum(v["num_recomputed_frames"] or 0 for v in r["variants"].values())
        reused = sum(v["num_reused_frames"] or 0 for v in r["variants"].values())
        lines.append(f"| {r['model']} | {run['wall_s'] / 60:.1f} | {recomputed} | {reused} |")
    out = write_report(
        results, args.out, sources=[r["results"] for r in runs], latex=True,
        command=None, appendix="\n".join(lines),
    )  # fmt: skip
    run_info = {"data_path": str(root), "device": device, "total_wall_s": total, "runs": runs}
    (Path(args.out) / "run.json").write_text(json.dumps(run_info, indent=2) + "\n")
    print(f"report: {out['report']}  total {total / 60:.1f} min")
    return {**out, "run": run_info}


if __name__ == "__main__":
    main()
