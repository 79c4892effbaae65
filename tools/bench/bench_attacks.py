"""Benchmarks of the attack engine, measured side by side in one run.

    python tools/bench/bench_attacks.py                       # every part, CPU, 1 torch thread
    python tools/bench/bench_attacks.py --part raycast --device cuda --repeats 50

Parts:
    raycast: ``raycast_merge`` on a seeded 180k-point Waymo-like scan with a 1,000-point phantom
        at ~17 m, against a plain numpy range-image z-buffer on the same input (every point binned
        with the same LidarModel math, ``np.minimum.at`` into a 64 x M grid, then the same keep
        rules). Both masks must be identical. Then the fidelity knobs: azimuth resolution
        (1325 / 2651 / 5302 columns) and dual returns (p_dual 0 vs 0.01), with what they change.
    getitem: ``AtlasWaymoDataset[i]`` against ``WaymoDataset[i]`` on the same frames of a
        Waymo-format split (``--data_path``, a synthetic one is generated if absent), single-frame
        (target <= 1.25x on spoofed frames) and 4-frame input (<= 1.35x), for an injection and a
        removal variant; clean frames (ratio ~1) alongside.
    visible: not a timing: how many of a phantom's points the raycast keeps (one echo per ray,
        docs/attacks.md), per injection variant over the spoofed frames of the val split of
        ``--data_path``: the budget (trace points), the visible points, their ratio, and the
        phantom's range.

Times are the median of ``--repeats`` calls after one warm-up call (getitem: after a warm-up
pass of both datasets over every timed frame; clean and attacked alternate call by call;
``--rounds K`` repeats each row K times and prints the median and the range of its K ratios,
since on a shared 2-core VM one round's ratio moves by +-0.04).
"""

from __future__ import annotations

import argparse
import functools
import itertools
import math
import os
import statistics
import time

import numpy as np
import torch

from pcdet_atlas.attacks.counters import COUNTERS, AttackCounters
from pcdet_atlas.attacks.raycast import (
    _elevation_band_rows,
    azimuth_sector_candidates,
    raycast_merge,
)
from pcdet_atlas.config import REPO_ROOT
from pcdet_atlas.ops.lidar_model import LidarModel
from pcdet_atlas.utils.cli import add_debug_flag, run_tool


def time_interleaved(fns: dict, repeats: int, sync=None, block: int = 5) -> dict[str, float]:
    """Median wall time (ms) per call of each callable.

    The callables take turns in blocks of ``block`` consecutive calls, so that a shared, loaded
    machine slows all of them alike, while each runs with its own data in cache as it would in
    a loop. One warm-up block each.
    """
    times: dict[str, list[float]] = {name: [] for name in fns}
    rounds = max(1, math.ceil(repeats / block))
    for rnd in range(rounds + 1):
        for name, fn in fns.items():
            for _ in range(block):
                t0 = time.perf_counter()
                fn()
                if sync:
                    sync()
                if rnd:
                    times[name].append(time.perf_counter() - t0)
    return {name: 1e3 * statistics.median(t) for name, t in times.items()}


# ---------------------------------------------------------------------------------- raycast part
def waymo_like_scene(lidar: LidarModel, num_points: int = 180_000, seed: int = 0) -> np.ndarray:
    """A seeded ``(num_points, 3)`` float32 scan: ground for the downward beams, walls and cars
    at 5-75 m elsewhere, ~8% sky, a few second returns, range noise, azimuth jitter."""
    g = np.random.default_rng(seed)
    beams = np.repeat(np.arange(lidar.num_beams), lidar.azimuth_bins)
    cols = np.tile(np.arange(lidar.azimuth_bins), lidar.num_beams)
    el = lidar.inclinations.numpy()[beams]
    height = float(lidar.origin[2])
    ground = np.where(el < -1e-3, height / np.sin(np.maximum(-el, 1e-3)), np.inf)
    wall = g.uniform(5.0, 75.0, beams.size)
    rng = np.minimum(ground, wall)
    keep = (g.random(beams.size) > 0.08) & (rng < lidar.max_range)
    beams, cols, el, rng = beams[keep], cols[keep], el[keep], rng[keep]
    # second returns on some rays fill up to num_points
    extra = g.choice(beams.size, max(0, num_points - beams.size), replace=True)
    beams = np.concatenate([beams, beams[extra]])
    cols = np.concatenate([cols, cols[extra]])
    el = np.concatenate([el, el[extra]])
    rng = np.concatenate([rng, rng[extra] + g.uniform(0.5, 20.0, extra.size)])
    sel = g.permutation(beams.size)[:num_points]
    beams, cols, el, rng = beams[sel], cols[sel], el[sel], rng[sel]
    width = 2 * np.pi / lidar.azimuth_bins
    az = -np.pi + (cols + g.uniform(0.02, 0.98, cols.size)) * width
    el = el + g.normal(0.0, 2e-4, el.size)
    rng = rng + g.normal(0.0, 0.02, rng.size)
    o = lidar.origin.numpy()
    xyz = np.stack(
        [
            o[0] + rng * np.cos(el) * np.cos(az),
            o[1] + rng * np.cos(el) * np.sin(az),
            o[2] + rng * np.sin(el),
        ],
        1,
    )
    return xyz.astype(np.float32)


def phantom_points(num_points: int = 1000, seed: int = 1) -> np.ndarray:
    """``(num_points, 3)`` float32 points on the surface of a 4.5 x 1.9 x 1.6 m car box centred
    at (17.5, 6, 0.8) m (about 17 m from the sensor, yaw 30°)."""
    g = np.random.default_rng(seed)
    dims = np.array([4.5, 1.9, 1.6])
    face = g.integers(0, 6, num_points)
    local = g.uniform(-0.5, 0.5, (num_points, 3))
    axis = face // 2
    local[np.arange(num_points), axis] = np.where(face % 2 == 0, -0.5, 0.5)
    local *= dims
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    xyz = local @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) + [17.5, 6.0, 0.8]
    return xyz.astype(np.float32)


def numpy_zbuffer(scene, spoof, lidar: LidarModel, p_dual: float = 0.0, generator=None):
    """The raycast rules as a dense range image: bin every point, ``np.minimum.at`` z-buffers."""
    M, B = lidar.azimuth_bins, lidar.num_beams
    origin = lidar.origin.numpy()
    mids = ((lidar.inclinations[1:] + lidar.inclinations[:-1]) / 2).numpy()

    def bin_points(xyz):
        rel = xyz.astype(np.float64) - origin
        horiz = np.sqrt(rel[:, 0] ** 2 + rel[:, 1] ** 2)
        az = np.arctan2(rel[:, 1], rel[:, 0])
        az[az == -np.pi] = np.pi
        el = np.arctan2(rel[:, 2], horiz)
        r = np.sqrt(horiz**2 + rel[:, 2] ** 2)
        col = np.clip(np.floor((az + np.pi) / (2 * np.pi / M)), 0, M - 1).astype(np.int64)
        beam = np.searchsorted(mids, el, side="left")
        fov = (el >= lidar.fov_min) & (el <= lidar.fov_max)
        return beam * M + col, fov, r

    s_bin, s_fov, s_r = bin_points(scene)
    p_bin, p_fov, p_r = bin_points(spoof)
    n, m = len(scene), len(spoof)
    s_ok = s_fov & (s_r > 0) & np.isfinite(s_r)
    p_ok = p_fov & (p_r > 0) & (p_r <= lidar.max_range)
    echo_r = np.full(B * M, np.inf)
    np.minimum.at(echo_r, p_bin[p_ok], p_r[p_ok])
    win = p_ok & (p_r == echo_r[p_bin])
    echo_idx = np.full(B * M, m)
    np.minimum.at(echo_idx, p_bin[win], np.flatnonzero(win))
    far_r = np.full(B * M, -np.inf)
    np.maximum.at(far_r, s_bin[s_ok], s_r[s_ok])
    near_r = np.full(B * M, np.inf)
    np.minimum.at(near_r, s_bin[s_ok], s_r[s_ok])
    has_spoof = echo_idx < m
    has_scene = far_r > -np.inf
    ray_keeps = has_spoof & (~has_scene | (echo_r < far_r))
    keep_spoof = np.zeros(m, dtype=bool)
    keep_spoof[echo_idx[ray_keeps]] = True
    keep_scene = ~(s_ok & ray_keeps[s_bin] & (s_r > echo_r[s_bin]))
    if p_dual > 0:
        primary = np.flatnonzero(ray_keeps & has_scene & (echo_r < near_r))
        if primary.size:
            u = torch.rand(primary.size, generator=generator, dtype=torch.float64).numpy()
            near_idx = np.full(B * M, n)
            nearest = s_ok & (s_r == near_r[s_bin])
            np.minimum.at(near_idx, s_bin[nearest], np.flatnonzero(nearest))
            keep_scene[near_idx[primary[u < p_dual]]] = True
    return keep_scene, keep_spoof


def bench_raycast(args) -> None:
    device = torch.device(args.device)
    sync = torch.cuda.synchronize if device.type == "cuda" else None
    lidar = LidarModel.waymo_top()
    scene_np = waymo_like_scene(lidar, args.num_points)
    spoof_np = phantom_points(args.spoof_points)
    scene = torch.from_numpy(scene_np).to(device)
    spoof = torch.from_numpy(spoof_np).to(device)
    print(
        f"raycast: scene {len(scene_np)} pts, phantom {len(spoof_np)} pts at "
        f"{np.linalg.norm(spoof_np.mean(0)[:2] - lidar.origin.numpy()[:2]):.1f} m, "
        f"device {device}, torch threads {torch.get_num_threads()}, repeats {args.repeats}, "
        f"load average {os.getloadavg()[0]:.1f}"
    )

    # correctness on the benchmark input: identical masks, p_dual 0 and 0.01
    for p in (0.0, 0.01):
        gen_a = torch.Generator().manual_seed(7)
        gen_b = torch.Generator().manual_seed(7)
        ours = raycast_merge(scene, spoof, lidar, p_dual=p, generator=gen_a)
        ref = numpy_zbuffer(scene_np, spoof_np, lidar, p_dual=p, generator=gen_b)
        same = np.array_equal(ours[0].cpu().numpy(), ref[0]) and np.array_equal(
            ours[1].cpu().numpy(), ref[1]
        )
        if not same:
            raise SystemExit(f"MISMATCH between raycast_merge and the numpy z-buffer (p={p})")
    counters = AttackCounters()
    keep_scene, keep_spoof = raycast_merge(scene, spoof, lidar, p_dual=0.0, counters=counters)
    print(
        f"  identical masks (p_dual 0 and 0.01): yes; kept {int(keep_spoof.sum())} phantom pts, "
        f"removed {int((~keep_scene).sum())} scene pts; examined {counters.points_examined} pts, "
        f"{counters.bins_touched} rays"
    )
    # what the elevation-band pre-filter leaves to bin exactly (the raycaster's own steps)
    spoof_bin, spoof_fov, spoof_rng = lidar.bin_index(spoof)
    rays = torch.unique(spoof_bin[spoof_fov & (spoof_rng > 0) & (spoof_rng <= lidar.max_range)])
    sector = azimuth_sector_candidates(scene, torch.unique(rays % lidar.azimuth_bins), lidar)
    beams = (int(rays[0]) // lidar.azimuth_bins, int(rays[-1]) // lidar.azimuth_bins)
    band = _elevation_band_rows(scene, sector, lidar, *beams)
    print(
        f"  elevation band (beams {beams[0]}-{beams[1]}): {band.numel()} of {sector.numel()} "
        "sector candidates binned exactly"
    )

    fns = {
        "ours": lambda: raycast_merge(scene, spoof, lidar, p_dual=0.0),
        "numpy": lambda: numpy_zbuffer(scene_np, spoof_np, lidar),
    }
    t = time_interleaved(fns, args.repeats, sync)
    t_ours, t_np = t["ours"], t["numpy"]
    print(f"  raycast_merge          {t_ours:8.2f} ms   (sector-restricted, torch on {device})")
    print(f"  numpy range image      {t_np:8.2f} ms   (every point binned, dense z-buffer)")
    print(
        f"  speed-up               {t_np / t_ours:8.1f} x   (target >= 15 x on CPU); "
        f"load average {os.getloadavg()[0]:.1f}"
    )

    print("  fidelity knobs (raycast_merge):")
    print(
        f"    {'setting':<32}{'time ms':>9}{'rays':>7}{'examined':>10}{'draws':>7}"
        f"{'kept':>6}{'removed':>9}"
    )
    knobs, stats = {}, {}
    for bins in (1325, 2651, 5302):
        model = LidarModel.waymo_top(azimuth_bins=bins)
        for p in (0.0, 0.01):
            name = f"azimuth_bins={bins}, p_dual={p}"
            counters = AttackCounters()
            ks, kp = raycast_merge(
                scene, spoof, model, p, torch.Generator().manual_seed(0), counters
            )
            stats[name] = (counters, int(kp.sum()), int((~ks).sum()))
            knobs[name] = lambda model=model, p=p: raycast_merge(
                scene, spoof, model, p, torch.Generator().manual_seed(0)
            )
    times = time_interleaved(knobs, args.repeats, sync)
    for name, (counters, kept, removed) in stats.items():
        print(
            f"    {name:<32}{times[name]:>9.2f}{counters.bins_touched:>7}"
            f"{counters.points_examined:>10}{counters.dual_draws:>7}{kept:>6}{removed:>9}"
        )


# ------------------------------------------------------------------------------ getitem part
GETITEM_VARIANTS = ("inj_global_hard", "inj_rel_medium", "rem_30")


def _getitem_data(args):
    """The dataset root to time (``--data_path``; generated into a temp dir if absent) and an
    injection trace library for it (the root's own when it matches the YAML, else built)."""
    import tempfile
    from pathlib import Path

    from pcdet_atlas.attacks.trace_library import TraceFilter, TraceLibrary, build_trace_library
    from pcdet_atlas.config import cfg_from_yaml_file, resolve_cli_path

    root = resolve_cli_path(args.data_path)
    if not (root / "ImageSets" / "val.txt").is_file():
        from pcdet_atlas.datasets.synthetic import create_synthetic_waymo

        root = Path(tempfile.mkdtemp(prefix="bench_getitem_"))
        print(f"getitem: no dataset at {args.data_path}; generating a synthetic one in {root}")
        create_synthetic_waymo(
            root, num_sequences={"train": 2, "val": 1},
            frames_per_sequence={"train": 10, "val": 70}, seed=0,
        )  # fmt: skip
    inj = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "attacks" / "inj_global_hard.yaml")
    filters = TraceFilter.from_config(inj.TRACE_LIBRARY)
    lib_path = root / filters.path
    origin = LidarModel.from_config(inj.get("LIDAR")).origin_xyz
    if lib_path.is_file() and not TraceLibrary.load(lib_path).build_mismatch(filters, origin):
        return root, lib_path
    lib_path = Path(tempfile.mkdtemp(prefix="bench_lib_")) / "lib.npz"
    build_trace_library(root, filters, split=filters.split, sensor_origin=origin).save(lib_path)
    return root, lib_path


def warm_up_process(dataset, indices: list[int], seconds: float) -> None:
    """Read ``dataset[i]`` over ``indices`` for ``seconds``.

    A fresh process reads frames about twice as slowly for its first few hundred samples:
    glibc serves the multi-MB point arrays with fresh ``mmap`` pages (page faults) until its
    adaptive mmap / trim thresholds have grown past their size (with ``MALLOC_MMAP_THRESHOLD_``
    fixed the first calls are as fast as the later ones). Whichever variant is timed first would
    pay it, so the process is brought to its steady state before any timing.
    """
    end = time.perf_counter() + seconds
    calls = 0
    while time.perf_counter() < end or calls < len(indices):
        dataset[indices[calls % len(indices)]]
        calls += 1


def bench_getitem(args) -> None:
    """Attacked vs clean ``__getitem__`` on the same spoofed frames, 1-frame and 4-frame input."""

    from pcdet_atlas.attacks.atlas_dataset import AtlasWaymoDataset
    from pcdet_atlas.attacks.schedule import is_spoofed
    from pcdet_atlas.config import cfg_from_yaml_file
    from pcdet_atlas.datasets import WaymoDataset

    root, lib_path = _getitem_data(args)
    classes = ["Vehicle", "Pedestrian", "Cyclist"]
    print(f"getitem: data {root}, torch threads {torch.get_num_threads()}, repeats {args.repeats}")
    print(
        f"getitem: {args.rounds} round(s) of {args.repeats} alternating calls per row; medians "
        "over rounds, ratio range over rounds"
    )
    print(
        "getitem: sims = attack simulations per sample, read in order (the attacked-frame cache "
        "serves history frames; 'no cache' = frame_cache_size 0)"
    )
    print(f"  {'input':<8}{'variant':<27}{'frames':<9}{'clean ms':>10}{'attacked ms':>13}"
          f"{'extra ms':>10}{'ratio':>8}{'range':>12}{'sims':>6}{'target':>9}")  # fmt: skip
    inputs = {
        "1": ("synthetic_waymo.yaml", 1.25),
        "4": ("synthetic_waymo_multiframe.yaml", 1.35),
    }
    unknown = set(args.inputs.split(",")) - set(inputs)
    if unknown:
        raise SystemExit(f"--inputs: expected 1, 4 or 1,4, got {args.inputs!r}")
    for key, (name, target) in inputs.items():
        if key not in args.inputs.split(","):
            continue
        data_cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "dataset_configs" / name)
        data_cfg.DATA_PATH = str(root)
        clean = WaymoDataset(data_cfg, classes, training=False)
        mode = "4-frame" if clean.sequence_cfg is not None else "1-frame"
        frames = {
            "spoofed": [i for i, info in enumerate(clean.infos)
                        if is_spoofed(info["point_cloud"]["sample_idx"])],
            "clean": [i for i, info in enumerate(clean.infos)
                      if not is_spoofed(info["point_cloud"]["sample_idx"])],
        }  # fmt: skip
        warm_up_process(clean, frames["spoofed"], args.warmup_s)
        caches = (None, 0) if clean.sequence_cfg is not None else (None,)
        for variant, cache in itertools.product(GETITEM_VARIANTS, caches):
            attack_cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "attacks" / f"{variant}.yaml")
            if "TRACE_LIBRARY" in attack_cfg:
                attack_cfg.TRACE_LIBRARY.PATH = str(lib_path)
            make = functools.partial(
                AtlasWaymoDataset, data_cfg, classes, attack_cfg, root_path=root,
                frame_cache_size=cache,
            )  # fmt: skip
            attacked = make()
            label = variant if cache is None else f"{variant} (no cache)"
            for kind in ("spoofed", "clean"):
                with COUNTERS.measure() as work:  # a fresh dataset, its frames read in order
                    fresh = make()
                    for i in frames[kind]:
                        fresh[i]
                sims = work["frames_simulated"] / len(frames[kind])
                # warm both datasets on every timed frame first (page cache, lazily loaded
                # trace library, prepared runs, allocator), so that no variant's first row
                # pays for it; then alternate call by call on the same frame
                for i in frames[kind]:
                    clean[i], attacked[i]
                idx_a, idx_c = itertools.cycle(frames[kind]), itertools.cycle(frames[kind])
                rounds = [
                    time_interleaved(
                        {
                            "clean": lambda ds=clean, it=idx_c: ds[next(it)],
                            "attacked": lambda ds=attacked, it=idx_a: ds[next(it)],
                        },
                        args.repeats,
                        block=1,  # alternate call by call: load spikes hit both alike
                    )
                    for _ in range(args.rounds)
                ]
                ratios = sorted(t["attacked"] / t["clean"] for t in rounds)
                c_ms = statistics.median(t["clean"] for t in rounds)
                a_ms = statistics.median(t["attacked"] for t in rounds)
                spread = f"{ratios[0]:.2f}-{ratios[-1]:.2f}" if len(ratios) > 1 else ""
                goal = f"<= {target}" if kind == "spoofed" else "~ 1"
                print(f"  {mode:<8}{label:<27}{kind:<9}{c_ms:>10.2f}{a_ms:>13.2f}"
                      f"{a_ms - c_ms:>10.2f}{statistics.median(ratios):>8.2f}{spread:>12}"
                      f"{sims:>6.2f}{goal:>9}")  # fmt: skip


def visible_counts(args) -> None:
    """Budget vs visible phantom points per injection variant (the one-echo-per-ray cap)."""
    from pcdet_atlas.attacks.atlas_dataset import AtlasWaymoDataset
    from pcdet_atlas.attacks.schedule import is_spoofed
    from pcdet_atlas.config import cfg_from_yaml_file

    root, lib_path = _getitem_data(args)
    data_cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "dataset_configs" / "synthetic_waymo.yaml")
    data_cfg.DATA_PATH = str(root)
    classes = ["Vehicle", "Pedestrian", "Cyclist"]
    print(f"visible: data {root}, spoofed frames of the val split")
    print("| variant | frames | budget (median) | visible (median) | visible / budget (median, "
          "min-max) | range m (median, min-max) | frames with 0 visible |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    for variant in INJECTION_VARIANTS:
        attack_cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "attacks" / f"{variant}.yaml")
        attack_cfg.TRACE_LIBRARY.PATH = str(lib_path)
        ds = AtlasWaymoDataset(data_cfg, classes, attack_cfg, root_path=root)
        rows = []
        for i, info in enumerate(ds.infos):
            if is_spoofed(info["point_cloud"]["sample_idx"]):
                meta = ds[i]["attack"]
                box = meta["target_box"]
                rng = math.hypot(box[0], box[1]) if box is not None else float("nan")
                rows.append((meta["num_spoof_points"], meta["num_visible"], rng))
        budget, vis, rng = (np.array(c, dtype=np.float64) for c in zip(*rows))
        ratio = vis / budget
        print(
            f"| {variant} | {len(rows)} | {np.median(budget):.0f} | {np.median(vis):.0f} | "
            f"{np.median(ratio):.2f} ({ratio.min():.2f}-{ratio.max():.2f}) | "
            f"{np.nanmedian(rng):.1f} ({np.nanmin(rng):.1f}-{np.nanmax(rng):.1f}) | "
            f"{int((vis == 0).sum())} |"
        )


INJECTION_VARIANTS = [f"inj_{m}_{d}" for m in ("rel", "global") for d in ("easy", "medium", "hard")]
PARTS = {"raycast": bench_raycast, "getitem": bench_getitem, "visible": visible_counts}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_debug_flag(parser)
    parser.add_argument(
        "--part", choices=["all", *PARTS], default="all", help="which benchmark (default: all)"
    )  # all: the timings
    parser.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument(
        "--repeats", type=int, default=30, help="timed repeats per case (default: 30)"
    )
    parser.add_argument(
        "--num_points",
        type=int,
        default=180_000,
        help="points of the synthetic scan (default: 180,000)",
    )
    parser.add_argument(
        "--spoof_points", type=int, default=1000, help="phantom points injected (default: 1,000)"
    )
    parser.add_argument(
        "--data_path", default=str(REPO_ROOT / "data" / "synthetic_waymo"), help="getitem part"
    )
    parser.add_argument(
        "--warmup_s", type=float, default=8.0, help="getitem part: process warm-up per input"
    )
    parser.add_argument(
        "--inputs", default="1,4", help="getitem part: frames per input to time (1, 4 or 1,4)"
    )
    parser.add_argument(
        "--rounds", type=int, default=1,
        help="getitem part: timed rounds per row (median and range of their ratios)",
    )  # fmt: skip
    args = parser.parse_args()
    if args.rounds < 1:
        parser.error(f"--rounds: expected a positive number of rounds, got {args.rounds}")
    torch.set_num_threads(args.threads)
    for name, fn in PARTS.items():
        if args.part == name or (args.part == "all" and name != "visible"):
            fn(args)


if __name__ == "__main__":
    run_tool(main)
