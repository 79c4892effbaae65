"""Run the official Waymo detection metric op on flat, OpenPCDet-style arrays.

Runs ONLY inside the isolated venv built by ``setup_venv.sh`` (tensorflow 2.13, numpy 1.23.5,
``waymo-open-dataset-tf-2-12-0==1.6.7``); it imports nothing from pcdet_atlas.

Input ``.npz`` keys (one scene; frames are integers ``0 .. num_frames - 1``):
    gt_frame (M,) int64, gt_name (M,) int64 index into WAYMO_CLASSES, gt_boxes (M, 7) float32,
    gt_num_points (M,) int64, gt_difficulty (M,) int64 (0 unknown, 1, 2),
    det_frame (K,) int64, det_name (K,) int64, det_boxes (K, 7) float32, det_score (K,) float32.

The OpenPCDet preprocessing (``waymo_eval.py`` ``generate_waymo_type_results``) is re-implemented
here, plainly and independently of pcdet_atlas: keep GT of the evaluated classes with > 0 points,
difficulty 0 -> 2 if <= 5 points else 1, distance mask < 1000.5 m, heading ``limit_period`` in
float32, sigmoid on scores if their max (in range, any class) is > 1.

CLI: ``python official_eval.py IN.npz OUT.npz [--matcher hungarian|score_first] [--repeat N]
[--threads N]``
writes ``names`` (B,), ``ap``, ``aph`` (B,), ``pr`` (B, 101, 5) = (P, R, TP, FP, FN) per cutoff,
``pr_h`` (B, 101, 2) and ``seconds`` (best wall time of the op over ``--repeat`` runs).
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")

import numpy as np  # noqa: E402
import tensorflow as tf  # noqa: E402
from google.protobuf import text_format  # noqa: E402
from waymo_open_dataset.metrics.ops import py_metrics_ops  # noqa: E402
from waymo_open_dataset.metrics.python import config_util_py as config_util  # noqa: E402
from waymo_open_dataset.protos import metrics_pb2  # noqa: E402

WAYMO_CLASSES = ["unknown", "Vehicle", "Pedestrian", "Sign", "Cyclist"]
CLASS_NAMES = ["Vehicle", "Pedestrian", "Cyclist"]


def build_config(matcher: str = "hungarian") -> metrics_pb2.Config:
    """OpenPCDet's config: OBJECT_TYPE breakdown, L1 + L2, 3D boxes, 101 score cutoffs."""
    matcher_type = {"hungarian": "TYPE_HUNGARIAN", "score_first": "TYPE_SCORE_FIRST"}[matcher]
    text = f"""
    breakdown_generator_ids: OBJECT_TYPE
    difficulties {{ levels: 1 levels: 2 }}
    matcher_type: {matcher_type}
    iou_thresholds: 0.0
    iou_thresholds: 0.7
    iou_thresholds: 0.5
    iou_thresholds: 0.5
    iou_thresholds: 0.5
    box_type: TYPE_3D
    """
    config = metrics_pb2.Config()
    text_format.Parse(text, config)
    for x in range(100):
        config.score_cutoffs.append(x * 0.01)
    config.score_cutoffs.append(1.0)
    return config


def _limit_period(val: np.ndarray) -> np.ndarray:
    return val - np.floor(val / (np.pi * 2) + 0.5) * (np.pi * 2)


def openpcdet_preprocess(scene: dict, class_names=CLASS_NAMES) -> dict:
    """OpenPCDet ``generate_waymo_type_results`` for GT and predictions -> op inputs."""
    wanted = np.array([WAYMO_CLASSES.index(c) for c in class_names])
    gt_mask = np.isin(scene["gt_name"], wanted) & (scene["gt_num_points"] > 0)
    diff = scene["gt_difficulty"].astype(np.int64).copy()
    zero = diff == 0
    diff[(scene["gt_num_points"] > 5) & zero] = 1
    diff[(scene["gt_num_points"] <= 5) & zero] = 2
    gt_boxes = scene["gt_boxes"].astype(np.float32).copy()
    gt_mask &= np.linalg.norm(gt_boxes[:, 0:2], axis=1) < 1000.5
    gt_boxes[:, 6] = _limit_period(gt_boxes[:, 6])

    det_boxes = scene["det_boxes"].astype(np.float32).copy()
    in_range = np.linalg.norm(det_boxes[:, 0:2], axis=1) < 1000.5
    det_mask = in_range & np.isin(scene["det_name"], wanted)
    det_boxes[:, 6] = _limit_period(det_boxes[:, 6])
    score = scene["det_score"].astype(np.float32)
    if in_range.any() and score[in_range].max() > 1:  # over every class, before the class filter
        score = (1.0 / (1.0 + np.exp(-score.astype(np.float64)))).astype(np.float32)
    score = score[det_mask]
    return {
        "prediction_bbox": det_boxes[det_mask].reshape(-1, 7),
        "prediction_type": scene["det_name"][det_mask].astype(np.uint8),
        "prediction_score": score,
        "prediction_frame_id": scene["det_frame"][det_mask].astype(np.int64),
        "prediction_overlap_nlz": np.zeros(int(det_mask.sum()), dtype=bool),
        "ground_truth_bbox": gt_boxes[gt_mask].reshape(-1, 7),
        "ground_truth_type": scene["gt_name"][gt_mask].astype(np.uint8),
        "ground_truth_frame_id": scene["gt_frame"][gt_mask].astype(np.int64),
        "ground_truth_difficulty": diff[gt_mask].astype(np.uint8),
    }


def run_official(
    scene: dict, matcher: str = "hungarian", repeat: int = 1, class_names=CLASS_NAMES
) -> dict:
    """Official metric on one scene; returns names, ap, aph, pr, pr_h and the best op time."""
    config = build_config(matcher)
    inputs = openpcdet_preprocess(scene, class_names)
    best = float("inf")
    for _ in range(max(1, repeat)):
        start = time.perf_counter()
        ap, aph, _apl, pr, pr_h, _pr_l, _bd = py_metrics_ops.detection_metrics(
            **{k: tf.constant(v) for k, v in inputs.items()}, config=config.SerializeToString()
        )
        ap = ap.numpy()
        best = min(best, time.perf_counter() - start)
    return {
        "names": np.array(config_util.get_breakdown_names_from_config(config)),
        "ap": ap.astype(np.float32),
        "aph": aph.numpy().astype(np.float32),
        "pr": pr.numpy().astype(np.float32),
        "pr_h": pr_h.numpy().astype(np.float32),
        "seconds": np.float64(best),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("input")
    parser.add_argument("output")
    parser.add_argument("--matcher", default="hungarian", choices=["hungarian", "score_first"])
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--threads", type=int, default=None, help="TF intra/inter-op threads")
    args = parser.parse_args()
    if args.threads:  # before the first op: TensorFlow fixes its pools then
        tf.config.threading.set_intra_op_parallelism_threads(args.threads)
        tf.config.threading.set_inter_op_parallelism_threads(args.threads)
    with np.load(args.input) as data:
        scene = {k: data[k] for k in data.files}
    result = run_official(scene, args.matcher, args.repeat)
    np.savez(args.output, **result)
    print(f"official op: {result['seconds']:.4f} s ({args.matcher})")


if __name__ == "__main__":
    main()
