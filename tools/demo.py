"""`make demo`: the embedded default end to end.

1. Generate the default synthetic Waymo-format dataset at ``data/synthetic_waymo`` (a finished
   dataset is reused as is) and print a summary of it.
2. Build the injection trace library from its train split (once).
3. Run three ATLAS variants (``clean``, ``inj_global_hard``, ``rem_40``) through
   ``AtlasWaymoDataset`` over the val sequence's first attack run and the frames around it, print
   what each frame's attack did (phantom points injected / visible, removal target tracked /
   fired / points removed) and the attack engine's work counters, and draw before/after pictures
   of one attacked frame per family under ``output/demo/``.
4. Evaluate the shipped CP4F checkpoint named by ``cfgs/atlas/synthetic/cp4f.yaml``
   (``checkpoints/cp4f_synthetic.pth``, docs/model_zoo.md) on the same three variants over the
   whole val sequence with ``tools/test.py``: the L2 mAP/mAPH and ASR table, and results.json.
   A missing checkpoint is an error naming the file (it ships with the repository).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from pcdet_atlas.attacks.atlas_dataset import AtlasWaymoDataset
from pcdet_atlas.attacks.counters import COUNTERS
from pcdet_atlas.config import REPO_ROOT, cfg_from_list, cfg_from_yaml_file
from pcdet_atlas.datasets.synthetic import create_synthetic_waymo, format_summary
from pcdet_atlas.utils.cli import RenamedFlag, add_debug_flag, run_tool
from pcdet_atlas.utils.common import create_logger

SYNTHETIC_ROOT = REPO_ROOT / "data" / "synthetic_waymo"
DATA_CFG = REPO_ROOT / "cfgs" / "dataset_configs" / "synthetic_waymo.yaml"
MODEL_CFG = REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "cp4f.yaml"
VARIANTS = ("clean", "inj_global_hard", "rem_40")
CLASS_NAMES = ["Vehicle", "Pedestrian", "Cyclist"]
OUT_DIR = REPO_ROOT / "output" / "demo"


def run_child(script: str, *args: str) -> None:
    """Run a tool of this repo in a child process; a failure stops the demo with its exit code."""
    cmd = [sys.executable, str(REPO_ROOT / "tools" / script), *args]
    print("$", " ".join(cmd[1:]), flush=True)
    subprocess.run(cmd, check=True, cwd=REPO_ROOT)


def ensure_trace_library(root: Path) -> None:
    attack_cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "attacks" / "inj_global_hard.yaml")
    path = Path(attack_cfg.TRACE_LIBRARY.PATH)
    path = path if path.is_absolute() else root / path
    if path.is_file():
        print(f"trace library: {path} (built earlier)")
        return
    run_child("data/build_trace_library.py", "--cfg", "cfgs/attacks/inj_global_hard.yaml",
             "--data_path", str(root))  # fmt: skip


def attack_showcase(root: Path, first: int, last: int) -> list[dict]:
    """Attack frames ``first..last`` of the val split with each variant; one row per variant."""
    data_cfg = cfg_from_yaml_file(DATA_CFG)
    cfg_from_list(["DATA_PATH", str(root)], data_cfg)
    rows = []
    for variant in VARIANTS:
        attack_cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "attacks" / f"{variant}.yaml")
        dataset = AtlasWaymoDataset(data_cfg, CLASS_NAMES, attack_cfg, training=False)
        frames = range(first, min(last, len(dataset) - 1) + 1)
        COUNTERS.reset()
        start = time.perf_counter()
        metas = [dataset[i]["attack"] for i in frames]
        seconds = time.perf_counter() - start
        spoofed = [m for m in metas if m["spoofed"]]
        rows.append(
            {
                "variant": variant,
                "frames": len(metas),
                "spoofed": len(spoofed),
                "injected": sum(m["num_spoof_points"] for m in spoofed),
                "visible": sum(m["num_visible"] for m in spoofed),
                "tracked": sum(m["tracked"] for m in spoofed),
                "fired": sum(m["fired"] for m in spoofed),
                "removed": sum(m["num_removed"] for m in spoofed),
                "targets": sum(
                    m["target_box"] is not None and not m["target_is_shadow"] for m in metas
                ),
                "ms_per_frame": 1000 * seconds / max(len(metas), 1),
                "counters": COUNTERS.snapshot(),
            }
        )  # fmt: skip
    return rows


def print_showcase(rows: list[dict], first: int, last: int) -> None:
    print(f"\nATLAS attacks on val frames {first}-{last} (first run = frames 32-63), 1-frame input")
    head = (f"{'variant':<16}{'spoofed':>8}{'injected':>10}{'visible':>9}{'tracked':>9}"
            f"{'fired':>7}{'scene_pts_removed':>19}{'targets':>9}{'ms/frame':>10}")  # fmt: skip
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['variant']:<16}{r['spoofed']:>8}{r['injected']:>10}{r['visible']:>9}"
              f"{r['tracked']:>9}{r['fired']:>7}{r['removed']:>19}{r['targets']:>9}"
              f"{r['ms_per_frame']:>10.1f}")  # fmt: skip
    print("\nattack engine work counters per variant (a clean variant must do none):")
    for r in rows:
        work = {k: v for k, v in r["counters"].items() if v}
        print(f"  {r['variant']:<16}{work if work else 'no attack work'}")


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_debug_flag(parser)
    parser.add_argument(
        "--data_path",
        "--root",
        action=RenamedFlag,
        old=("--root",),
        default=str(SYNTHETIC_ROOT),
        help="synthetic dataset root, generated when absent (default: %(default)s)",
    )
    parser.add_argument(
        "--frames",
        type=int,
        nargs=2,
        default=[30, 66],
        metavar=("FIRST", "LAST"),
        help="val frames of the attack showcase (default: 30 66)",
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    root = Path(args.data_path)
    # the detector of step 4: checked first, before minutes of data generation
    ckpt = cfg_from_yaml_file(MODEL_CFG).ATLAS.CHECKPOINT
    if not ckpt or not (REPO_ROOT / ckpt).is_file():
        raise SystemExit(
            f"{MODEL_CFG.relative_to(REPO_ROOT)}: ATLAS.CHECKPOINT {ckpt!r} is not a file; the "
            "shipped checkpoint is part of the repository (restore it with git, or train one as "
            "in docs/model_zoo.md)"
        )
    logger = create_logger()
    logger.info("synthetic dataset: %s (default size, seed 0)", root)
    summary = create_synthetic_waymo(
        root, seed=0, logger=logger, workers=min(2, os.cpu_count() or 1)
    )
    print(format_summary(summary))
    if summary["generated"] == 0:
        print("  (already generated earlier: nothing rewritten)")

    ensure_trace_library(root)
    first, last = args.frames
    rows = attack_showcase(root, first, last)
    print_showcase(rows, first, last)
    clean = next(r for r in rows if r["variant"] == "clean")
    if any(clean["counters"].values()):
        raise RuntimeError(f"the clean variant did attack work: {clean['counters']}")
    for variant in VARIANTS[1:]:
        out = str(OUT_DIR / f"{variant}_0040.png")
        attack = f"cfgs/attacks/{variant}.yaml"
        run_child("dev/visualize_attack.py", "--data_cfg", str(DATA_CFG), "--data_path", str(root),
                 "--attack", attack, "--frame", "40", "--out", out)  # fmt: skip

    # the demo's own evaluation directory: a rerun replaces it (tools/test.py refuses otherwise)
    run_child("test.py", "--cfg", str(MODEL_CFG), "--attacks", ",".join(VARIANTS), "--overwrite",
             "--set", "DATA_CONFIG.DATA_PATH", str(root))  # fmt: skip
    return {"summary": summary, "attacks": rows}


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    run_tool(main)
