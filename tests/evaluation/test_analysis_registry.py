"""Evaluation is open to new analyses: an analysis, a confidence kind and a metadata key
registered from a module outside the package reach ``results.json``, its schema and the report
without an edit elsewhere; the built-in analyses keep their order and keys."""

from __future__ import annotations

import importlib
import sys
import textwrap

import numpy as np
import pytest

from pcdet_atlas.attacks.metadata import _EXTRA_KEYS, make_meta, meta_keys, validate_meta
from pcdet_atlas.evaluation.analyses import (
    ANALYSES,
    CONFIDENCE_KINDS,
    AttackMetricError,
    evaluate_attack,
    match_targets,
    registered_analyses,
)
from pcdet_atlas.evaluation.results import (
    ResultsError,
    build_results,
    build_variant_result,
    load_results,
    save_results,
    write_report,
)
from pcdet_atlas.evaluation.results.report import report_figures

CLASSES = ["Vehicle"]
TARGET = np.array([20.0, 2.0, 1.0, 4.0, 2.0, 2.0, 0.3], dtype=np.float32)

#: The plugin: written to a folder outside the package, imported by its name only.
PLUGIN = '''
import numpy as np

from pcdet_atlas.attacks.metadata import register_meta_key
from pcdet_atlas.evaluation.analyses import (
    Analysis, ConfidenceKind, ReportFigure, ReportSection, register_analysis,
    register_confidence_kind,
)
from pcdet_atlas.evaluation.analyses.schema_parts import COUNT, FRAC, fail, nullable
from pcdet_atlas.evaluation.results.style import figure_grid, render

register_meta_key("plugin_weather", default="clear")


def mean_iou_table(results_list, fmt):
    rows = [f"| {r['model']} | {n} | {v['mean_target_iou']:.3f} |"
            for r in results_list for n, v in r["variants"].items()
            if v.get("mean_target_iou") is not None]
    if not rows:
        return []
    text = "\\n".join(["| Model | Variant | mean IoU |", "|:---|:---|---:|", *rows])
    return [("Mean target IoU (plugin)", text)]


def mean_iou_bars(results_list, notes):
    values = [v["mean_target_iou"] for r in results_list for v in r["variants"].values()
              if v.get("mean_target_iou") is not None]
    if not values:
        return "no variant with a mean target IoU"
    fig, (ax,) = figure_grid(1)
    ax.bar(range(len(values)), values)
    notes.append(f"{len(values)} variant(s).")
    return fig


def mean_iou_figure(results_list, path, notes):
    return render(lambda: mean_iou_bars(results_list, notes), path)


@register_analysis
class MeanTargetIou(Analysis):
    """The mean best IoU of the attacked targets, and the weather the frames recorded."""

    name = "mean_target_iou"

    def schema(self):
        return {"mean_target_iou": nullable(FRAC), "plugin_weathers": nullable(COUNT)}

    def compute(self, data):
        attacked = data.matches.attacked()
        weathers = {info["plugin_weather"] for info in data.attack_infos}
        mean = float(np.mean(attacked.max_iou)) if len(attacked) else None
        return {"mean_target_iou": mean, "plugin_weathers": len(weathers)}

    def check(self, entry, path):
        if entry["mean_target_iou"] is not None and entry["num_targets"] == 0:
            fail(f"{path}['mean_target_iou']", "set on a variant without targets")

    def sections(self):
        return [ReportSection(mean_iou_table)]

    def figures(self):
        return [ReportFigure("mean_target_iou.png", "Mean target IoU (plugin)", mean_iou_figure)]


def count_only(data):
    attacked = data.matches.attacked()
    scores = attacked.matched_score[attacked.detected]
    return {"kind": "count_only", "high_score_threshold": data.high_score,
            "num_targets": len(attacked), "num_detected": int(scores.size),
            "num_above": int(np.sum(scores > data.high_score)),
            "fraction_above": float(np.mean(scores > data.high_score)) if scores.size else None,
            "histogram": {"bin_edges": [0.0, 1.0], "counts": [int(scores.size)]}}


register_confidence_kind(ConfidenceKind(
    name="count_only", compute=count_only, shown="num_detected",
    properties={"num_detected": COUNT},
))
'''


@pytest.fixture()
def plugin(tmp_path, monkeypatch):
    """Import the plugin from a folder outside the package; undo its registrations after."""
    folder = tmp_path / "plugins"
    folder.mkdir()
    (folder / "atlas_test_plugin.py").write_text(textwrap.dedent(PLUGIN))
    monkeypatch.syspath_prepend(str(folder))
    module = importlib.import_module("atlas_test_plugin")
    yield module
    ANALYSES.unregister("mean_target_iou")
    CONFIDENCE_KINDS.unregister("count_only")
    _EXTRA_KEYS.pop("plugin_weather")
    sys.modules.pop("atlas_test_plugin")


def variant(confidence: str, hit_ious=(1.0, 0.5, 0.0)) -> tuple[list, list]:
    """One run of three spoofed injection frames; frame i has a prediction of IoU
    ``hit_ious[i]`` with the target (length scaled), none for 0."""
    dets, infos = [], []
    for i, iou in enumerate(hit_ious):
        box = TARGET.copy()
        box[3] *= iou if iou else 1.0
        n = int(iou > 0)
        dets.append({"frame_id": f"f{i}", "name": np.array(["Vehicle"] * n),
                     "boxes_lidar": np.array([box] * n, np.float32).reshape(-1, 7),
                     "score": np.full(n, 0.9, np.float32)})  # fmt: skip
        infos.append(make_meta("inj_x", "injection", spoofed=True, sequence_name="seq",
                               run_id=0, run_position=i, lifecycle_k=i + 1, target_box=TARGET,
                               success_if_detected=True, confidence=confidence,
                               rank_group="injection"))  # fmt: skip
    return dets, infos


def results_of(dets, infos, model="M") -> dict:
    attack = evaluate_attack(dets, infos)
    entry = build_variant_result("inj_x", family="injection", num_frames=len(dets),
                                 metrics=None, class_names=CLASSES, attack=attack)  # fmt: skip
    clean = build_variant_result("clean", family="clean", num_frames=len(dets), metrics=None,
                                 class_names=CLASSES)  # fmt: skip
    return build_results(model=model, config="cfgs/m.yaml", checkpoint=None,
                         class_names=CLASSES, variants={"clean": clean, "inj_x": entry},
                         created="2026-11-29T08:00:00+00:00")  # fmt: skip


def test_builtin_analyses_register_in_the_order_of_their_keys():
    assert [a.name for a in registered_analyses()] == [
        "asr",
        "attributable",
        "confidence",
        "lifecycle",
        "ranks",
    ]
    assert list(registered_analyses()[0].schema())[:4] == ["asr", "asr_ci", "num_runs", "runs"]


def test_an_analysis_from_outside_the_package_reaches_results_and_report(plugin, tmp_path):
    dets, infos = variant("injection")
    assert "plugin_weather" in meta_keys() and infos[0]["plugin_weather"] == "clear"
    validate_meta(infos[0])
    results = results_of(dets, infos)
    path = save_results(results, tmp_path / "results.json")
    entry = load_results(path)["variants"]["inj_x"]
    expected = float(np.mean(match_targets(dets, infos).max_iou))  # IoU 1, 0.5 and 0
    assert entry["mean_target_iou"] == pytest.approx(expected) and 0.45 < expected < 0.55
    assert entry["plugin_weathers"] == 1
    assert list(entry)[-3:] == ["lifecycle", "mean_target_iou", "plugin_weathers"]
    clean = load_results(path)["variants"]["clean"]
    assert clean["mean_target_iou"] is None  # the default empty value
    out = write_report([results], tmp_path / "report", latex=True)
    text = out["report"].read_text()
    assert "## Mean target IoU (plugin)" in text and f"| M | inj_x | {expected:.3f} |" in text
    assert text.index("## Mean target IoU (plugin)") < text.index("## Figures")
    assert "![Mean target IoU (plugin)](mean_target_iou.png)" in text and "1 variant(s)." in text
    assert (tmp_path / "report" / "mean_target_iou.png").read_bytes()[:4] == b"\x89PNG"
    assert "% Mean target IoU (plugin)" in out["latex"].read_text()
    # its invariants are checked with the built-ins'
    broken = load_results(path)
    broken["variants"]["clean"]["mean_target_iou"] = 0.5
    with pytest.raises(ResultsError, match=r"\['clean'\]\['mean_target_iou'\]: set on a variant"):
        save_results(broken, tmp_path / "broken.json")


def test_files_written_before_or_without_the_analysis(plugin, tmp_path):
    without = tmp_path / "without.json"
    plugin_keys = ("mean_target_iou", "plugin_weathers")
    results = results_of(*variant("injection"))
    old = {**results, "variants": {n: {k: v for k, v in e.items() if k not in plugin_keys}
                                   for n, e in results["variants"].items()}}  # fmt: skip
    save_results(old, without)  # optional keys: a file from before the analysis stays valid
    assert "mean_target_iou" not in load_results(without)["variants"]["inj_x"]
    with_key = save_results(results, tmp_path / "with.json")
    ANALYSES.unregister("mean_target_iou")
    try:
        with pytest.raises(ResultsError, match="unknown key 'mean_target_iou', 'plugin_weathers'"):
            load_results(with_key)
    finally:
        ANALYSES.register("mean_target_iou")(plugin.MeanTargetIou())


def test_a_registered_confidence_kind_is_computed_and_checked(plugin, tmp_path):
    results = results_of(*variant("count_only"))
    conf = results["variants"]["inj_x"]["confidence"]
    assert conf["kind"] == "count_only" and conf["num_detected"] == 1  # only IoU 1 >= 0.7
    broken = {**results}
    broken["variants"]["inj_x"]["confidence"]["num_detected"] = 2
    # the kind's ``shown`` count is checked against the common keys
    with pytest.raises(ResultsError, match=r"\['fraction_above'\]: 1.0 != 1/2"):
        save_results(broken, tmp_path / "r.json")


def test_unknown_confidence_kind_and_meta_key_are_clear_errors():
    dets, infos = variant("no_such_kind")
    with pytest.raises(AttackMetricError, match="'no_such_kind'.*not registered; known: "):
        evaluate_attack(dets, infos)
    with pytest.raises(ValueError, match=r"metadata keys \['weather'\] are not registered"):
        make_meta("v", "injection", weather="rain")


def test_report_figures_are_the_registered_ones_in_order():
    files = [f.file for f in report_figures()]
    assert files == [
        "rank_correlation.png",
        "lifecycle_injection.png",
        "lifecycle_removal.png",
        "confidence_injection.png",
        "confidence_removal.png",
        "heatmap_injection.png",
        "heatmap_removal.png",
        "accuracy_vs_time.png",
    ]
