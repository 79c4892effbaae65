"""Loader throughput (frames/s) for 1-frame and 4-frame input, measured side by side.

Reads the synthetic dataset (generated here, small, if ``--data_path`` holds none) through
``build_dataloader`` exactly as training/testing do, and prints frames/s per setting and the
4-frame / 1-frame ratio. Settings are interleaved over ``--repeats`` rounds (median reported) so
that machine load affects them alike.

    python tools/bench/bench_loader.py --frames 40 --workers 0

``--baseline_src DIR`` measures another source tree side by side (e.g. an older commit unpacked
with ``git archive <commit> pcdet_atlas cfgs | tar -x -C DIR``): each round runs this script once
with ``DIR`` and once with this tree first on ``PYTHONPATH`` (separate processes, alternating),
and the table shows both medians and the speed-up.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.datasets import build_dataloader
from pcdet_atlas.utils.cli import add_debug_flag, baseline_tree_env, run_tool

CFG_DIR = REPO_ROOT / "cfgs" / "dataset_configs"
CLASS_NAMES = ["Vehicle", "Pedestrian", "Cyclist"]


DEFAULT_ROOT = REPO_ROOT / "data" / "synthetic_waymo"


def _ensure_data(root: Path) -> None:
    if (root / "ImageSets" / "val.txt").is_file():
        return
    from pcdet_atlas.datasets.synthetic import create_synthetic_waymo

    if root.resolve() == DEFAULT_ROOT.resolve():  # the default dataset, as `make demo` makes it
        print(f"no dataset at {root}: generating the default synthetic dataset")
        create_synthetic_waymo(root, seed=0, workers=2)
    else:
        print(f"no dataset at {root}: generating a small synthetic one (1 train x 20, 1 val x 40)")
        create_synthetic_waymo(root, {"train": 1, "val": 1}, {"train": 20, "val": 40}, seed=0)


def _loader(cfg_name: str, root: Path, training: bool, workers: int):
    cfg = cfg_from_yaml_file(CFG_DIR / cfg_name)
    cfg.SAMPLED_INTERVAL = {"train": 1, "test": 1}
    if training:  # world augmentations; GT sampling needs a database, benchmarked separately
        cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST = [
            a for a in cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST if a.NAME != "gt_sampling"
        ]
    _, loader, _ = build_dataloader(
        cfg,
        CLASS_NAMES,
        batch_size=1,
        dist=False,
        root_path=root,
        workers=workers,
        seed=0,
        training=training,
    )
    return loader


def _time(loader, frames: int) -> tuple[float, float]:
    """(frames/s, mean points per frame) over the first ``frames`` samples."""
    points = 0
    start = time.perf_counter()
    for i, batch in enumerate(loader):
        points += len(batch["points"])
        if i + 1 >= frames:
            break
    elapsed = time.perf_counter() - start
    return (i + 1) / elapsed, points / (i + 1)


SETTINGS = [
    ("test  1-frame", "synthetic_waymo.yaml", False),
    ("test  4-frame", "synthetic_waymo_multiframe.yaml", False),
    ("train 1-frame (flip/rot/scale)", "synthetic_waymo.yaml", True),
    ("train 4-frame (flip/rot/scale)", "synthetic_waymo_multiframe.yaml", True),
]


def _measure(root: Path, frames: int, workers: int, repeats: int):
    """``({setting: [frames/s per round]}, {setting: points per frame})``."""
    loaders = {name: _loader(cfg, root, training, workers) for name, cfg, training in SETTINGS}
    for loader in loaders.values():  # warm the page cache and the workers' imports
        _time(loader, 2)
    rates: dict[str, list[float]] = {name: [] for name, _, _ in SETTINGS}
    npts: dict[str, float] = {}
    for _ in range(repeats):
        for name, loader in loaders.items():
            rate, npts[name] = _time(loader, frames)
            rates[name].append(rate)
    return rates, npts


def _compare(args, root: Path) -> None:
    """Alternate rounds of the baseline tree and this tree, one process each."""
    trees = {"baseline": Path(args.baseline_src).resolve(), "this tree": REPO_ROOT}
    for tree in trees.values():
        if not (tree / "pcdet_atlas" / "__init__.py").is_file():
            raise SystemExit(f"--baseline_src: no pcdet_atlas package under {tree}")
    rates = {tree: {name: [] for name, _, _ in SETTINGS} for tree in trees}
    npts = {}
    for _ in range(args.repeats):
        for tree, src in trees.items():
            env = baseline_tree_env(src)
            cmd = [
                sys.executable,
                __file__,
                "--data_path",
                str(root),
                "--frames",
                str(args.frames),
                "--workers",
                str(args.workers),
                "--repeats",
                "1",
                "--json",
            ]
            out = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True).stdout
            result = json.loads(out.strip().splitlines()[-1])
            if not Path(result["package"]).resolve().is_relative_to(src):
                raise SystemExit(f"{tree}: imported {result['package']}, not {src}")
            for name in rates[tree]:
                rates[tree][name] += result["rates"][name]
            npts = result["npts"]
    print(
        f"data: {root}  frames/setting: {args.frames}  workers: {args.workers}  "
        f"rounds: {args.repeats} (median, alternating)  baseline: {trees['baseline']}"
    )
    print(f"{'setting':34s} {'baseline f/s':>12s} {'this f/s':>9s} {'speed-up':>9s} {'points':>8s}")
    for name, _, _ in SETTINGS:
        base = statistics.median(rates["baseline"][name])
        this = statistics.median(rates["this tree"][name])
        print(f"{name:34s} {base:12.1f} {this:9.1f} {this / base:8.2f}x {npts[name]:8.0f}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_debug_flag(parser)
    parser.add_argument(
        "--data_path", default=str(DEFAULT_ROOT), help="dataset root (default: the demo dataset)"
    )
    parser.add_argument("--frames", type=int, default=40, help="frames timed per setting")
    parser.add_argument("--workers", type=int, default=0, help="DataLoader workers (default: 0)")
    parser.add_argument("--repeats", type=int, default=3, help="timed passes (default: 3)")
    parser.add_argument("--baseline_src", default=None, help="source tree to compare against")
    parser.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    root = Path(args.data_path)
    _ensure_data(root)
    if args.baseline_src:
        _compare(args, root)
        return
    rates, npts = _measure(root, args.frames, args.workers, args.repeats)
    if args.json:
        package = str(Path(sys.modules["pcdet_atlas"].__file__).parent)
        print(json.dumps({"rates": rates, "npts": npts, "package": package}))
        return
    print(
        f"data: {root}  frames/setting: {args.frames}  workers: {args.workers}  "
        f"repeats: {args.repeats} (median)"
    )
    print(f"{'setting':34s} {'frames/s':>9s} {'points/frame':>13s}")
    med = {name: statistics.median(r) for name, r in rates.items()}
    for name in rates:
        print(f"{name:34s} {med[name]:9.1f} {npts[name]:13.0f}")
    print(
        f"ratio 4-frame / 1-frame: test {med['test  4-frame'] / med['test  1-frame']:.2f}, "
        f"train {med['train 4-frame (flip/rot/scale)'] / med['train 1-frame (flip/rot/scale)']:.2f}"
    )


if __name__ == "__main__":
    run_tool(main)
