"""Benchmark of the Waymo metric: pcdet_atlas vs the official op, exact Hungarian vs greedy.

Prints, for one seeded synthetic evaluation set (default 200 frames x ~100 GT x ~300 predictions
per frame, all three classes):
- the time of ``waymo_evaluate`` (exact Hungarian, the official semantics);
- where the official venv exists (``tools/official_waymo_metric/setup_venv.sh``), the official
  ``py_metrics_ops.detection_metrics`` time on the same input, the ratio, and the largest AP/APH
  difference between the two (a large-scale cross-check of the fixtures' result);
- the price of exactness: greedy score-first matching (COCO style) vs Hungarian, time and AP.

Usage: ``python tools/bench_metric.py [--frames 200] [--gt 100] [--det 300] [--repeats 3]
[--threads 1] [--venv .cache/waymo_official_venv]``
"""

from __future__ import annotations

import argparse
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from pcdet_atlas.evaluation.waymo_metric import waymo_evaluate
from pcdet_atlas.utils.seeding import numpy_generator

REPO = Path(__file__).resolve().parents[1]
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
    """Flat arrays in the input format of ``tools/official_waymo_metric/official_eval.py``."""

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


def run_official(venv: Path, scene: dict, repeats: int) -> tuple[float, dict] | None:
    python = venv / "bin" / "python"
    if not python.exists():
        return None
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "scene.npz", Path(tmp) / "official.npz"
        np.savez(src, **scene)
        script = REPO / "tools" / "official_waymo_metric" / "official_eval.py"
        cmd = [str(python), str(script), str(src), str(dst), "--repeat", str(repeats)]
        subprocess.run(cmd, check=True, capture_output=True)
        with np.load(dst) as res:
            out = {k: res[k] for k in res.files}
    return float(out["seconds"]), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--gt", type=int, default=100)
    parser.add_argument("--det", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--venv", type=Path, default=REPO / ".cache" / "waymo_official_venv")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    gts, dets = [], []
    for f in range(args.frames):
        gt, det = make_frame(numpy_generator(args.seed, "bench_metric", f), args.gt, args.det)
        gts.append(gt)
        dets.append(det)
    n_gt = sum(len(g["name"]) for g in gts)
    n_det = sum(len(d["name"]) for d in dets)
    print(f"input: {args.frames} frames, {n_gt} GT, {n_det} predictions, classes {CLASSES}")

    t_exact, exact = timed(lambda: waymo_evaluate(gts, dets, CLASSES), args.repeats)
    t_greedy, greedy = timed(
        lambda: waymo_evaluate(gts, dets, CLASSES, matcher="score_first"), args.repeats
    )
    print(f"pcdet_atlas waymo_evaluate (exact Hungarian): {t_exact:.3f} s")

    official = run_official(args.venv, to_official_scene(gts, dets), args.repeats)
    if official is None:
        print(f"official op: not measured (no venv at {args.venv}; see setup_venv.sh)")
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
        print(f"official py_metrics_ops.detection_metrics: {t_off:.3f} s")
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
    main()
