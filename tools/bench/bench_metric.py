"""Benchmark of the Waymo metric: pcdet_atlas vs the official op, exact Hungarian vs greedy.

Prints, for one seeded synthetic evaluation set (default 200 frames x ~100 GT x ~300 predictions
per frame, all three classes):
- the time of ``waymo_evaluate`` (exact Hungarian, the official semantics);
- where the official venv exists (``tools/dev/official_waymo_metric/setup_venv.sh``), the official
  ``py_metrics_ops.detection_metrics`` time on the same input, the ratio, and the largest AP/APH
  difference between the two (a large-scale cross-check of the fixtures' result);
- the price of exactness: greedy score-first matching (COCO style) vs Hungarian, time and AP.

Both sides run with ``--threads`` threads (torch intra-op for pcdet_atlas, TensorFlow intra- and
inter-op for the official op), and the machine's load average is printed beside every figure: the
ratio between the two moves with the load (the official op's threads lose more).

``--scale`` instead measures ``waymo_evaluate`` at Waymo's size: Waymo-like frames (Poisson
~27 GT and ~25 predictions per frame, the same class mix, difficulties and noise) at each
``--scale_frames`` count (default 4,000 and 40,000: the val split is 39,987 frames, ~1.1 M
GT), each in a fresh process (``--threads`` threads, BLAS pools too), printing the metric's
time, the process's peak resident memory (``ru_maxrss``, inputs included) and what the inputs
alone held, and the growth from the smallest to the largest count; ``--profile`` adds the
largest count's cProfile top 15.

Usage: ``python tools/bench/bench_metric.py [--frames 200] [--gt 100] [--det 300] [--repeats 3]
[--threads 1] [--venv .cache/waymo_official_venv]``, or
``python tools/bench/bench_metric.py --scale [--scale_frames 4000 40000] [--profile]``
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from pcdet_atlas.evaluation.waymo_metric import waymo_evaluate
from pcdet_atlas.utils.cli import add_debug_flag, run_tool
from pcdet_atlas.utils.seeding import numpy_generator

REPO = Path(__file__).resolve().parents[2]
CLASSES = ["Vehicle", "Pedestrian", "Cyclist"]
WAYMO_CODES = {"Vehicle": 1, "Pedestrian": 2, "Cyclist": 4}
SIZES = {"Vehicle": (4.6, 2.0, 1.7), "Pedestrian": (0.85, 0.8, 1.75), "Cyclist": (1.8, 0.7, 1.7)}
MIX = {"Vehicle": 0.6, "Pedestrian": 0.3, "Cyclist": 0.1}


def make_frame(rng: np.random.Generator, num_gt: int, num_det: int) -> tuple[dict, dict]:
    """One frame: GT spread over 150 m x 150 m, noisy detections (~40% of the budget), duplicates
    and near-miss clutter around objects (~25%), scattered false positives (the rest)."""
    names = rng.choice(CLASSES, size=num_gt, p=[MIX[c] for c in CLASSES])
    size = np.array([SIZES[n] for n in names]) * rng.uniform(0.85, 1.15, (num_gt, 3))
    xy = rng.uniform(-75, 75, (num_gt, 2))
    gt_boxes = np.concatenate(
        [xy, size[:, 2:3] / 2, size, rng.uniform(-np.pi, np.pi, (num_gt, 1))], axis=1
    ).astype(np.float32)
    points = np.where(rng.uniform(size=num_gt) < 0.1, 0, rng.integers(1, 3000, num_gt))
    difficulty = rng.choice([0, 0, 0, 1, 2], size=num_gt)

    def noisy(idx: np.ndarray, pos: float) -> np.ndarray:
        b = gt_boxes[idx].astype(np.float64)
        b[:, :2] += rng.normal(0, pos, (len(idx), 2))
        b[:, 2] += rng.normal(0, pos / 2, len(idx))
        b[:, 3:6] *= np.exp(rng.normal(0, 0.06, (len(idx), 3)))
        b[:, 6] += rng.normal(0, 0.1, len(idx)) + np.pi * (rng.uniform(size=len(idx)) < 0.1)
        return b

    n_true = int(0.4 * num_det)
    n_clutter = int(0.25 * num_det)
    hit = rng.choice(num_gt, size=n_true, replace=n_true > num_gt)
    near = rng.choice(num_gt, size=n_clutter)
    det_boxes = [noisy(hit, 0.15), noisy(near, 0.8)]
    det_names = [names[hit], names[near]]
    det_scores = [rng.beta(5, 2, n_true), rng.beta(2, 4, n_clutter)]
    n_fp = num_det - n_true - n_clutter
    fp_names = rng.choice(CLASSES, size=n_fp, p=[MIX[c] for c in CLASSES])
    fp_size = np.array([SIZES[n] for n in fp_names])
    det_boxes.append(
        np.concatenate(
            [
                rng.uniform(-75, 75, (n_fp, 2)),
                fp_size[:, 2:3] / 2,
                fp_size,
                rng.uniform(-np.pi, np.pi, (n_fp, 1)),
            ],
            axis=1,
        )  # fmt: skip
    )
    det_names.append(fp_names)
    det_scores.append(rng.beta(2, 5, n_fp))
    gt = {
        "name": names,
        "gt_boxes_lidar": gt_boxes,
        "num_points_in_gt": points,
        "difficulty": difficulty,
    }
    det = {
        "name": np.concatenate(det_names),
        "boxes_lidar": np.concatenate(det_boxes).astype(np.float32),
        "score": np.concatenate(det_scores).astype(np.float32),
    }
    return gt, det


def to_official_scene(gts: list[dict], dets: list[dict]) -> dict[str, np.ndarray]:
    """Flat arrays in the input format of ``tools/dev/official_waymo_metric/official_eval.py``."""

    def codes(names):
        return np.array([WAYMO_CODES[n] for n in names], dtype=np.int64)

    return {
        "gt_frame": np.concatenate([np.full(len(g["name"]), i) for i, g in enumerate(gts)]),
        "gt_name": np.concatenate([codes(g["name"]) for g in gts]),
        "gt_boxes": np.concatenate([g["gt_boxes_lidar"] for g in gts]),
        "gt_num_points": np.concatenate([g["num_points_in_gt"] for g in gts]),
        "gt_difficulty": np.concatenate([g["difficulty"] for g in gts]),
        "det_frame": np.concatenate([np.full(len(d["name"]), i) for i, d in enumerate(dets)]),
        "det_name": np.concatenate([codes(d["name"]) for d in dets]),
        "det_boxes": np.concatenate([d["boxes_lidar"] for d in dets]),
        "det_score": np.concatenate([d["score"] for d in dets]),
    }


def timed(fn, repeats: int):
    best, out = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best, out


def load() -> str:
    """The machine's 1-minute load average, for the output."""
    return f"{os.getloadavg()[0]:.1f}"


def waymo_like_frames(frames: int, seed: int) -> tuple[list[dict], list[dict]]:
    """``frames`` seeded Waymo-like frames: Poisson(27) GT and Poisson(25) predictions each."""
    gts, dets = [], []
    for f in range(frames):
        rng = numpy_generator(seed, "bench_metric_scale", f)
        gt, det = make_frame(rng, int(rng.poisson(27)), int(rng.poisson(25)))
        gts.append(gt)
        dets.append(det)
    return gts, dets


def scale_child(frames: int, seed: int, profile: bool) -> dict:
    """One ``--scale`` size in this process: inputs, then the metric, timed and measured."""
    gts, dets = waymo_like_frames(frames, seed)
    inputs_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    profiler = None
    if profile:
        import cProfile

        profiler = cProfile.Profile()
        profiler.enable()
    start = time.perf_counter()
    result = waymo_evaluate(gts, dets, CLASSES)
    seconds = time.perf_counter() - start
    if profiler is not None:
        import io
        import pstats

        profiler.disable()
        text = io.StringIO()
        pstats.Stats(profiler, stream=text).sort_stats("tottime").print_stats(15)
        print(text.getvalue(), file=sys.stderr)
    return {
        "frames": frames,
        "gt": sum(len(g["name"]) for g in gts),
        "det": sum(len(d["name"]) for d in dets),
        "seconds": seconds,
        "inputs_mib": inputs_mib,
        "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "l2_map": result["L2/mAP"],
    }


def scale_table(args) -> None:
    """Run every ``--scale_frames`` size in a fresh process and print the table."""
    threads = str(args.threads)
    env = dict(os.environ, OMP_NUM_THREADS=threads, OPENBLAS_NUM_THREADS=threads,
               MKL_NUM_THREADS=threads)  # fmt: skip
    print(
        f"waymo_evaluate at scale: {args.threads} thread(s), torch {torch.__version__}, "
        f"numpy {np.__version__}; load average {load()} at the start"
    )
    print("| frames | GT | predictions | metric s | peak RSS MiB | of it inputs MiB | load |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    for i, frames in enumerate(sorted(args.scale_frames)):
        last = i == len(args.scale_frames) - 1
        cmd = [sys.executable, __file__, "--scale_child", str(frames), "--seed", str(args.seed),
               "--threads", threads] + (["--profile"] if args.profile and last else [])  # fmt: skip
        out = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if out.returncode:
            raise SystemExit(f"--scale {frames} frames failed:\n{out.stderr[-3000:]}")
        row = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(
            f"| {frames:,} | {row['gt']:,} | {row['det']:,} | {row['seconds']:.1f} "
            f"| {row['peak_mib']:,.0f} | {row['inputs_mib']:,.0f} | {load()} |"
        )
        if out.stderr.strip():
            print(out.stderr)
    if len(rows) > 1:
        small, large = rows[0], rows[-1]
        size = large["frames"] / small["frames"]
        growth = large["seconds"] / small["seconds"]
        print(
            f"\ngrowth {small['frames']:,} -> {large['frames']:,} frames ({size:.0f}x): time "
            f"{growth:.2f}x ({growth / size:.2f}x linear), peak RSS "
            f"{large['peak_mib'] / small['peak_mib']:.2f}x; L2 mAP {small['l2_map']:.4f} / "
            f"{large['l2_map']:.4f}"
        )


def run_official(venv: Path, scene: dict, repeats: int, threads: int) -> tuple[float, dict] | None:
    python = venv / "bin" / "python"
    if not python.exists():
        return None
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "scene.npz", Path(tmp) / "official.npz"
        np.savez(src, **scene)
        script = REPO / "tools" / "dev" / "official_waymo_metric" / "official_eval.py"
        cmd = [str(python), str(script), str(src), str(dst), "--repeat", str(repeats),
               "--threads", str(threads)]  # fmt: skip
        subprocess.run(cmd, check=True, capture_output=True)
        with np.load(dst) as res:
            out = {k: res[k] for k in res.files}
    return float(out["seconds"]), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_debug_flag(parser)
    parser.add_argument(
        "--frames", type=int, default=200, help="frames of the synthetic input (default: 200)"
    )
    parser.add_argument(
        "--gt", type=int, default=100, help="ground-truth boxes per frame (default: 100)"
    )
    parser.add_argument(
        "--det", type=int, default=300, help="predicted boxes per frame (default: 300)"
    )
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (default: 3)")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--seed", type=int, default=0, help="seed of the synthetic input")
    parser.add_argument(
        "--venv",
        type=Path,
        default=REPO / ".cache" / "waymo_official_venv",
        help="venv holding the official metric op (tools/dev/official_waymo_metric/setup_venv.sh)",
    )
    parser.add_argument("--scale", action="store_true", help="time the metric at Waymo's size")
    parser.add_argument(
        "--scale_frames", type=int, nargs="+", default=[4000, 40000], help="--scale sizes"
    )
    parser.add_argument("--profile", action="store_true", help="--scale: profile the largest")
    parser.add_argument("--scale_child", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.scale_child is not None:
        print(json.dumps(scale_child(args.scale_child, args.seed, args.profile)))
        return
    if args.scale:
        scale_table(args)
        return

    gts, dets = [], []
    for f in range(args.frames):
        gt, det = make_frame(numpy_generator(args.seed, "bench_metric", f), args.gt, args.det)
        gts.append(gt)
        dets.append(det)
    n_gt = sum(len(g["name"]) for g in gts)
    n_det = sum(len(d["name"]) for d in dets)
    print(f"input: {args.frames} frames, {n_gt} GT, {n_det} predictions, classes {CLASSES}")
    print(f"threads: {args.threads} on both sides; load average {load()} at the start")

    t_exact, exact = timed(lambda: waymo_evaluate(gts, dets, CLASSES), args.repeats)
    t_greedy, greedy = timed(
        lambda: waymo_evaluate(gts, dets, CLASSES, matcher="score_first"), args.repeats
    )
    print(f"pcdet_atlas waymo_evaluate (exact Hungarian): {t_exact:.3f} s (load {load()})")

    official = run_official(args.venv, to_official_scene(gts, dets), args.repeats, args.threads)
    if official is None:
        print(
            f"official op: SKIPPED, not measured: no venv at {args.venv} (build it with "
            "tools/dev/official_waymo_metric/setup_venv.sh); no ratio is printed"
        )
    else:
        t_off, res = official
        names = list(res["names"])
        worst = 0.0
        for cls in CLASSES:
            for level in (1, 2):
                row = names.index(f"OBJECT_TYPE_TYPE_{cls.upper()}_LEVEL_{level}")
                worst = max(
                    worst,
                    abs(exact[f"{cls}/L{level}/AP"] - float(res["ap"][row])),
                    abs(exact[f"{cls}/L{level}/APH"] - float(res["aph"][row])),
                )
        print(f"official py_metrics_ops.detection_metrics: {t_off:.3f} s (load {load()})")
        print(f"ratio official / pcdet_atlas: {t_off / t_exact:.2f}x")
        print(f"max |AP or APH difference| vs official over 6 breakdowns: {worst:.2e}")

    print("\nexactness price (same input):")
    print(f"{'matcher':<28}{'time s':>9}{'L1 mAP':>9}{'L2 mAP':>9}{'L2 mAPH':>9}")
    for label, t, m in (
        ("Hungarian (official)", t_exact, exact),
        ("greedy score-first", t_greedy, greedy),
    ):
        print(f"{label:<28}{t:>9.3f}{m['L1/mAP']:>9.4f}{m['L2/mAP']:>9.4f}{m['L2/mAPH']:>9.4f}")
    diffs = {k: greedy[k] - exact[k] for k in exact}
    key = max(diffs, key=lambda k: abs(diffs[k]))
    print(f"greedy - Hungarian: L2 mAP {diffs['L2/mAP']:+.5f}; ", end="")
    print(f"largest |diff| {diffs[key]:+.5f} ({key})")
    print(f"time greedy / Hungarian: {t_greedy / t_exact:.2f}")


if __name__ == "__main__":
    run_tool(main)
