"""How many points the hard voxelization's caps drop, per voxel config (``MeanVFE``).

    python tools/dev/voxel_caps.py --data_path data/synthetic_waymo --caps 5 20 24 32 \\
        --cfgs cfgs/atlas/cp4f_voxel.yaml cfgs/atlas/synthetic/cp4f_voxel.yaml

For each config, ``--frames`` val frames spread evenly over the split of ``--data_path`` (default
the config's own ``DATA_PATH``) go through the config's test pipeline (its frames, range and
shuffle) and :func:`~pcdet_atlas.models.model_utils.hard_voxelize.hard_voxelize` on the config's
voxel grid and test voxel cap, once per ``MAX_POINTS_PER_VOXEL`` in ``--caps`` (the config's own
value is marked). Printed per cap: the share of the points inside the range that no voxel keeps,
over all frames, and the voxels per frame. A real-Waymo config on the synthetic data shows what
its 0.1 m grid does to the same frames.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from pcdet_atlas.config import cfg_from_yaml_file, resolve_cli_path
from pcdet_atlas.datasets import build_dataloader
from pcdet_atlas.datasets.dataset import collate_batch
from pcdet_atlas.models.model_utils.hard_voxelize import hard_voxelize
from pcdet_atlas.models.model_utils.voxelize import VoxelGrid, voxelize
from pcdet_atlas.utils.cli import add_debug_flag, run_tool


def parse_args():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_debug_flag(p)
    p.add_argument("--cfgs", nargs="+", required=True, help="voxel model configs (MeanVFE)")
    p.add_argument("--data_path", default=None, help="dataset root (default: each config's)")
    p.add_argument(
        "--caps",
        type=int,
        nargs="+",
        default=[5, 10, 20, 32],
        help="points-per-voxel caps compared (default: 5 10 20 32)",
    )
    p.add_argument("--frames", type=int, default=24, help="val frames, spread over the split")
    return p.parse_args()


def cap_table(cfg_file: str, data_path: str | None, caps: list[int], frames: int) -> None:
    cfg = cfg_from_yaml_file(cfg_file)
    vfe = cfg.MODEL.VFE
    if vfe.get("NAME") != "MeanVFE":
        raise SystemExit(f"{cfg_file}: MODEL.VFE.NAME is {vfe.get('NAME')!r}, not MeanVFE")
    if data_path is not None:
        cfg.DATA_CONFIG.DATA_PATH = str(resolve_cli_path(data_path))
    dataset, _, _ = build_dataloader(
        cfg.DATA_CONFIG, cfg.CLASS_NAMES, 1, False, workers=0, training=False
    )
    grid = VoxelGrid(
        tuple(map(float, cfg.DATA_CONFIG.POINT_CLOUD_RANGE)), tuple(map(float, vfe.VOXEL_SIZE))
    )
    own, max_voxels = int(vfe.MAX_POINTS_PER_VOXEL), int(vfe.MAX_NUMBER_OF_VOXELS["test"])
    caps = sorted({*caps, own})
    picks = np.unique(np.linspace(0, len(dataset) - 1, frames).round().astype(int))
    in_range, kept = 0, {c: 0 for c in caps}
    voxels = {c: 0 for c in caps}
    for index in picks:
        points = torch.from_numpy(collate_batch([dataset[int(index)]])["points"])
        in_range += int(voxelize(points, grid).point_mask.sum())
        for cap in caps:
            vox = hard_voxelize(points, grid, cap, max_voxels)
            kept[cap] += int(vox.voxel_num_points.sum())
            voxels[cap] += vox.voxel_coords.shape[0]
    print(
        f"\n{cfg_file}: voxels {list(vfe.VOXEL_SIZE)} m, test voxel cap {max_voxels:,}, "
        f"{len(picks)} val frames of {dataset.root_path}, {in_range / len(picks):,.0f} points "
        f"in range per frame\n"
    )
    print("| MAX_POINTS_PER_VOXEL | points dropped | voxels per frame |")
    print("|---|---|---|")
    for cap in caps:
        mark = " (config)" if cap == own else ""
        print(
            f"| {cap}{mark} | {1 - kept[cap] / max(in_range, 1):.1%} | "
            f"{voxels[cap] / len(picks):,.0f} |"
        )


def main() -> None:
    args = parse_args()
    for cfg_file in args.cfgs:
        cap_table(cfg_file, args.data_path, args.caps, args.frames)


if __name__ == "__main__":
    run_tool(main)
