"""Loader throughput (frames/s) for 1-frame and 4-frame input, measured side by side.

Reads the synthetic dataset (generated here, small, if ``--data_path`` holds none) through
``build_dataloader`` exactly as training/testing do, and prints frames/s per setting and the
4-frame / 1-frame ratio. Settings are interleaved over ``--repeats`` rounds (median reported) so
that machine load affects them alike.

    python tools/bench_loader.py --frames 40 --workers 0
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.datasets import build_dataloader

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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data_path", default=str(DEFAULT_ROOT))
    parser.add_argument("--frames", type=int, default=40, help="frames timed per setting")
    parser.add_argument("--workers", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    root = Path(args.data_path)
    _ensure_data(root)
    settings = [
        ("test  1-frame", "synthetic_waymo.yaml", False),
        ("test  4-frame", "synthetic_waymo_multiframe.yaml", False),
        ("train 1-frame (flip/rot/scale)", "synthetic_waymo.yaml", True),
        ("train 4-frame (flip/rot/scale)", "synthetic_waymo_multiframe.yaml", True),
    ]
    loaders = {name: _loader(cfg, root, training, args.workers) for name, cfg, training in settings}
    for loader in loaders.values():  # warm the page cache and the workers' imports
        _time(loader, 2)
    rates: dict[str, list[float]] = {name: [] for name, _, _ in settings}
    npts: dict[str, float] = {}
    for _ in range(args.repeats):
        for name, loader in loaders.items():
            rate, npts[name] = _time(loader, args.frames)
            rates[name].append(rate)
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
    main()
