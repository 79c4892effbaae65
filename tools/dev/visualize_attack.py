"""Picture one attacked frame: bird's-eye view and range image, before and after the attack.

    python tools/dev/visualize_attack.py --data_cfg cfgs/dataset_configs/synthetic_waymo.yaml \
        --attack cfgs/attacks/rem_30.yaml --frame 40 --out output/viz/rem_30_040.png

``--frame`` indexes the split's frames (``dataset.infos``). The PNG has four panels:

* BEV before: points coloured by height; the points the attack removes (A-HFR) or occludes
  (behind the phantom) in orange.
* BEV after: the attacked points; injected phantom points in red; the phantom / target box drawn
  (dashed when it is a shadow target), and for removal the azimuth sector's edges.
* Range image before / after (beam x azimuth column, colour = range) over the target's azimuth
  window (the full 360° when the frame has no target); removed returns appear as holes, the
  phantom as a near (dark) blob.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

try:
    import matplotlib
except ModuleNotFoundError as err:  # the plots extra
    print(f"visualize_attack.py: error: {err}; install it with pip install -e .[plots]",
          file=sys.stderr)  # fmt: skip
    sys.exit(2)

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from pcdet_atlas.attacks.atlas_dataset import AtlasWaymoDataset  # noqa: E402
from pcdet_atlas.attacks.removal import RemovalAttack  # noqa: E402
from pcdet_atlas.config import (  # noqa: E402
    REPO_ROOT,
    cfg_from_list,
    cfg_from_yaml_file,
    resolve_cli_path,
)
from pcdet_atlas.ops.boxes import boxes_to_corners_3d  # noqa: E402
from pcdet_atlas.utils.cli import add_debug_flag, add_set_flag, run_tool

CLASS_NAMES = ["Vehicle", "Pedestrian", "Cyclist"]


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_debug_flag(parser)
    parser.add_argument(
        "--data_cfg",
        default="cfgs/dataset_configs/synthetic_waymo.yaml",
        help="dataset config (default: the synthetic one)",
    )
    parser.add_argument("--attack", required=True, help="attack yaml")
    parser.add_argument("--data_path", default=None, help="dataset root (default: DATA_PATH)")
    parser.add_argument("--frame", type=int, default=40, help="index into the split's frames")
    parser.add_argument("--out", default=None, help="PNG path (default output/viz/...)")
    parser.add_argument("--bev_range", type=float, nargs=4, default=[-25.0, 55.0, -30.0, 30.0],
                        metavar=("XMIN", "XMAX", "YMIN", "YMAX"),
                        help="bird's-eye extent in metres")  # fmt: skip
    add_set_flag(parser, help="KEY VALUE pairs overriding config keys (last on the command line)")
    return parser.parse_args(argv)


def range_image(xyz: np.ndarray, lidar) -> np.ndarray:
    """``(B, M)`` nearest range per ray (NaN where empty) of ``(N, 3)`` points."""
    bins, fov, rng = lidar.bin_index(torch.from_numpy(np.ascontiguousarray(xyz, np.float64)))
    bins, rng = bins[fov].numpy(), rng[fov].numpy()
    img = np.full(lidar.num_bins, np.inf)
    np.minimum.at(img, bins, rng)
    img[np.isinf(img)] = np.nan
    return img.reshape(lidar.num_beams, lidar.azimuth_bins)[::-1]  # top beam first


def draw_box(ax, box, color, dashed=False, label=None) -> None:
    corners = boxes_to_corners_3d(np.asarray(box, np.float64)[None, :7])[0, :4, :2]
    loop = np.vstack([corners, corners[:1]])
    ax.plot(loop[:, 0], loop[:, 1], color=color, lw=1.6, ls="--" if dashed else "-", label=label)
    front = (corners[0] + corners[1]) / 2
    ax.plot([box[0], front[0]], [box[1], front[1]], color=color, lw=1.2)


def render(dataset: AtlasWaymoDataset, index: int, out: Path, bev_range) -> Path:
    info = dataset.infos[index]
    seq_name = info["point_cloud"]["lidar_sequence"]
    sample_idx = int(info["point_cloud"]["sample_idx"])
    attack = dataset.attack
    before, result = dataset.simulate_frame(seq_name, sample_idx)
    meta = result.meta if result is not None else dataset.frame_attack_meta(seq_name, sample_idx)
    keep = np.ones(len(before), bool) if result is None or result.keep is None else result.keep
    added = np.zeros((0, 5), np.float32) if result is None else result.added
    after = np.concatenate([before[keep, :3], added[:, :3]])
    lidar = getattr(attack, "lidar", None)
    if lidar is None:
        from pcdet_atlas.ops.lidar_model import LidarModel

        lidar = LidarModel.waymo_top()

    fig = plt.figure(figsize=(16, 11), dpi=110)
    grid = fig.add_gridspec(3, 2, height_ratios=[3.2, 1, 1])
    x0, x1, y0, y1 = bev_range
    box = meta["target_box"]
    for col, title in enumerate(("before", "after")):
        ax = fig.add_subplot(grid[0, col])
        pts = before if col == 0 else before[keep]
        inside = (pts[:, 0] > x0) & (pts[:, 0] < x1) & (pts[:, 1] > y0) & (pts[:, 1] < y1)
        sc = ax.scatter(pts[inside, 0], pts[inside, 1], c=np.clip(pts[inside, 2], -1, 3),
                        s=0.15, cmap="viridis", rasterized=True)  # fmt: skip
        if col == 0 and (~keep).any():
            gone = before[~keep]
            ax.scatter(gone[:, 0], gone[:, 1], s=1.5, c="tab:orange",
                       label=f"removed/occluded ({len(gone)})")  # fmt: skip
        if col == 1 and len(added):
            ax.scatter(added[:, 0], added[:, 1], s=2.0, c="red",
                       label=f"phantom points ({len(added)} visible)")  # fmt: skip
        if box is not None:
            shadow = meta["target_is_shadow"]
            draw_box(ax, box, "magenta", shadow, "shadow target" if shadow else "target box")
        if col == 1 and isinstance(attack, RemovalAttack) and meta["fired"]:
            origin = lidar.origin.numpy()
            theta = math.atan2(box[1] - origin[1], box[0] - origin[0])
            for side in (-1, 1):
                a = theta + side * attack.azimuth_width / 2
                ax.plot([origin[0], origin[0] + 80 * math.cos(a)],
                        [origin[1], origin[1] + 80 * math.sin(a)], "r--", lw=1.0)  # fmt: skip
            ax.plot(
                [], [], "r--", label=f"sector alpha={math.degrees(attack.azimuth_width):.0f} deg"
            )
        ax.plot(0, 0, marker=(3, 0, -90), ms=12, color="black")  # ego, heading +x
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m, forward)")
        ax.set_ylabel("y (m, left)")
        ax.set_title(f"BEV {title}: {len(pts) if col == 0 else len(after)} points")
        handles, _ = ax.get_legend_handles_labels()
        if handles:
            ax.legend(loc="upper left", fontsize=8, markerscale=4)
        fig.colorbar(sc, ax=ax, fraction=0.03, label="z (m)")

    if box is not None:
        origin = lidar.origin.numpy()
        theta = math.atan2(box[1] - origin[1], box[0] - origin[0])
        center = int((theta + math.pi) / (2 * math.pi) * lidar.azimuth_bins)
        half = int(lidar.azimuth_bins * 40 / 360)
        cols = np.arange(center - half, center + half) % lidar.azimuth_bins
        extent_deg = (math.degrees(theta) - 40, math.degrees(theta) + 40)
    else:
        cols = np.arange(lidar.azimuth_bins)
        extent_deg = (-180.0, 180.0)
    for row, (title, xyz) in enumerate((("before", before[:, :3]), ("after", after))):
        ax = fig.add_subplot(grid[1 + row, :])
        img = range_image(xyz, lidar)[:, cols][:, ::-1]  # azimuth increasing to the left
        im = ax.imshow(img, aspect="auto", cmap="turbo_r", vmin=0, vmax=60, interpolation="nearest",
                       extent=(extent_deg[1], extent_deg[0], 0, lidar.num_beams))  # fmt: skip
        ax.set_ylabel("beam")
        ax.set_title(f"range image {title} (azimuth deg, beam; colour = range m)", fontsize=10)
        fig.colorbar(im, ax=ax, fraction=0.02, label="range (m)")
    ax.set_xlabel("azimuth (deg, relative to the sensor)")
    status = (
        f"spoofed, run {meta['run_id']} position {meta['run_position']}"
        if meta["spoofed"]
        else f"clean (lifecycle k={meta['lifecycle_k']})"
    )
    fig.suptitle(
        f"{attack.variant}  |  {info['frame_id']}  |  {status}  |  spoof pts "
        f"{meta['num_spoof_points']}, visible {meta['num_visible']}, removed {meta['num_removed']}"
        f", tracked {meta['tracked']}, fired {meta['fired']}",
        fontsize=11,
    )
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


def main(argv=None) -> Path:
    args = parse_args(argv)
    attack_cfg = cfg_from_yaml_file(args.attack)
    if args.set_cfgs:
        cfg_from_list(args.set_cfgs, attack_cfg)
    data_cfg = cfg_from_yaml_file(args.data_cfg)
    if args.data_path is not None:
        cfg_from_list(["DATA_PATH", str(resolve_cli_path(args.data_path))], data_cfg)
    dataset = AtlasWaymoDataset(data_cfg, CLASS_NAMES, attack_cfg)
    if not 0 <= args.frame < len(dataset):
        raise SystemExit(f"--frame {args.frame} outside the split's {len(dataset)} frames")
    out = Path(args.out) if args.out else REPO_ROOT / "output" / "viz" / (
        f"{dataset.attack.variant}_{args.frame:04d}.png"
    )  # fmt: skip
    render(dataset, args.frame, out, args.bev_range)
    print(f"wrote {out}")
    return out


if __name__ == "__main__":
    run_tool(main)
