"""Localisation diagnosis: per-parameter box errors, one-to-one IoU matching, AP by IoU."""

from __future__ import annotations

import importlib.util
import math
import pickle

import numpy as np
import pytest
from malicious_files import malicious_pickle

from pcdet_atlas.config import REPO_ROOT
from pcdet_atlas.evaluation.localization import (
    ap_by_iou,
    box_errors,
    localization_errors,
    match_by_iou,
    match_score_first,
    projected_ap,
)
from pcdet_atlas.evaluation.waymo_metric import compute_waymo_curves
from pcdet_atlas.utils.safe_pickle import RefusedGlobalError


def shifted(boxes: np.ndarray, along: np.ndarray) -> np.ndarray:
    """``boxes`` moved by ``along`` metres along their own heading."""
    out = boxes.copy()
    out[:, 0] += along * np.cos(boxes[:, 6])
    out[:, 1] += along * np.sin(boxes[:, 6])
    return out


def test_box_errors_in_the_ground_truth_frame():
    gt = np.array([[10.0, 5.0, 1.0, 4.0, 2.0, 1.5, math.pi / 2], [0, 0, 0, 4, 2, 1.5, 3.0]])
    pred = gt.copy()
    pred[0, :2] += [-0.3, 0.2]  # heading +y: along = +0.2, across = +0.3
    pred[0, 3:6] += [-0.5, 0.1, 0.2]
    pred[0, 6] += 0.1
    pred[1, 6] = 3.0 - math.pi + 0.05  # flipped, 0.05 rad off once folded
    e = box_errors(gt, pred)
    np.testing.assert_allclose(e["along"], [0.2, 0.0], atol=1e-12)
    np.testing.assert_allclose(e["across"], [0.3, 0.0], atol=1e-12)
    np.testing.assert_allclose([e["length"][0], e["width"][0], e["height"][0]], [-0.5, 0.1, 0.2])
    np.testing.assert_allclose(e["heading"], [0.1, 0.05 - math.pi], atol=1e-12)
    assert e["flipped"].tolist() == [False, True]
    np.testing.assert_allclose(e["heading_mod_pi"], [0.1, 0.05], atol=1e-12)


def test_match_by_iou_is_one_to_one_and_greedy():
    gt = np.array([[0, 0, 0, 4, 2, 1.5, 0], [20, 0, 0, 4, 2, 1.5, 0.0]])
    # prediction 0 overlaps GT 0 best; prediction 1 overlaps GT 0 a little less, GT 1 not at all
    pred = np.concatenate([shifted(gt[:1], np.array([0.2])), shifted(gt[:1], np.array([0.6]))])
    g, p, iou = match_by_iou(gt, pred)
    assert g.tolist() == [0] and p.tolist() == [0]
    np.testing.assert_allclose(iou, [(4 - 0.2) / (4 + 0.2)], rtol=1e-9)
    g, p, _ = match_by_iou(gt, np.zeros((0, 7)))
    assert g.size == p.size == 0


def test_ap_by_iou_falls_where_the_boxes_stop_overlapping_enough():
    rng = np.random.default_rng(0)
    gt_annos, det_annos = [], []
    for _ in range(5):
        n = 6
        boxes = np.column_stack([
            rng.uniform(-40, 40, n), rng.uniform(-40, 40, n), rng.uniform(0.5, 1.0, n),
            rng.uniform(3.5, 5.5, n), rng.uniform(1.8, 2.2, n), rng.uniform(1.4, 1.8, n),
            rng.uniform(-math.pi, math.pi, n),
        ])  # fmt: skip
        boxes[:, 0] += 100.0 * np.arange(n)  # far apart
        gt_annos.append({
            "name": np.array(["Vehicle"] * n), "gt_boxes_lidar": boxes,
            "num_points_in_gt": np.full(n, 50), "difficulty": np.zeros(n, np.int64),
        })  # fmt: skip
        # 3D IoU of a box and itself moved d along its length l: (l - d) / (l + d) = 0.65
        pred = shifted(boxes, 0.35 / 1.65 * boxes[:, 3])
        det_annos.append(
            {"name": np.array(["Vehicle"] * n), "boxes_lidar": pred, "score": np.full(n, 0.9)}
        )
    ap = ap_by_iou(gt_annos, det_annos, "Vehicle", (0.5, 0.6, 0.7))
    assert ap[0.5][0] == pytest.approx(1.0) and ap[0.6][0] == pytest.approx(1.0)
    assert ap[0.7][0] == pytest.approx(0.0)
    report = localization_errors(gt_annos, det_annos, "Vehicle")
    assert report["num_gt"] == report["num_matched"] == 30
    assert report["iou_median"] == pytest.approx(0.65, abs=1e-6)
    assert report["length"]["median_abs"] == pytest.approx(0.0, abs=1e-9)
    lengths = np.concatenate([g["gt_boxes_lidar"][:, 3] for g in gt_annos])
    assert report["along"]["bias"] == pytest.approx(np.mean(0.35 / 1.65 * lengths))
    # the official thresholds are untouched by the override
    assert compute_waymo_curves(gt_annos, det_annos, ["Vehicle"])["Vehicle/L2"]["ap"] == 0.0
    with pytest.raises(ValueError, match="iou_thresholds"):
        compute_waymo_curves(gt_annos, det_annos, ["Vehicle"], iou_thresholds={"Vehicle": 1.5})
    with pytest.raises(ValueError, match="iou_thresholds"):
        compute_waymo_curves(gt_annos, det_annos, ["Vehicle"], iou_thresholds={"Cyclist": 0.5})


def test_match_score_first_follows_the_ranking():
    gt = np.array([[0, 0, 0, 4, 2, 1.5, 0.0]])
    loose = shifted(gt, np.array([1.0]))  # IoU 0.6, high score
    tight = shifted(gt, np.array([0.1]))  # IoU 0.95, low score
    g, p = match_score_first(gt, np.concatenate([tight, loose]), np.array([0.2, 0.9]))
    assert g.tolist() == [0] and p.tolist() == [1]
    g, p = match_by_iou(gt, np.concatenate([tight, loose]))[:2]
    assert p.tolist() == [0]  # by IoU the tight one


def test_projected_ap_scales_the_chosen_errors():
    """Vehicles predicted 0.7 m too far along their heading and 0.2 rad off (IoU < 0.7): the
    AP at 0.7 is 0; with no centre error only the heading remains; with neither, 1."""
    rng = np.random.default_rng(1)
    n = 8
    boxes = np.column_stack([
        100.0 * np.arange(n), rng.uniform(-5, 5, n), np.full(n, 0.8), np.full(n, 4.5),
        np.full(n, 2.0), np.full(n, 1.6), rng.uniform(-3, 3, n),
    ])  # fmt: skip
    pred = shifted(boxes, np.full(n, 0.7))
    pred[:, 6] += 0.2
    gt_annos = [{
        "name": np.array(["Vehicle"] * n), "gt_boxes_lidar": boxes,
        "num_points_in_gt": np.full(n, 50), "difficulty": np.zeros(n, np.int64),
    }]  # fmt: skip
    det = {"name": np.array(["Vehicle"] * n), "boxes_lidar": pred, "score": np.full(n, 0.9)}
    before = pred.copy()
    assert projected_ap(gt_annos, [det], "Vehicle", {}) == pytest.approx(0.0)
    assert projected_ap(gt_annos, [det], "Vehicle", {"center": 0.0, "heading": 0.0}) == (
        pytest.approx(1.0)
    )
    only_heading = projected_ap(gt_annos, [det], "Vehicle", {"center": 0.0})
    iou = match_by_iou(boxes, np.column_stack([boxes[:, :6], boxes[:, 6] + 0.2]))[2]
    assert only_heading == pytest.approx(1.0 if iou.min() >= 0.7 else 0.0)
    assert np.array_equal(pred, before)  # the predictions are not modified
    with pytest.raises(ValueError, match="unknown component"):
        projected_ap(gt_annos, [det], "Vehicle", {"yaw": 0.5})


def test_projected_ap_matches_only_the_ground_truth_the_metric_scores():
    """A 0-point GT box (which the metric drops) must not take the prediction: it overlaps the
    0-point box exactly and the scored box at IoU 3.5 / 5.5 < 0.7; moved onto the scored box
    (centre error 0), it is a TP."""
    scored = np.array([[10.0, 0.0, 0.8, 4.5, 2.0, 1.6, 0.0]])
    empty = shifted(scored, np.array([1.0]))
    gt_annos = [{
        "name": np.array(["Vehicle", "Vehicle"]),
        "gt_boxes_lidar": np.concatenate([scored, empty]),
        "num_points_in_gt": np.array([50, 0]), "difficulty": np.zeros(2, np.int64),
    }]  # fmt: skip
    det = {"name": np.array(["Vehicle"]), "boxes_lidar": empty.copy(), "score": np.array([0.9])}
    assert projected_ap(gt_annos, [det], "Vehicle", {}) == pytest.approx(0.0)
    assert projected_ap(gt_annos, [det], "Vehicle", {"center": 0.0}) == pytest.approx(1.0)


def test_analyze_boxes_tool_on_a_test_result(synthetic_root, tmp_path, capsys):
    """``tools/dev/analyze_boxes.py`` on a result.pkl of the synthetic val split: predictions that
    are the ground-truth vehicles lengthened by 0.4 m."""
    spec = importlib.util.spec_from_file_location(
        "analyze", REPO_ROOT / "tools/dev/analyze_boxes.py"
    )
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    from pcdet_atlas.datasets.waymo_format import (
        load_sequence_infos,
        read_image_set,
        sequence_pkl_path,
    )

    name = read_image_set(synthetic_root / "ImageSets" / "val.txt")[0]
    infos = load_sequence_infos(sequence_pkl_path(synthetic_root, name))
    det = []
    for info in infos[:10]:
        a = info["annos"]
        keep = (np.asarray(a["name"]) == "Vehicle") & (np.asarray(a["num_points_in_gt"]) > 0)
        boxes = np.asarray(a["gt_boxes_lidar"])[keep].copy()
        boxes[:, 3] += 0.4
        det.append({"frame_id": info["frame_id"], "name": np.array(["Vehicle"] * len(boxes)),
                    "boxes_lidar": boxes, "score": np.full(len(boxes), 0.8)})  # fmt: skip
    result = tmp_path / "result.pkl"
    result.write_bytes(pickle.dumps(det))
    cfg = str(REPO_ROOT / "cfgs/atlas/synthetic/centerpoint.yaml")
    out = tool.main(["--cfg", cfg, "--result", str(result), "--project", "--set",
                     "DATA_CONFIG.DATA_PATH", str(synthetic_root)])  # fmt: skip
    report = out["localization"]
    assert report["num_matched"] == report["num_gt"] > 20
    assert report["length"]["bias"] == pytest.approx(0.4) and report["flipped_fraction"] == 0.0
    assert out["ap_by_iou"][0.5][0] > 0.9
    # the only error is the length: halving it or removing it helps, the others change nothing
    proj = out["projected"]
    assert proj["center x0.5"] == pytest.approx(out["ap_by_iou"][0.7][0])
    assert proj["all x0"] >= proj["length x0.5"] >= proj["center x0.5"]
    assert "length" in capsys.readouterr().out
    det[0] = dict(det[0], frame_id="segment-unknown_000")
    result.write_bytes(pickle.dumps(det))
    with pytest.raises(SystemExit, match="not in the config"):
        tool.main(["--cfg", cfg, "--result", str(result), "--set",
                   "DATA_CONFIG.DATA_PATH", str(synthetic_root)])  # fmt: skip
    marker = tmp_path / "marker"
    malicious_pickle(result, marker, det)
    with pytest.raises(RefusedGlobalError, match=rf"{result}: refused to unpickle the global "):
        tool.main(["--cfg", cfg, "--result", str(result), "--set",
                   "DATA_CONFIG.DATA_PATH", str(synthetic_root)])  # fmt: skip
    assert not marker.exists()
