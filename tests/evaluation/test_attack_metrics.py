"""ASR, lenient ASR, confidence, lifecycle and robustness ranks on hand-built predictions."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.stats
import torch

from pcdet_atlas.attacks import CleanAttack, InjectionAttack, RemovalAttack
from pcdet_atlas.evaluation.analyses import (
    AttackMetricError,
    attack_success_rate,
    evaluate_attack,
    injection_confidence,
    lifecycle_asr,
    lifecycle_position,
    linear_fit,
    match_targets,
    paired_asr_differences,
    removal_confidence,
    robustness_ranks,
    run_counts,
    score_histogram,
    score_peak,
)
from pcdet_atlas.evaluation.intervals import asr_interval, wilson_cluster_interval
from pcdet_atlas.evaluation.results import format_ranks
from pcdet_atlas.ops.iou3d_nms import boxes_iou3d

TARGET = np.array([20.0, 2.0, 1.0, 4.0, 2.0, 2.0, 0.3], dtype=np.float32)


def scaled(box, dx):
    """Same centre, heading, width and height; length ``dx``: 3D IoU = min/max of the lengths."""
    out = np.array(box, dtype=np.float32).copy()
    out[3] = dx
    return out


IOU_075 = scaled(TARGET, 3.0)  # IoU 3/4
IOU_065 = scaled(TARGET, 2.6)  # IoU 2.6/4
FAR = np.array([-30.0, 5.0, 1.0, 4.0, 2.0, 2.0, 0.0], dtype=np.float32)


def anno(frame_id, boxes=(), scores=None, names=None, with_velocity=False):
    boxes = np.asarray(boxes, dtype=np.float32).reshape(-1, 7)
    if with_velocity:
        boxes = np.concatenate([boxes, np.zeros((len(boxes), 2), np.float32)], axis=1)
    n = len(boxes)
    return {
        "frame_id": frame_id,
        "name": np.array(["Vehicle"] * n if names is None else names),
        "boxes_lidar": boxes,
        "score": np.full(n, 0.9, np.float32) if scores is None else np.asarray(scores, np.float32),
    }


FAMILIES = {"injection": InjectionAttack, "removal": RemovalAttack, "clean": CleanAttack}


def info(
    target=None,
    spoofed=None,
    shadow=False,
    k=-1,
    family="injection",
    variant=None,
    run_id=0,
    sequence="seq_0",
):
    spoofed = (target is not None and not shadow) if spoofed is None else spoofed
    cls = FAMILIES.get(family)  # the attack class says how its targets are scored
    return {
        "variant": variant or ("inj_rel_easy" if family == "injection" else "rem_40"),
        "family": family,
        "sequence_name": sequence,
        "spoofed": spoofed,
        "run_id": run_id if (spoofed or shadow) else -1,
        "run_position": -1,
        "lifecycle_k": k,
        "target_box": None if target is None else np.asarray(target, np.float32),
        "target_is_shadow": shadow,
        "target_obj_id": None,
        "num_spoof_points": 0,
        "num_visible": 0,
        "num_removed": 0,
        "tracked": False,
        "fired": False,
        "success_if_detected": None if cls is None else cls.SUCCESS_IF_DETECTED,
        "confidence": None if cls is None else cls.CONFIDENCE,
        "rank_group": None if cls is None else cls.RANK_GROUP,
    }


def four_frames(family):
    """f0: IoU 0.75 match; f1: IoU 0.65 only; f2: nothing; f3: no target (predictions anyway)."""
    dets = [
        anno("s_000", [IOU_075, FAR]),
        anno("s_001", [IOU_065]),
        anno("s_002", []),
        anno("s_003", [TARGET]),
    ]
    infos = [info(TARGET, family=family)] * 3 + [info(None, family=family)]
    return dets, infos


def test_scaled_boxes_have_the_intended_iou():
    t = torch.as_tensor(TARGET[None], dtype=torch.float64)
    iou = boxes_iou3d(t, torch.as_tensor(np.stack([IOU_075, IOU_065]), dtype=torch.float64))
    np.testing.assert_allclose(iou.numpy(), [[0.75, 0.65]], atol=1e-9)


def test_injection_asr_counts_exactly():
    dets, infos = four_frames("injection")
    out = attack_success_rate(dets, infos)
    assert out["num_targets"] == 3  # the frame without target is ignored
    assert out["num_success"] == 1  # only the 0.75 match
    assert out["asr"] == pytest.approx(1 / 3)
    assert out["num_success_lenient"] == 2  # 0.65 overlaps
    assert out["asr_lenient"] == pytest.approx(2 / 3)
    assert out["iou_threshold"] == 0.7 and out["target_class"] == "Vehicle"


def test_spoofed_frames_without_a_target_are_counted_apart():
    """A phantom absent from the scan (or a removal target lost) records no target: it is
    neither a success nor a failure, and is reported as untargeted."""
    dets, infos = four_frames("injection")
    dets.append(anno("e", [TARGET], scores=[0.9]))
    infos.append({**info(None, spoofed=True), "frame_id": "e"})  # phantom fully occluded
    out = attack_success_rate(dets, infos)
    assert out["num_targets"] == 3 and out["num_success"] == 1  # as without frame e
    assert out["num_spoofed_frames"] == 4 and out["num_untargeted"] == 1


def test_removal_asr_is_the_inverse():
    dets, infos = four_frames("removal")
    out = attack_success_rate(dets, infos)
    assert out["num_targets"] == 3
    assert out["num_success"] == 2  # 0.65 and nothing: the target is missed at IoU 0.7
    assert out["num_success_lenient"] == 1  # MVP: only a frame without any overlap
    assert out["asr"] == pytest.approx(2 / 3) and out["asr_lenient"] == pytest.approx(1 / 3)


def test_match_records_iou_and_scores():
    dets = [anno("a", [IOU_065, IOU_075, FAR], scores=[0.95, 0.4, 0.99])]
    m = match_targets(dets, [info(TARGET)])
    assert len(m) == 1
    np.testing.assert_allclose(m.max_iou, [0.75], atol=1e-6)
    # matched: the best score at IoU >= 0.7 (0.4), not the higher one at 0.65 or far away
    np.testing.assert_allclose(m.matched_score, [0.4], atol=1e-6)
    np.testing.assert_allclose(m.overlap_score, [0.95], atol=1e-6)
    assert m.frame_id.tolist() == ["a"] and m.success.tolist() == [True]


def test_class_handling():
    dets = [anno("a", [TARGET], names=["Pedestrian"]), anno("b", [TARGET], names=["Vehicle"])]
    infos = [info(TARGET), info(TARGET)]
    assert attack_success_rate(dets, infos)["num_success"] == 1
    assert attack_success_rate(dets, infos, target_class=None)["num_success"] == 2
    assert attack_success_rate(dets, infos, target_class="Pedestrian")["num_success"] == 1


def test_score_threshold():
    dets = [anno("a", [TARGET], scores=[0.3]), anno("b", [TARGET], scores=[0.6])]
    infos = [info(TARGET), info(TARGET)]
    assert attack_success_rate(dets, infos)["num_success"] == 2
    out = attack_success_rate(dets, infos, score_threshold=0.5)
    assert out["num_success"] == 1 and out["score_threshold"] == 0.5


def test_empty_predictions_and_no_targets():
    empty = {"name": np.zeros(0, dtype="<U7"), "boxes_lidar": np.zeros((0, 9)), "score": []}
    out = attack_success_rate([empty, anno("b")], [info(TARGET), info(TARGET)])
    assert out["num_targets"] == 2 and out["num_success"] == 0 and out["asr"] == 0.0
    removal = attack_success_rate([empty], [info(TARGET, family="removal")])
    assert removal["asr"] == 1.0 and removal["asr_lenient"] == 1.0
    clean = [info(None, family="clean", variant="clean")] * 2
    out = attack_success_rate([anno("a", [TARGET]), empty], clean)
    assert out["num_targets"] == 0 and out["asr"] is None and out["asr_lenient"] is None


def test_nine_column_boxes_and_attack_key():
    dets = [anno("a", [TARGET], with_velocity=True)]
    dets[0]["attack"] = info(TARGET)
    assert attack_success_rate(dets)["num_success"] == 1


def test_rotated_boxes_use_exact_iou():
    flipped = TARGET.copy()
    flipped[6] += math.pi  # the same box
    turned = TARGET.copy()
    turned[6] += math.pi / 2  # 4x2 crossing 4x2: IoU = 4 / (16 - 4)
    m = match_targets([anno("a", [flipped]), anno("b", [turned])], [info(TARGET)] * 2)
    np.testing.assert_allclose(m.max_iou, [1.0, 1 / 3], atol=1e-6)
    assert m.success.tolist() == [True, False]


def test_prefilter_agrees_with_brute_force():
    rng = np.random.default_rng(0)
    n = 200
    boxes = np.column_stack(
        [
            rng.uniform(15, 25, n),
            rng.uniform(-3, 7, n),
            rng.uniform(-1, 3, n),
            rng.uniform(0.5, 12, n),
            rng.uniform(0.5, 6, n),
            rng.uniform(0.5, 4, n),
            rng.uniform(-np.pi, np.pi, n),
        ]
    ).astype(np.float32)
    m = match_targets([anno("a", boxes)], [info(TARGET)])
    brute = boxes_iou3d(
        torch.as_tensor(TARGET[None], dtype=torch.float64),
        torch.as_tensor(boxes, dtype=torch.float64),
    ).max()
    assert brute > 0
    assert m.max_iou[0] == pytest.approx(float(brute), abs=1e-12)


def test_shadow_targets_are_not_counted_by_asr():
    dets = [anno("a", [TARGET]), anno("b", [TARGET]), anno("c", [])]
    infos = [info(TARGET, shadow=True, k=0), info(TARGET, k=1), info(TARGET, k=2)]
    m = match_targets(dets, infos)
    assert len(m) == 3 and m.is_shadow.tolist() == [True, False, False]
    out = attack_success_rate(dets, infos)
    assert out["num_targets"] == 2 and out["num_success"] == 1


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda d, i: d.pop(), "differ"),
        (lambda d, i: d[0].update(frame_id="zzz") or i[0].update(frame_id="s_000"), "aligned"),
        (lambda d, i: i.__setitem__(0, {**i[0], "target_is_shadow": True}), "both True"),
        (lambda d, i: i.__setitem__(1, {**i[1], "variant": "inj_rel_hard"}), "one variant"),
        (lambda d, i: d[0].update(boxes_lidar=np.zeros((2, 6))), "boxes_lidar"),
        (lambda d, i: d[0].update(score=np.zeros(5)), "lengths differ"),
        (lambda d, i: d[1].pop("score"), "'score'"),
        (
            lambda d, i: d[1].update(score=np.full(len(d[1]["score"]), 3.2)),
            r"frame 1 .*'score' must be in \[0, 1\] .*got \[3\.2",
        ),
        (lambda d, i: i.__setitem__(0, {**i[0], "target_box": np.zeros(5)}), "target_box"),
        (lambda d, i: i.__setitem__(3, {**i[3], "target_box": TARGET}), "neither spoofed"),
        (
            lambda d, i: i.__setitem__(2, {k: v for k, v in i[2].items() if k != "lifecycle_k"}),
            "lifecycle_k",
        ),
        (
            lambda d, i: i.__setitem__(1, {k: v for k, v in i[1].items() if k != "family"}),
            "frame 1: attack metadata lacks key 'family'",
        ),
        # a target frame without its run would merge with other runs into one interval cluster
        (
            lambda d, i: i.__setitem__(1, {k: v for k, v in i[1].items() if k != "run_id"}),
            r"frame 1 \(s_001\): a target frame needs a 'run_id' >= 0, got None",
        ),
        (lambda d, i: i.__setitem__(2, {**i[2], "run_id": -1}), r"frame 2 .*'run_id' >= 0, got -1"),
        (
            lambda d, i: i.__setitem__(0, {**i[0], "sequence_name": None}),
            r"frame 0 \(s_000\): a target frame needs its 'sequence_name'",
        ),
        (
            lambda d, i: i.__setitem__(0, {k: v for k, v in i[0].items() if k != "sequence_name"}),
            "frame 0 .*'sequence_name'",
        ),
        (
            lambda d, i: i.__setitem__(
                0, {**i[0], "sequence_name": "", "target_is_shadow": True, "spoofed": False}
            ),
            "frame 0 .*'sequence_name'",
        ),
    ],
)
def test_bad_input_raises_naming_the_problem(mutate, match):
    dets, infos = four_frames("injection")
    infos = list(infos)
    mutate(dets, infos)
    with pytest.raises(AttackMetricError, match=match):
        match_targets(dets, infos)


def test_a_family_without_a_success_rule_cannot_record_targets():
    infos = [info(TARGET, family="laser_blind", variant="blind_1")]
    with pytest.raises(AttackMetricError, match="laser_blind.*no success_if_detected"):
        match_targets([anno("a")], infos)
    out = attack_success_rate([anno("a")], infos, success_if_detected=False)
    assert out["num_targets"] == 1 and out["num_success"] == 1
    # the rule comes from the metadata: the same family scored the other way
    flipped = [{**infos[0], "success_if_detected": True}]
    assert attack_success_rate([anno("a")], flipped)["num_success"] == 0


def test_one_call_takes_one_scoring_rule():
    infos = [info(TARGET), {**info(TARGET), "success_if_detected": False}]
    with pytest.raises(AttackMetricError, match="success_if_detected"):
        match_targets([anno("a"), anno("b")], infos)


# ---------------------------------------------------------------------------- confidence
def test_score_histogram_and_peak():
    h = score_histogram(np.array([0.0, 0.05, 0.7, 1.0]))
    assert len(h["bin_edges"]) == 21 and h["bin_edges"][1] == 0.05
    assert h["counts"][0] == 1 and h["counts"][1] == 1 and h["counts"][14] == 1
    assert h["counts"][19] == 1 and sum(h["counts"]) == 4  # 1.0 in the last (closed) bin
    with pytest.raises(AttackMetricError, match="in \\[0, 1\\]"):
        score_histogram(np.array([1.2]))


def test_score_peak_at_the_papers_resolution():
    assert score_peak(np.array([0.12, 0.13, 0.14, 0.9])) == pytest.approx(0.13)
    # no spread: the value itself, on the 0.001 grid
    assert score_peak(np.array([0.4])) == 0.4 and score_peak(np.array([0.5, 0.5])) == 0.5
    assert score_peak(np.zeros(0)) is None
    # a peak between the 0.05 histogram bins' centres is found to within the estimate's error
    g = np.random.default_rng(0)
    peak = score_peak(np.clip(g.normal(0.637, 0.02, 4000), 0, 1))
    assert abs(peak - 0.637) < 0.01 and peak not in (0.625, 0.675)  # not a bin centre
    assert peak == round(peak, 3)
    # two equal modes: the lower one
    assert score_peak(np.array([0.2, 0.2, 0.8, 0.8])) < 0.5


def test_injection_confidence():
    dets = [
        anno("a", [TARGET], scores=[0.9]),
        anno("b", [IOU_075], scores=[0.8]),
        anno("c", [TARGET], scores=[0.7]),  # exactly 0.7 is not "> 0.7"
        anno("d", [IOU_065], scores=[0.99]),  # not detected: no score
    ]
    c = injection_confidence(match_targets(dets, [info(TARGET)] * 4))
    assert c["num_targets"] == 4 and c["num_detected"] == 3 and c["num_above"] == 2
    assert c["fraction_above"] == pytest.approx(2 / 3)
    assert c["mean_score"] == pytest.approx(0.8, abs=1e-6)
    counts = c["histogram"]["counts"]
    assert counts[18] == 1 and counts[16] == 1 and counts[14] == 1 and sum(counts) == 3


def test_removal_confidence_against_clean_run():
    attacked = [
        anno("f0", [TARGET], scores=[0.30]),
        anno("f1", [IOU_075], scores=[0.35]),
        anno("f2", []),  # hidden: removal success, no score
        anno("f3", [TARGET], scores=[0.40]),
    ]
    clean = [  # any order: aligned by frame_id
        anno("f3", [FAR], scores=[0.9]),  # the clean model misses f3's target too
        anno("f2", [TARGET], scores=[0.95]),
        anno("f1", [TARGET], scores=[0.92]),
        anno("f0", [TARGET, IOU_075], scores=[0.90, 0.5]),
    ]
    m = match_targets(attacked, [info(TARGET, family="removal")] * 4)
    c = removal_confidence(m, clean)
    assert c["num_targets"] == 4 and c["num_surviving"] == 3
    assert c["num_paired"] == 2 and c["num_clean_missed"] == 1
    assert c["num_above"] == 0 and c["fraction_above"] == 0.0
    assert c["mean_score_drop"] == pytest.approx((0.60 + 0.57) / 2, abs=1e-6)
    assert c["clean_peak"] == pytest.approx(0.90)  # two equal modes 0.90 | 0.92: the lower
    assert c["attacked_peak"] == pytest.approx(0.30)
    assert c["peak_gap"] == pytest.approx(0.6)
    assert sum(c["histogram"]["counts"]) == 3
    assert sum(c["paired_clean_histogram"]["counts"]) == 2
    with pytest.raises(AttackMetricError, match="'f1'"):
        removal_confidence(m, [a for a in clean if a["frame_id"] != "f1"])


# ---------------------------------------------------------------------------- lifecycle
def lifecycle_run(success_by_k, window, family="injection", run_id=0):
    """One run's lifecycle frames: k = 0..2W, the target detected where ``success_by_k`` says so
    (for injection success = detected; for removal success = missed)."""
    dets, infos = [], []
    for k, ok in enumerate(success_by_k):
        detected = ok if family == "injection" else not ok
        dets.append(anno(f"r{run_id}_{k:03d}", [TARGET] if detected else []))
        shadow = not (1 <= k <= window)
        infos.append(info(TARGET, shadow=shadow, k=k, family=family, run_id=run_id))
    return dets, infos


@pytest.mark.parametrize("family", ["injection", "removal"])
def test_lifecycle_counts_and_asr(family):
    w = 4
    d0, i0 = lifecycle_run([0, 1, 1, 1, 1, 0, 0, 0, 0], w, family, run_id=0)
    d1, i1 = lifecycle_run([0, 0, 1, 1, 1, 1, 0, 0, 0], w, family, run_id=1)
    # a frame without a target is ignored
    d2, i2 = [anno("y", [TARGET])], [info(None, family=family)]
    m = match_targets(d0 + d1 + d2, i0 + i1 + i2)
    lc = lifecycle_asr(m, w, recorded_window=w)
    assert lc["k"] == list(range(9))
    assert lc["attacked"] == [False, True, True, True, True, False, False, False, False]
    assert lc["num_targets"] == [2] * 9
    assert lc["num_success"] == [0, 1, 2, 2, 2, 1, 0, 0, 0]
    assert lc["asr"] == [0.0, 0.5, 1.0, 1.0, 1.0, 0.5, 0.0, 0.0, 0.0]
    assert len(lc["score_counts"]) == 9 and len(lc["score_counts"][0]) == 20
    detected = (
        np.array(lc["num_success"]) if family == "injection" else 2 - np.array(lc["num_success"])
    )
    assert [sum(c) for c in lc["score_counts"]] == detected.tolist()


@pytest.mark.parametrize("family", ["injection", "removal"])
def test_lifecycle_clean_baseline_counts_the_clean_scores_of_the_same_targets(family):
    w = 2
    dets, infos = lifecycle_run([0, 1, 1, 0, 0], w, family)
    # the clean run sees the target at k = 0, 1, 3 (score 0.93), not at k = 2, 4; a phantom
    # far away never matches
    seen = (0, 1, 3)
    clean = [anno(d["frame_id"], [TARGET] * (k in seen), scores=[0.93] * (k in seen))
             for k, d in enumerate(dets)]  # fmt: skip
    clean[4] = anno(dets[4]["frame_id"], [TARGET + np.array([30, 0, 0, 0, 0, 0, 0], np.float32)])
    out = evaluate_attack(dets, infos, clean_det_annos=clean, window=w, recorded_window=w)
    lc = out["lifecycle"]
    assert [sum(c) for c in lc["clean_score_counts"]] == [1, 1, 0, 1, 0]
    assert lc["clean_score_counts"][0][18] == 1  # 0.93 in the bin [0.90, 0.95)
    assert evaluate_attack(dets, infos, window=w, recorded_window=w)["lifecycle"][
        "clean_score_counts"] is None  # fmt: skip
    m = match_targets(dets, infos)
    with pytest.raises(AttackMetricError, match="clean_scores has 2 entries for 5 targets"):
        lifecycle_asr(m, w, recorded_window=w, clean_scores=np.zeros(2))


def test_lifecycle_default_is_the_schedule_window():
    # the engine's default: W = 32 spoofed frames, 32 shadow frames after; a 4-frame detector
    ks = list(range(0, 65))
    dets, infos = lifecycle_run([k % 2 for k in ks], 32)
    lc = lifecycle_asr(match_targets(dets, infos), 4)
    assert lc["recorded_window"] == 32 and lc["num_targets"] == [1] * 9
    # positions 1..4 = k 1..4, positions 5..8 = k 33..36
    assert lc["num_success"] == [0, 1, 0, 1, 0, 1, 0, 1, 0]


def test_lifecycle_shorter_detector_window():
    # engine recorded We = 4; a 2-frame detector sees k = 0, spoofed 1..2, after-run 1..2
    k = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8])
    shadow = np.array([1, 0, 0, 0, 0, 1, 1, 1, 1], dtype=bool)
    pos = lifecycle_position(k, shadow, window=2, recorded_window=4)
    assert pos.tolist() == [0, 1, 2, -1, -1, 3, 4, -1, -1]
    assert lifecycle_position(k, shadow, 4, 4).tolist() == [0, 1, 2, 3, 4, 5, 6, 7, 8]
    with pytest.raises(AttackMetricError, match="recorded_window=2"):
        lifecycle_position(k, shadow, window=2, recorded_window=2)  # spoofed k = 3 contradicts
    # a spoofed target outside any lifecycle (make_meta's default -1: never set) would count in
    # the ASR and vanish from the lifecycle
    with pytest.raises(AttackMetricError, match=r"lifecycle_k \[-1\]"):
        lifecycle_position(np.append(k, -1), np.append(shadow, False), 2, 4)
    with pytest.raises(AttackMetricError, match="window"):
        lifecycle_position(k, shadow, window=5, recorded_window=4)


def test_evaluate_attack_bundles_everything():
    dets, infos = lifecycle_run([0, 1, 1, 1, 1, 0, 0, 0, 0], 4)
    out = evaluate_attack(dets, infos, window=4, recorded_window=4)
    assert out["variant"] == "inj_rel_easy" and out["num_frames"] == 9
    assert out["num_targets"] == 4 and out["asr"] == 1.0
    assert out["confidence"]["kind"] == "injection" and out["confidence"]["num_detected"] == 4
    assert out["lifecycle"]["asr"][5] == 0.0
    rem_d, rem_i = lifecycle_run([0, 1, 0, 1, 1, 0, 0, 0, 0], 4, family="removal")
    out = evaluate_attack(
        rem_d, rem_i, clean_det_annos=[anno(a["frame_id"], [TARGET]) for a in rem_d]
    )
    assert out["asr"] == 0.75 and out["confidence"]["num_surviving"] == 1
    assert out["lifecycle"] is None
    assert evaluate_attack(rem_d, rem_i)["confidence"] is None  # no clean run given


# ---------------------------------------------------------------------------- ranks
def test_robustness_ranks_known_answer():
    asr = {
        "A": {"i1": 0.1, "i2": 0.1, "r1": 0.9, "r2": 0.8, "clean": None},
        "B": {"i1": 0.2, "i2": 0.1, "r1": 0.5, "r2": 0.8, "clean": None},
        "C": {"i1": 0.3, "i2": 0.5, "r1": 0.1, "r2": 0.2, "clean": None},
    }
    fam = {"i1": "injection", "i2": "injection", "r1": "removal", "r2": "removal", "clean": None}
    out = robustness_ranks(asr, fam)
    assert out["per_setting"]["i2"] == {"A": 1.5, "B": 1.5, "C": 3.0}  # ties share the mean
    assert out["group_ranks"]["injection"] == {"A": 1.25, "B": 1.75, "C": 3.0}
    assert out["group_ranks"]["removal"] == {"A": 2.75, "B": 2.25, "C": 1.0}
    assert "clean" not in out["per_setting"] and out["fit_axes"] == ["injection", "removal"]
    # removal = 4 - injection exactly
    assert out["fit"]["slope"] == pytest.approx(-1.0)
    assert out["fit"]["intercept"] == pytest.approx(4.0)
    assert out["fit"]["r2"] == pytest.approx(1.0)
    low = robustness_ranks(asr, fam, tie_method="min")
    assert low["per_setting"]["i2"] == {"A": 1.0, "B": 1.0, "C": 3.0}
    two = robustness_ranks({m: asr[m] for m in "AB"}, fam)
    assert two["fit"] is None  # two points always fit exactly
    tied = {m: {**asr[m], "i1": 0.2, "i2": 0.2} for m in asr}  # one injection rank for all
    flat = robustness_ranks(tied, fam)
    assert flat["fit"] is None
    assert "every model has the same injection rank" in format_ranks(flat)
    with pytest.raises(AttackMetricError, match="'C'.*'r2'"):
        robustness_ranks({**asr, "C": {"i1": 0.3, "i2": 0.5, "r1": 0.1}}, fam)


def test_linear_fit_reproduces_the_paper_figure():
    # coordinates of the paper's Fig. "Robustness Correlation" (injection rank, removal rank)
    inj = [1.667, 3.500, 4.667, 2.333, 3.500, 5.500, 7.167, 9.000, 7.667]
    rem = [8.667, 7.333, 6.000, 7.500, 5.333, 3.500, 3.167, 2.333, 1.167]
    fit = linear_fit(np.array(inj), np.array(rem))
    assert fit["slope"] == pytest.approx(-0.9596, abs=1e-4)
    assert fit["intercept"] == pytest.approx(9.7980, abs=1e-4)
    assert fit["r2"] == pytest.approx(0.87, abs=5e-3)  # the paper's R^2 = 0.87
    with pytest.raises(AttackMetricError, match="varying x"):
        linear_fit(np.ones(3), np.arange(3.0))


def test_iou_fn_can_be_swapped_for_bev():
    from pcdet_atlas.ops.iou3d_nms import boxes_aligned_iou_bev

    lifted = TARGET.copy()
    lifted[2] += 1.0  # same footprint, half the height overlapping: 3D IoU 1/3, BEV IoU 1
    dets, infos = [anno("a", [lifted])], [info(TARGET)]
    np.testing.assert_allclose(match_targets(dets, infos).max_iou, [1 / 3], atol=1e-6)
    bev = match_targets(dets, infos, iou_fn=boxes_aligned_iou_bev)
    assert bev.max_iou[0] == pytest.approx(1.0) and bev.success.tolist() == [True]


def test_accepts_the_attack_engine_metadata_records():
    from pcdet_atlas.attacks.metadata import make_meta, validate_meta

    rem = dict(success_if_detected=False, confidence="removal", rank_group="removal")
    rem["sequence_name"] = "seq_0"  # AtlasWaymoDataset adds the sequence to the engine's record
    infos = [
        make_meta("rem_40", "removal", lifecycle_k=0, run_id=0, target_box=TARGET,
                  target_is_shadow=True, tracked=True, **rem),
        make_meta("rem_40", "removal", spoofed=True, run_id=0, run_position=0, lifecycle_k=1,
                  target_box=TARGET, tracked=True, fired=True, **rem),
        make_meta("rem_40", "removal", spoofed=True, run_id=0, run_position=1, lifecycle_k=2,
                  **rem),
        make_meta("rem_40", "removal", **rem),
    ]  # fmt: skip
    with pytest.raises(ValueError, match="needs success_if_detected"):
        validate_meta(make_meta("rem_40", "removal", spoofed=True, run_id=0, run_position=0,
                                target_box=TARGET))  # fmt: skip
    for meta in infos:
        validate_meta(meta)
    dets = [anno("a", [TARGET]), anno("b", [IOU_065]), anno("c", []), anno("d", [])]
    m = match_targets(dets, infos)
    assert m.lifecycle_k.tolist() == [0, 1] and m.is_shadow.tolist() == [True, False]
    out = attack_success_rate(dets, infos)
    assert out["num_targets"] == 1 and out["num_success"] == 1  # lost-target frame not counted


# ------------------------------------------------------------------- the ASR interval
#: Targets and successes of 12 runs with unequal rates: the interval depends on the draws.
RUN_TARGETS = (3, 5, 4, 6, 2, 5, 7, 3, 4, 6, 5, 4)
RUN_HITS = (0, 5, 1, 6, 2, 0, 3, 3, 1, 2, 5, 4)


def spoof_runs(sequence="seq_0", variant="inj_rel_easy", runs=range(12)):
    """Injection targets of the given runs of one sequence (run r: ``RUN_HITS[r]`` of
    ``RUN_TARGETS[r]`` phantoms detected); -> dets, infos, successes (T,) bool."""
    dets, infos, success = [], [], []
    for run in runs:
        for j in range(RUN_TARGETS[run]):
            fid, hit = f"{sequence}_r{run}_{j}", j < RUN_HITS[run]
            dets.append(anno(fid, [TARGET] if hit else []))
            infos.append({**info(TARGET, run_id=run, variant=variant, sequence=sequence),
                          "frame_id": fid})  # fmt: skip
            success.append(hit)
    return dets, infos, np.array(success)


def test_asr_ci_is_the_asr_interval_of_the_per_run_counts():
    """``asr_ci`` is :func:`asr_interval` of the variant's own ``runs``: closed-form, so the
    same every call and for any variant name; it holds the ASR."""
    dets, infos, _ = spoof_runs()
    a, b = attack_success_rate(dets, infos), attack_success_rate(dets, infos)
    assert a["num_runs"] == 12 and a["asr_ci"] == b["asr_ci"]  # reproducible
    assert a["asr_ci"] == list(asr_interval(a["runs"]))
    assert a["asr_ci"][0] <= a["asr"] <= a["asr_ci"][1]
    other = attack_success_rate(dets, [{**i, "variant": "inj_rel_hard"} for i in infos])
    assert other["asr"] == a["asr"] and other["asr_ci"] == a["asr_ci"]


def test_a_run_is_its_sequence_and_run_id():
    """Run ids are numbered per sequence: runs 0-5 of two sequences are 12 runs (ordered by
    sequence and run id) in 2 sequences, the interval's clusters, whatever order the frames
    come in; a target frame without its sequence is refused rather than merged into another
    run."""
    d_a, i_a, _ = spoof_runs("seq_a", runs=range(6))
    d_b, i_b, _ = spoof_runs("seq_b", runs=range(6, 12))
    i_b = [{**i, "run_id": i["run_id"] - 6} for i in i_b]  # seq_b's runs are 0-5 too
    dets, infos = d_a + d_b, i_a + i_b
    out = attack_success_rate(dets, infos)
    assert out["num_runs"] == 12 and out["num_targets"] == sum(RUN_TARGETS)
    hits = [sum(RUN_HITS[:6]), sum(RUN_HITS[6:])]
    targets = [sum(RUN_TARGETS[:6]), sum(RUN_TARGETS[6:])]
    want = wilson_cluster_interval(np.array(hits), np.array(targets))  # the two sequences
    assert out["asr_ci"] == pytest.approx([float(want[0]), float(want[1])], abs=1e-15)
    order = np.random.default_rng(0).permutation(len(dets))
    shuffled = attack_success_rate([dets[i] for i in order], [infos[i] for i in order])
    assert shuffled["num_runs"] == 12 and shuffled["asr_ci"] == out["asr_ci"]
    with pytest.raises(AttackMetricError, match=r"frame 0 \(seq_a_r0_0\).*'sequence_name'"):
        attack_success_rate(dets, [{**i, "sequence_name": None} for i in infos])


def test_run_counts_per_sequence_and_run():
    """One entry per (sequence, run), sorted, with its targets and successes; shadow targets
    are not counted; the totals are the variant's."""
    d_a, i_a, _ = spoof_runs("seq_b", runs=range(6))
    d_b, i_b, _ = spoof_runs("seq_a", runs=range(6, 12))
    i_b = [{**i, "run_id": i["run_id"] - 6} for i in i_b]
    shadow = {**i_a[0], "spoofed": False, "target_is_shadow": True, "lifecycle_k": 0,
              "frame_id": "shadow"}  # fmt: skip
    dets, infos = d_a + d_b + [anno("shadow", [TARGET])], i_a + i_b + [shadow]
    out = attack_success_rate(dets, infos)
    runs = out["runs"]
    assert [(r["sequence"], r["run_id"]) for r in runs] == [
        *(("seq_a", r) for r in range(6)), *(("seq_b", r) for r in range(6))]  # fmt: skip
    assert [r["num_targets"] for r in runs] == [*RUN_TARGETS[6:], *RUN_TARGETS[:6]]
    assert [r["num_success"] for r in runs] == [*RUN_HITS[6:], *RUN_HITS[:6]]
    assert sum(r["num_targets"] for r in runs) == out["num_targets"] == sum(RUN_TARGETS)
    assert sum(r["num_success_lenient"] for r in runs) == out["num_success_lenient"]
    assert run_counts(match_targets([anno("shadow", [])], [shadow])) == []


def _runs(hits, targets, sequence="seq_0"):
    return [{"sequence": sequence, "run_id": i, "num_targets": t, "num_success": h,
             "num_success_lenient": h} for i, (h, t) in enumerate(zip(hits, targets))]  # fmt: skip


def test_paired_differences_against_a_hand_computed_interval():
    """Two variants over the same six runs in three sequences: per sequence, the contribution of
    its runs to the difference of the mean ASRs; the interval is the difference -/+ t(2 df) x
    the cluster-robust standard error, the same sequences for both models and variants, kept
    within [-1, 1]."""
    targets = {"inj_a": [4, 2, 6, 3, 5, 4], "inj_b": [3, 3, 5, 4, 4, 5]}
    hits = {"A": {"inj_a": [4, 0, 3, 2, 5, 3], "inj_b": [3, 1, 5, 4, 4, 2]},
            "B": {"inj_a": [2, 0, 1, 1, 4, 1], "inj_b": [1, 0, 5, 2, 3, 2]}}  # fmt: skip
    seqs = ["s0", "s0", "s1", "s1", "s2", "s2"]
    runs = {m: {v: [{**r, "sequence": q} for r, q in zip(_runs(hits[m][v], t), seqs)]
                for v, t in targets.items()} for m in hits}  # fmt: skip
    out = paired_asr_differences(runs)
    rate = {(m, v): sum(hits[m][v]) / sum(t) for m in hits for v, t in targets.items()}
    diff = (sum(rate["A", v] for v in targets) - sum(rate["B", v] for v in targets)) / 2
    u = np.zeros(3)  # per sequence
    for v, t in targets.items():
        d = rate["A", v] - rate["B", v]
        for j, q in enumerate(seqs):
            u[int(q[1])] += (hits["A"][v][j] - hits["B"][v][j] - d * t[j]) / sum(t) / 2
    half = scipy.stats.t.ppf(0.975, 2) * math.sqrt(3 / 2 * (u**2).sum())
    assert -1 < diff - half and diff + half < 1  # not clipped
    assert out["difference"]["A"]["B"] == pytest.approx(diff)
    assert out["ci"]["A"]["B"] == pytest.approx([diff - half, diff + half], abs=1e-12)
    assert out["ci"]["B"]["A"] == pytest.approx([-diff - half, -diff + half], abs=1e-12)
    assert out["mean_asr"]["A"] == pytest.approx((17 / 24 + 19 / 24) / 2)
    assert out["num_runs"] == {"inj_a": 6, "inj_b": 6}
    assert out["num_clusters"] == 3 and out["cluster"] == "sequence"
    assert out["models"] == ["A", "B"]
    two = {m: {v: [{**r, "sequence": q[:2].replace("2", "1")} for r, q in zip(x, seqs)]
               for v, x in by_v.items()} for m, by_v in runs.items()}  # fmt: skip
    lo, hi = paired_asr_differences(two)["ci"]["A"]["B"]  # 2 sequences: t with 1 df
    assert -1.0 <= lo and hi <= 1.0


def test_paired_interval_is_the_t_interval_of_per_sequence_differences():
    """One variant, equal runs per sequence: the interval is the textbook paired t interval of
    the per-sequence ASR differences (S - 1 degrees of freedom)."""
    rng = np.random.default_rng(2)
    a, b = rng.integers(0, 33, 18).tolist(), rng.integers(0, 33, 18).tolist()
    seqs = [f"seq_{i // 3}" for i in range(18)]

    def runs_of(h):
        return [{**r, "sequence": q} for r, q in zip(_runs(h, [32] * 18), seqs)]

    out = paired_asr_differences({"A": {"rem": runs_of(a)}, "B": {"rem": runs_of(b)}})
    d = (np.array(a) - np.array(b)).reshape(6, 3).sum(1) / 96  # (6,) per sequence
    half = scipy.stats.t.ppf(0.975, 5) * d.std(ddof=1) / math.sqrt(6)
    assert out["ci"]["A"]["B"] == pytest.approx([d.mean() - half, d.mean() + half], abs=1e-12)
    assert out["num_clusters"] == 6


def test_variants_that_share_runs_are_clustered_together():
    """The variants of a family share their runs (the same target, another budget): a variant
    repeated adds no information, so its interval is the one variant's, not narrower; variants
    with runs of their own are clustered over the union of the sequences."""
    rng = np.random.default_rng(1)
    targets = [32] * 12
    a, b = rng.integers(0, 33, 12).tolist(), rng.integers(0, 33, 12).tolist()
    one = {"A": {"rem_10": _runs(a, targets)}, "B": {"rem_10": _runs(b, targets)}}
    two = {m: {"rem_10": v["rem_10"], "rem_40": v["rem_10"]} for m, v in one.items()}
    single = paired_asr_differences(one)
    double = paired_asr_differences(two)
    assert double["ci"]["A"]["B"] == pytest.approx(single["ci"]["A"]["B"], abs=1e-15)
    assert double["difference"]["A"]["B"] == pytest.approx(single["difference"]["A"]["B"])
    assert single["cluster"] == "run" and single["num_clusters"] == 12  # one sequence
    other = {"A": {**one["A"], "inj": _runs(a[:3], [32] * 3, "seq_9")},
             "B": {**one["B"], "inj": _runs(b[:3], [32] * 3, "seq_9")}}  # fmt: skip
    union = paired_asr_differences(other)
    assert union["num_clusters"] == 2 and union["cluster"] == "sequence"
    assert union["num_runs"] == {"rem_10": 12, "inj": 3}
    lo, hi = union["ci"]["A"]["B"]
    assert lo <= union["difference"]["A"]["B"] <= hi


def test_pairing_runs_narrows_the_interval():
    """Runs that are hard or easy for every model: the paired difference is settled (interval
    away from 0) where the two models' own intervals overlap."""
    rng = np.random.default_rng(0)
    difficulty = rng.uniform(0.0, 1.0, 18)
    targets = [32] * 18
    a = np.round(32 * np.clip(difficulty + 0.1, 0, 1)).astype(int).tolist()
    b = np.round(32 * difficulty).astype(int).tolist()
    seqs = [f"seq_{i // 3}" for i in range(18)]
    runs = {m: {"inj": [{**r, "sequence": q} for r, q in zip(_runs(x, targets), seqs)]}
            for m, x in (("A", a), ("B", b))}  # fmt: skip
    out = paired_asr_differences(runs)
    lo, hi = out["ci"]["A"]["B"]
    assert 0 < lo <= out["difference"]["A"]["B"] <= hi
    own = [asr_interval(runs[m]["inj"]) for m in "AB"]
    assert own[0][0] < own[1][1]  # the separate intervals overlap
    assert hi - lo < 0.5 * (own[0][1] - own[0][0])


def test_paired_differences_refuse_unpaired_inputs():
    one = {"inj": _runs([1, 2], [3, 3])}
    with pytest.raises(AttackMetricError, match="at least 2 models"):
        paired_asr_differences({"A": one})
    with pytest.raises(AttackMetricError, match="different variants"):
        paired_asr_differences({"A": one, "B": {"rem": one["inj"]}})
    twice = {"inj": _runs([1, 2], [3, 3]) * 2}
    with pytest.raises(AttackMetricError, match=r"variant 'inj': run \('seq_0', 0\) twice"):
        paired_asr_differences({"A": twice, "B": twice})
    other = {"inj": _runs([1, 2], [3, 4])}
    with pytest.raises(AttackMetricError, match=r"'inj'.*'A' and 'B'.*not scored on the same"):
        paired_asr_differences({"A": one, "B": other})
    single = paired_asr_differences({"A": {"inj": _runs([1], [3])}, "B": {"inj": _runs([2], [3])}})
    assert single["ci"] is None and single["difference"]["B"]["A"] == pytest.approx(1 / 3)


# ---------------------------------------------------------------------------- attributable ASR
def test_attributable_asr_leaves_out_what_the_clean_run_already_gives():
    """Injection: a phantom on a box the clean model detects anyway is confounded; removal: a
    target the clean model misses too. The rest is the attributable ASR, with its runs."""
    from pcdet_atlas.evaluation.analyses.attributable_analysis import attributable_asr

    attacked = [anno("f0", [TARGET]), anno("f1", [TARGET]), anno("f2", []), anno("f3", [])]
    clean = [anno("f3", []), anno("f2", [FAR]), anno("f1", []), anno("f0", [IOU_075])]
    infos = [{**info(TARGET, run_id=r), "frame_id": f"f{i}"} for i, r in enumerate((0, 0, 1, 1))]
    m = match_targets(attacked, infos)
    a = attributable_asr(m, clean)
    # f0's phantom lies on a box the clean model detects (IoU 0.75): confounded, and a success
    assert (a["num_confounded"], a["num_confounded_success"]) == (1, 1)
    assert (a["num_targets"], a["num_success"], a["asr"]) == (3, 1, pytest.approx(1 / 3))
    assert a["num_runs"] == 2 and a["asr_ci"] == list(asr_interval(run_counts(m.select(
        np.array([False, True, True, True])))))  # fmt: skip
    assert attack_success_rate(attacked, infos)["asr"] == 0.5  # the paper's ASR counts f0

    rem = [{**i, **info(TARGET, family="removal", run_id=i["run_id"])} for i in infos]
    m = match_targets(attacked, rem)  # removal: f2, f3 missed -> successes
    a = attributable_asr(m, clean)  # the clean model misses f1, f2, f3's target
    assert (a["num_confounded"], a["num_confounded_success"]) == (3, 2)
    assert (a["num_targets"], a["num_success"], a["asr"]) == (1, 0, 0.0)
    assert a["asr_ci"] is None  # one run left


def test_attributable_asr_reaches_the_results_entry_and_its_checks():
    from pcdet_atlas.evaluation.analyses.attributable_analysis import AttributableAnalysis
    from pcdet_atlas.evaluation.analyses.schema_parts import ResultsError

    dets, infos = four_frames("injection")
    clean = [anno(d["frame_id"], [IOU_075] if i == 0 else []) for i, d in enumerate(dets)]
    infos = [{**i, "frame_id": d["frame_id"]} for i, d in zip(infos, dets)]
    out = evaluate_attack(dets, infos, clean_det_annos=clean)
    a = out["attributable"]
    assert (out["num_targets"], out["num_success"]) == (3, 1)
    assert (a["num_confounded"], a["num_confounded_success"], a["num_targets"]) == (1, 1, 2)
    assert a["asr"] == 0.0
    assert evaluate_attack(dets, infos)["attributable"] is None  # no clean run: unknown
    AttributableAnalysis().check(out, "v")
    with pytest.raises(ResultsError, match="num_success"):
        AttributableAnalysis().check({**out, "num_success": 2}, "v")
