"""Waymo L1/L2 AP/APH: the official op's stored outputs, hand-computed cases, plain references."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.optimize import linear_sum_assignment

from pcdet_atlas.evaluation.waymo_metric import (
    WAYMO_SCORE_CUTOFFS,
    compute_waymo_curves,
    waymo_average_precision,
    waymo_evaluate,
    waymo_heading_accuracy,
)
from pcdet_atlas.ops.iou3d_nms import boxes_iou3d

FIXTURE = Path(__file__).parent / "fixtures" / "official_waymo_metric.npz"
CLASSES = ["Vehicle", "Pedestrian", "Cyclist"]
SHARD = {"Vehicle": "VEHICLE", "Pedestrian": "PEDESTRIAN", "Sign": "SIGN", "Cyclist": "CYCLIST"}


# ------------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def official():
    with np.load(FIXTURE) as data:
        return {k: data[k] for k in data.files}


def _scenes(official) -> list[str]:
    return sorted({k.split("/")[0] for k in official if k.endswith("/num_frames")})


def _annos(official, scene: str):
    classes = list(official["waymo_classes"])
    gts, dets = [], []
    for f in range(int(official[f"{scene}/num_frames"])):
        g = official[f"{scene}/gt_frame"] == f
        d = official[f"{scene}/det_frame"] == f
        gts.append(
            {
                "frame_id": f"seq_{f:03d}",
                "name": np.array([classes[i] for i in official[f"{scene}/gt_name"][g]]),
                "gt_boxes_lidar": official[f"{scene}/gt_boxes"][g],
                "num_points_in_gt": official[f"{scene}/gt_num_points"][g],
                "difficulty": official[f"{scene}/gt_difficulty"][g],
            }
        )
        dets.append(
            {
                "frame_id": f"seq_{f:03d}",
                "name": np.array([classes[i] for i in official[f"{scene}/det_name"][d]]),
                "boxes_lidar": official[f"{scene}/det_boxes"][d],
                "score": official[f"{scene}/det_score"][d],
            }
        )
    return gts, dets


def _gt(boxes, names=None, points=None, difficulty=None):
    boxes = np.asarray(boxes, dtype=np.float32).reshape(-1, 7)
    n = len(boxes)
    return {
        "name": np.array(names or ["Vehicle"] * n),
        "gt_boxes_lidar": boxes,
        "num_points_in_gt": np.asarray(points if points is not None else [100] * n),
        "difficulty": np.asarray(difficulty if difficulty is not None else [0] * n),
    }


def _det(boxes, scores, names=None):
    boxes = np.asarray(boxes, dtype=np.float32).reshape(-1, 7)
    return {
        "name": np.array(names or ["Vehicle"] * len(boxes)),
        "boxes_lidar": boxes,
        "score": np.asarray(scores, dtype=np.float32),
    }


CAR = [0.0, 0.0, 1.0, 4.5, 2.0, 1.6, 0.3]
CAR2 = [20.0, 5.0, 1.0, 4.5, 2.0, 1.6, -1.0]


# ------------------------------------------------------------------------------------------------
# against the official waymo-open-dataset-tf-2-12-0==1.6.7 op (fixtures made by
# tools/dev/official_waymo_metric/make_fixtures.py)
# ------------------------------------------------------------------------------------------------
def test_fixture_covers_the_required_cases(official):
    scenes = _scenes(official)
    assert {"random_mixed", "crowded", "near_threshold", "ties_and_headings"} <= set(scenes)
    mixed = "random_mixed"
    assert (official[f"{mixed}/gt_num_points"] == 0).any()
    assert (
        (official[f"{mixed}/gt_num_points"] <= 5) & (official[f"{mixed}/gt_num_points"] > 0)
    ).any()
    assert (official[f"{mixed}/gt_difficulty"] == 2).any()
    frames = set(range(int(official[f"{mixed}/num_frames"])))
    with_gt, with_det = set(official[f"{mixed}/gt_frame"]), set(official[f"{mixed}/det_frame"])
    assert frames - with_gt - with_det  # empty frames
    assert with_det - with_gt and with_gt - with_det  # prediction-only and GT-only frames
    assert FIXTURE.stat().st_size < 2_000_000


@pytest.mark.parametrize(
    "scene",
    [
        "random_mixed",
        "crowded",
        "near_threshold",
        "ties_and_headings",
        "hungarian_vs_greedy",
        "logits",
        "only_predictions",
        "only_gt",
        "single_class",
    ],
)
def test_matches_official_op(official, scene):
    _compare_with_official(official, scene, CLASSES, "hungarian")


def test_matches_official_op_with_sign(official):
    _compare_with_official(
        official, "random_mixed", ["Vehicle", "Pedestrian", "Sign", "Cyclist"], "with_sign"
    )


def _compare_with_official(official, scene, class_names, run):
    gts, dets = _annos(official, scene)
    curves = compute_waymo_curves(gts, dets, class_names)
    metrics = waymo_evaluate(gts, dets, class_names)
    names = list(official["breakdown_names"])
    for cls in class_names:
        for level in (1, 2):
            row = names.index(f"OBJECT_TYPE_TYPE_{SHARD[cls]}_LEVEL_{level}")
            pr = official[f"{scene}/{run}/pr"][row]  # (101, 5): P, R, TP, FP, FN
            pr_h = official[f"{scene}/{run}/pr_h"][row]  # (101, 2): P_heading, R
            curve = curves[f"{cls}/L{level}"]
            where = f"{scene} {cls} L{level}"
            np.testing.assert_array_equal(curve["tp"], pr[:, 2].astype(np.int64), err_msg=where)
            np.testing.assert_array_equal(curve["fp"], pr[:, 3].astype(np.int64), err_msg=where)
            np.testing.assert_array_equal(curve["fn"], pr[:, 4].astype(np.int64), err_msg=where)
            np.testing.assert_allclose(curve["precision"], pr[:, 0], atol=1e-7, err_msg=where)
            np.testing.assert_allclose(curve["recall"], pr[:, 1], atol=1e-7, err_msg=where)
            np.testing.assert_allclose(curve["precision_ha"], pr_h[:, 0], atol=1e-6, err_msg=where)
            ap = official[f"{scene}/{run}/ap"][row]
            aph = official[f"{scene}/{run}/aph"][row]
            assert metrics[f"{cls}/L{level}/AP"] == pytest.approx(ap, abs=1e-4), where
            assert metrics[f"{cls}/L{level}/APH"] == pytest.approx(aph, abs=1e-4), where
            assert curve["ap"] == pytest.approx(ap, abs=1e-6), where
    for level in (1, 2):
        aps = [metrics[f"{c}/L{level}/AP"] for c in class_names]
        assert metrics[f"L{level}/mAP"] == pytest.approx(np.mean(aps))


def test_hungarian_fixture_differs_from_greedy(official):
    """The adversarial scene must separate the exact matching from score-first matching."""
    gts, dets = _annos(official, "hungarian_vs_greedy")
    exact = waymo_evaluate(gts, dets, CLASSES)
    greedy = waymo_evaluate(gts, dets, CLASSES, matcher="score_first")
    assert exact["L2/mAP"] > greedy["L2/mAP"] + 0.05
    for c in CLASSES:
        row = list(official["breakdown_names"]).index(f"OBJECT_TYPE_TYPE_{SHARD[c]}_LEVEL_2")
        assert exact[f"{c}/L2/AP"] == pytest.approx(
            official["hungarian_vs_greedy/hungarian/ap"][row], abs=1e-4
        )


def _official_score_first_quirk(official, scene: str, cls_code: int, thr: float) -> np.ndarray:
    """TP per cutoff of the official TYPE_SCORE_FIRST matcher, which (in 1.6.7) compares
    ``IoU(subset position, subset position)`` instead of the IoU of the candidate pair."""
    tp = np.zeros(len(WAYMO_SCORE_CUTOFFS), np.int64)
    for f in range(int(official[f"{scene}/num_frames"])):
        g = official[f"{scene}/gt_frame"] == f
        d = official[f"{scene}/det_frame"] == f
        gb, gt_type = official[f"{scene}/gt_boxes"][g], official[f"{scene}/gt_name"][g]
        db, dt_type = official[f"{scene}/det_boxes"][d], official[f"{scene}/det_name"][d]
        score = official[f"{scene}/det_score"][d]
        iou = boxes_iou3d(torch.from_numpy(db).double(), torch.from_numpy(gb).double()).numpy()
        iou = iou.astype(np.float32) * (dt_type[:, None] == gt_type[None, :])
        gsub = np.nonzero(gt_type == cls_code)[0]
        for k, cutoff in enumerate(WAYMO_SCORE_CUTOFFS):
            psub = np.nonzero((dt_type == cls_code) & (score >= cutoff))[0]
            taken = np.zeros(len(gsub), bool)
            for a in sorted(range(len(psub)), key=lambda a: -score[psub[a]]):
                best, best_j = -1.0, -1
                for j in range(len(gsub)):
                    if not taken[j] and iou[psub[a], gsub[j]] >= thr and iou[a, j] > best:
                        best, best_j = iou[a, j], j
                if best_j >= 0:
                    taken[best_j] = True
                    tp[k] += 1
    return tp


def test_official_score_first_matcher_quirk_explains_its_counts(official):
    """Documents why ``matcher='score_first'`` is a correct greedy and not the official one."""
    scene = "hungarian_vs_greedy"
    names = list(official["breakdown_names"])
    gts, dets = _annos(official, scene)
    ours = compute_waymo_curves(gts, dets, CLASSES, matcher="score_first")
    differs = False
    for cls, code, thr in (("Vehicle", 1, 0.7), ("Pedestrian", 2, 0.5), ("Cyclist", 4, 0.5)):
        row = names.index(f"OBJECT_TYPE_TYPE_{SHARD[cls]}_LEVEL_2")
        official_tp = official[f"{scene}/score_first/pr"][row][:, 2].astype(np.int64)
        np.testing.assert_array_equal(
            _official_score_first_quirk(official, scene, code, thr), official_tp
        )
        differs |= not np.array_equal(ours[f"{cls}/L2"]["tp"], official_tp)
    assert differs


# ------------------------------------------------------------------------------------------------
# hand-computed cases
# ------------------------------------------------------------------------------------------------
def test_official_average_precision_unit_cases():
    """The cases of the official ``metrics_utils_test.cc``."""
    assert waymo_average_precision([], []) == 0.0
    assert waymo_average_precision([0.1], [0.2]) == pytest.approx(0.02, abs=1e-6)
    expected = 0.05 * 0.8 + 0.1 * 0.2 + (0.1 - 0.05) * 0.5 * 0.05
    assert waymo_average_precision([0.1, 0.05], [0.2, 1.0]) == pytest.approx(expected, abs=1e-6)
    expected = 0.2 * 0.1 + 0.5 * (0.1 + 0.05) * 0.8
    assert waymo_average_precision([0.1, 0.05], [0.2, 1.0], 1.0) == pytest.approx(
        expected, abs=1e-6
    )
    expected = 0.05 * 0.8 + 0.1 * 0.2 + (0.1 - 0.05) * 0.5 * 0.05
    got = waymo_average_precision([0.1, 0.0, 0.05], [0.2, 0.4, 1.0])
    assert got == pytest.approx(expected, abs=1e-6)


def test_perfect_detection_and_half_recall():
    gts = [_gt([CAR, CAR2])]
    assert waymo_evaluate(gts, [_det([CAR, CAR2], [0.9, 0.8])], ["Vehicle"])["L2/mAP"] == 1.0
    m = waymo_evaluate(gts, [_det([CAR], [0.9])], ["Vehicle"])
    assert m["Vehicle/L1/AP"] == pytest.approx(0.5, abs=1e-6)  # P = 1 up to R = 0.5
    assert m["Vehicle/L1/APH"] == pytest.approx(0.5, abs=1e-6)


def test_false_positive_above_true_positive():
    """TP at score 0.4, FP at 0.8: the envelope is P = 0.5 from R = 0 to R = 1 -> AP 0.5."""
    far = [50.0, 50.0, 1.0, 4.5, 2.0, 1.6, 0.0]
    curves = compute_waymo_curves([_gt([CAR])], [_det([CAR, far], [0.4, 0.8])], ["Vehicle"])
    curve = curves["Vehicle/L1"]
    assert curve["ap"] == pytest.approx(0.5, abs=1e-6)
    k = np.searchsorted(WAYMO_SCORE_CUTOFFS, np.float32(0.4), side="right")
    assert (curve["tp"][:k] == 1).all() and (curve["tp"][k:] == 0).all()
    assert (
        curve["fp"][: np.searchsorted(WAYMO_SCORE_CUTOFFS, np.float32(0.8), side="right")] == 1
    ).all()
    assert (curve["precision"][k:] == 1).all()  # R = 0 -> P = 1


def test_heading_accuracy_and_aph():
    assert waymo_heading_accuracy(
        [0.0, np.pi, 0.5], [np.pi, -np.pi, 0.5 + np.pi / 2]
    ).tolist() == pytest.approx([0.0, 1.0, 0.5], abs=1e-6)
    flipped = list(CAR)
    flipped[6] += math.pi
    m = waymo_evaluate([_gt([CAR])], [_det([flipped], [0.9])], ["Vehicle"])
    assert m["Vehicle/L1/AP"] == pytest.approx(1.0, abs=1e-6)
    assert m["Vehicle/L1/APH"] == pytest.approx(0.0, abs=1e-6)
    quarter = list(CAR)
    quarter[6] += math.pi / 2
    square = [0.0, 0.0, 1.0, 2.0, 2.0, 1.6, 0.3]  # a square keeps IoU 1 under a quarter turn
    sq_turned = square[:6] + [0.3 + math.pi / 2]
    m = waymo_evaluate([_gt([square])], [_det([sq_turned], [0.9])], ["Vehicle"])
    assert m["Vehicle/L1/APH"] == pytest.approx(0.5, abs=1e-6)


def test_levels_differ_only_in_false_negatives():
    # GT 0: 100 points (L1) detected; GT 1: 3 points (L2 by the point rule) missed
    gts = [_gt([CAR, CAR2], points=[100, 3])]
    curves = compute_waymo_curves(gts, [_det([CAR], [0.9])], ["Vehicle"])
    l1, l2 = curves["Vehicle/L1"], curves["Vehicle/L2"]
    np.testing.assert_array_equal(l1["tp"], l2["tp"])
    np.testing.assert_array_equal(l1["fp"], l2["fp"])
    assert (l2["fn"] - l1["fn"] == 1).all()
    assert l1["ap"] == pytest.approx(1.0, abs=1e-6) and l2["ap"] == pytest.approx(0.5, abs=1e-6)
    # a matched L2 GT is a TP even at L1 (L1 only ignores *missed* L2 objects)
    m = waymo_evaluate([_gt([CAR2], points=[3])], [_det([CAR2], [0.9])], ["Vehicle"])
    assert m["Vehicle/L1/AP"] == pytest.approx(1.0, abs=1e-6)
    # the annotator's level wins over the point rule
    m = waymo_evaluate(
        [_gt([CAR, CAR2], points=[100, 500], difficulty=[0, 2])], [_det([CAR], [0.9])], ["Vehicle"]
    )
    assert m["Vehicle/L1/AP"] == pytest.approx(1.0, abs=1e-6)
    assert m["Vehicle/L2/AP"] == pytest.approx(0.5, abs=1e-6)


def test_zero_point_gt_dropped_and_classes_filtered():
    gts = [_gt([CAR, CAR2], points=[0, 100])]
    curves = compute_waymo_curves(gts, [_det([CAR, CAR2], [0.9, 0.8])], ["Vehicle"])
    assert curves["Vehicle/L2"]["fp"][0] == 1 and curves["Vehicle/L2"]["fn"][0] == 0
    # a pedestrian prediction never matches a vehicle GT
    m = waymo_evaluate([_gt([CAR])], [_det([CAR], [0.9], names=["Pedestrian"])], CLASSES)
    assert m["Vehicle/L1/AP"] == 0.0 and m["Pedestrian/L1/AP"] == 0.0


@pytest.mark.parametrize("side", ["gt", "det"])
def test_names_outside_the_waymo_classes_are_errors(side):
    """'Car' is no Waymo class: an error naming it and the frame, not a silent Vehicle AP 0."""
    gts = [_gt([CAR]), _gt([CAR2])]
    dets = [_det([CAR], [0.9]), _det([CAR2], [0.8])]
    if side == "gt":
        gts[1] = _gt([CAR2], names=["Car"])
    else:
        dets[1] = _det([CAR2], [0.8], names=["Car"])
    where = "gt_annos[1]" if side == "gt" else "det_annos[1]"
    with pytest.raises(ValueError, match=rf"{re.escape(where)}: 'name' 'Car' \(box 0\)"):
        waymo_evaluate(gts, dets, ["Vehicle"])
    # a Waymo class that is not evaluated (and GT of type 'unknown') is left out, as before
    gts[1] = _gt([CAR2, CAR], names=["Vehicle", "Sign"])
    dets[1] = _det([CAR2, CAR], [0.8, 0.7], names=["Vehicle", "unknown"])
    assert waymo_evaluate(gts, dets, ["Vehicle"])["Vehicle/L2/AP"] == 1.0


def test_class_names_as_a_string_is_an_error():
    with pytest.raises(TypeError, match="class_names must be a list.*'Vehicle'"):
        waymo_evaluate([_gt([CAR])], [_det([CAR], [0.9])], "Vehicle")


def test_iou_threshold_and_degenerate_boxes():
    def shifted(d):
        b = list(CAR)
        b[0] += d * math.cos(CAR[6])
        b[1] += d * math.sin(CAR[6])
        return b

    length = CAR[3]
    ok = waymo_evaluate(
        [_gt([CAR])], [_det([shifted(length * 0.3 / 1.7 * 0.99)], [0.9])], ["Vehicle"]
    )
    bad = waymo_evaluate(
        [_gt([CAR])], [_det([shifted(length * 0.3 / 1.7 * 1.01)], [0.9])], ["Vehicle"]
    )
    assert ok["Vehicle/L1/AP"] == pytest.approx(1.0, abs=1e-6) and bad["Vehicle/L1/AP"] == 0.0
    tiny = [0.0, 0.0, 1.0, 0.01, 2.0, 1.6, 0.0]  # dims <= 0.01: IoU 0 in the official metric
    assert waymo_evaluate([_gt([tiny])], [_det([tiny], [0.9])], ["Vehicle"])["L1/mAP"] == 0.0


def test_logit_scores_get_a_sigmoid():
    gts = [_gt([CAR, CAR2])]
    logits = waymo_evaluate(gts, [_det([CAR, CAR2], [3.0, -2.0])], ["Vehicle"])
    probs = waymo_evaluate(
        gts, [_det([CAR, CAR2], [1 / (1 + math.exp(-3)), 1 / (1 + math.exp(2))])], ["Vehicle"]
    )
    assert logits == probs


def test_sigmoid_rule_counts_predictions_of_every_class():
    """OpenPCDet takes the largest score over all predictions (in range) before any class
    filter: one Pedestrian logit of 3.0 squashes the Vehicle scores too, though only Vehicle is
    evaluated."""
    gts = [_gt([CAR, CAR2])]
    far = [50.0, 50.0, 1.0, 4.5, 2.0, 1.6, 0.0]
    scores = [0.3, 0.6]  # the TP at 0.3, an FP at 0.6
    mixed = _det(
        [CAR, far, CAR2], [scores[0], scores[1], 3.0], ["Vehicle", "Vehicle", "Pedestrian"]
    )
    squashed = _det([CAR, far], [1 / (1 + math.exp(-v)) for v in scores])
    got = compute_waymo_curves(gts, [mixed], ["Vehicle"])["Vehicle/L2"]
    expected = compute_waymo_curves(gts, [squashed], ["Vehicle"])["Vehicle/L2"]
    raw = compute_waymo_curves(gts, [_det([CAR, far], scores)], ["Vehicle"])["Vehicle/L2"]
    for key in ("tp", "fp", "fn"):
        np.testing.assert_array_equal(got[key], expected[key])
    assert not np.array_equal(got["tp"], raw["tp"])  # 0.3 -> 0.574: kept by more cutoffs
    # a prediction beyond the distance limit does not count
    beyond = _det([CAR, far, [2000.0, 0, 1, 1, 1, 1, 0]], [*scores, 3.0],
                  ["Vehicle", "Vehicle", "Pedestrian"])  # fmt: skip
    out = compute_waymo_curves(gts, [beyond], ["Vehicle"])["Vehicle/L2"]
    np.testing.assert_array_equal(out["tp"], raw["tp"])


# ------------------------------------------------------------------------------------------------
# invariances, empty inputs, errors
# ------------------------------------------------------------------------------------------------
def test_invariant_to_frame_order(official):
    gts, dets = _annos(official, "random_mixed")
    perm = np.random.default_rng(0).permutation(len(gts))
    a = waymo_evaluate(gts, dets, CLASSES)
    b = waymo_evaluate([gts[i] for i in perm], [dets[i] for i in perm], CLASSES)
    assert a == pytest.approx(b, abs=1e-6)


def test_empty_inputs():
    for gts, dets in (
        ([], []),
        ([_gt([])], [_det([], [])]),
        ([_gt([CAR])], [_det([], [])]),
        ([_gt([])], [_det([CAR], [0.5])]),
    ):
        m = waymo_evaluate(gts, dets, CLASSES)
        assert set(m) == {
            f"{c}/L{k}/{x}" for c in CLASSES for k in (1, 2) for x in ("AP", "APH")
        } | {f"L{k}/{x}" for k in (1, 2) for x in ("mAP", "mAPH")}
        assert all(v == 0.0 for v in m.values())


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="aligned"):
        waymo_evaluate([_gt([CAR])], [], ["Vehicle"])
    gt, det = _gt([CAR]), _det([CAR], [0.9])
    with pytest.raises(ValueError, match="frame_id"):
        waymo_evaluate([dict(gt, frame_id="a")], [dict(det, frame_id="b")], ["Vehicle"])
    with pytest.raises(KeyError, match="num_points_in_gt"):
        waymo_evaluate(
            [{k: v for k, v in gt.items() if k != "num_points_in_gt"}], [det], ["Vehicle"]
        )
    with pytest.raises(ValueError, match="difficulty"):
        waymo_evaluate([dict(gt, difficulty=np.array([3]))], [det], ["Vehicle"])
    with pytest.raises(ValueError, match="class_names"):
        waymo_evaluate([gt], [det], ["Car"])
    with pytest.raises(ValueError, match="boxes_lidar"):
        waymo_evaluate([gt], [dict(det, boxes_lidar=np.zeros((1, 5)))], ["Vehicle"])
    with pytest.raises(ValueError, match="matcher"):
        waymo_evaluate([gt], [det], ["Vehicle"], matcher="coco")


# ------------------------------------------------------------------------------------------------
# the fast paths against plain references (one full matching per frame, class and cutoff)
# ------------------------------------------------------------------------------------------------
def _reference_tp(gts, dets, cls: str, thr: float, greedy: bool) -> np.ndarray:
    tp = np.zeros(len(WAYMO_SCORE_CUTOFFS), np.int64)
    for gt, det in zip(gts, dets):
        g = (gt["name"] == cls) & (gt["num_points_in_gt"] > 0)
        d = det["name"] == cls
        if not g.any() or not d.any():
            continue
        gb = torch.from_numpy(gt["gt_boxes_lidar"][g].astype(np.float64))
        db = torch.from_numpy(det["boxes_lidar"][d].astype(np.float64))
        iou = boxes_iou3d(db, gb).numpy().astype(np.float32)
        score = det["score"][d].astype(np.float32)
        for k, cutoff in enumerate(WAYMO_SCORE_CUTOFFS):
            sub = np.nonzero(score >= cutoff)[0]
            can = iou[sub] >= np.float32(thr)
            if greedy:
                taken = np.zeros(len(gb), bool)
                for i in sorted(range(len(sub)), key=lambda i: (-score[sub[i]], sub[i])):
                    cand = np.where(can[i] & ~taken, iou[sub[i]], -1.0)
                    if cand.max() >= 0:
                        taken[int(np.argmax(cand))] = True
                        tp[k] += 1
            else:
                w = np.where(can, np.floor(iou[sub] * np.float32(1e6) + np.float32(0.5)), 0)
                r, c = linear_sum_assignment(w, maximize=True)
                tp[k] += int((w[r, c] > 0).sum())
    return tp


@pytest.mark.parametrize("matcher", ["hungarian", "score_first"])
def test_component_and_subset_shortcuts_match_plain_reference(official, matcher):
    gts, dets = _annos(official, "crowded")
    gts, dets = gts[:8], dets[:8]
    curves = compute_waymo_curves(gts, dets, CLASSES, matcher=matcher)
    for cls, thr in (("Vehicle", 0.7), ("Pedestrian", 0.5), ("Cyclist", 0.5)):
        ref = _reference_tp(gts, dets, cls, thr, greedy=matcher == "score_first")
        np.testing.assert_array_equal(curves[f"{cls}/L2"]["tp"], ref, err_msg=cls)


# ------------------------------------------------------------------------------------------------
# the candidate pairs' x-sweep and the one-GT components' closed form, against plain forms
# ------------------------------------------------------------------------------------------------
def _random_objects(seed: int, frames: int, n_gt: int, n_det: int, spread: float):
    """Objects of both sides: half the predictions noisy copies of GTs (so that many pairs can
    match), the rest anywhere; some boxes huge, frames and classes mixed, equal x centres
    across groups."""
    from pcdet_atlas.evaluation.waymo_inputs import Objects

    rng = np.random.default_rng(seed)
    boxes = np.zeros((n_gt, 7), np.float32)
    boxes[:, 0] = np.round(rng.uniform(-spread, spread, n_gt), 1)  # repeated x across groups
    boxes[:, 1] = rng.uniform(-spread, spread, n_gt)
    boxes[:, 2] = rng.uniform(0, 2, n_gt)
    boxes[:, 3:6] = rng.uniform(0.3, 6.0, (n_gt, 3))
    boxes[rng.random(n_gt) < 0.02, 3] = 400.0  # a box reaching across the whole frame
    boxes[:, 6] = rng.uniform(-np.pi, np.pi, n_gt)
    frame, cls = rng.integers(0, frames, n_gt), rng.integers(0, 3, n_gt)
    gt = Objects(frame=frame, cls=cls, boxes=boxes, score=None, level=rng.integers(1, 3, n_gt))
    src = rng.integers(0, n_gt, n_det)
    det_boxes = boxes[src] + rng.normal(0, 0.15, (n_det, 7)).astype(np.float32)
    det_boxes[:, 3:6] = np.abs(det_boxes[:, 3:6]) + 0.05
    far = rng.random(n_det) < 0.5
    det_boxes[far, :2] = rng.uniform(-spread, spread, (far.sum(), 2))
    det = Objects(frame=frame[src], cls=cls[src], boxes=det_boxes,
                  score=rng.random(n_det).astype(np.float32), level=None)  # fmt: skip
    return gt, det


@pytest.mark.parametrize("seed", range(4))
def test_candidate_pairs_keep_every_pair_that_can_match(seed):
    """The x-sweep forms no pair across frames or classes and loses none whose IoU reaches the
    threshold (all same-group pairs with the exact IoU as reference), in (frame, class),
    prediction, GT input order."""
    from pcdet_atlas.evaluation import waymo_metric as wm

    gt, det = _random_objects(seed, frames=5, n_gt=150, n_det=300, spread=6.0 + 10 * seed)
    thr = np.array([0.7, 0.5, 0.5], np.float32) * (0.2 if seed % 2 else 1.0)
    pi, gi = wm._candidate_edges(gt, det, thr)
    assert (det.frame[pi] == gt.frame[gi]).all() and (det.cls[pi] == gt.cls[gi]).all()
    pos = np.empty(len(det.cls), np.int64)
    pos[np.argsort(det.frame * 64 + det.cls, kind="stable")] = np.arange(len(det.cls))
    assert (np.diff(pos[pi] * len(gt.cls) + gi) > 0).all()  # the documented order
    same = (det.frame[:, None] == gt.frame[None]) & (det.cls[:, None] == gt.cls[None])
    all_p, all_g = np.nonzero(same)
    iou = wm._waymo_iou(det.boxes[all_p], gt.boxes[all_g])
    can = iou >= thr[det.cls[all_p]]
    assert can.sum() > 50  # the input has matchable pairs to lose
    found = set(zip(pi.tolist(), gi.tolist()))
    assert all((p, g) in found for p, g in zip(all_p[can].tolist(), all_g[can].tolist()))


@pytest.mark.parametrize("matcher", ["hungarian", "score_first"])
def test_one_gt_components_equal_the_general_matching(matcher):
    """Components whose predictions all reach one GT are matched in closed form at every
    subset: the same rows as _solve_component's Hungarian or greedy matching, ties in weight
    and in score (lowest prediction index wins, as linear_sum_assignment and the greedy order),
    predictions kept by no cutoff and zero weights included."""
    from pcdet_atlas.evaluation import waymo_metric as wm
    from pcdet_atlas.evaluation.waymo_inputs import Objects

    rng = np.random.default_rng(7)
    num_comp, edges_per = 300, rng.integers(2, 7, 300)
    comp = np.repeat(np.arange(num_comp), edges_per)
    n_edges = len(comp)
    pi = rng.permutation(n_edges)  # each prediction in one edge
    weight = rng.integers(0, 4, n_edges) * 250_000  # many ties, some zero weights
    ha = rng.random(n_edges)
    is_l1 = np.repeat(rng.integers(0, 2, num_comp), edges_per)
    det_cls = np.empty(n_edges, np.int64)
    det_cls[pi] = np.repeat(rng.integers(0, 3, num_comp), edges_per)  # one class per component
    n_of_pred = rng.integers(0, 5, n_edges)  # 0: kept by no cutoff
    score = rng.integers(0, 3, n_edges).astype(np.float32) / 4  # ties in score
    det = Objects(frame=np.zeros(n_edges, np.int64), cls=det_cls, boxes=None, score=score,
                  level=None)  # fmt: skip
    edges = np.arange(n_edges)[::-1].copy()
    if matcher == "hungarian":
        fast = wm._one_gt_components(edges, comp, pi, weight, ha, is_l1, det_cls, n_of_pred)
    else:
        fast = wm._one_gt_greedy(edges, comp, pi, weight, ha, is_l1, det, n_of_pred)
    rows = []
    for c in range(num_comp):
        e = np.flatnonzero(comp == c)
        edge_data = (pi[e], np.zeros(len(e), np.int64), weight[e], np.ones(len(e), np.float32),
                     ha[e], is_l1[e])  # fmt: skip
        rows.append(wm._solve_component(det, edge_data, n_of_pred, matcher))
    slow = [np.concatenate(col) for col in zip(*rows)]
    assert len(slow[0]) == len(fast[0]) > num_comp // 2

    def as_rows(r):  # rows carry no component: compare as multisets of (cls, hi, lo, tp, ...)
        return sorted(zip(*(np.asarray(r[i]).tolist() for i in (0, 1, 5, 2, 3, 4))))

    assert as_rows(fast) == as_rows(slow)
