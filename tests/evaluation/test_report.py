"""tools/report.py: the report's tables and figures from small hand-made results files (every
table row and figure present; a model missing a variant shows it as missing, not as zero; the
LOT ablation only with both models; LaTeX tables; clear errors)."""

from __future__ import annotations

import contextlib
import copy
import gzip
import json
import logging
import re
import sys
import threading
import time
import zlib
from pathlib import Path

import numpy as np
import pytest

from pcdet_atlas.attacks.metadata import make_meta
from pcdet_atlas.config import REPO_ROOT
from pcdet_atlas.evaluation.analyses import evaluate_attack
from pcdet_atlas.evaluation.analyses.asr_analysis import paired_table
from pcdet_atlas.evaluation.analyses.confidence_analysis import (
    centre_gap_table,
    confident_phantom_table,
)
from pcdet_atlas.evaluation.analyses.lifecycle_analysis import lifecycle_heatmaps, lifecycle_table
from pcdet_atlas.evaluation.intervals import asr_interval
from pcdet_atlas.evaluation.results import (
    ResultsError,
    build_results,
    build_variant_result,
    figures,
    queries,
    save_results,
)
from pcdet_atlas.evaluation.results import report as report_module
from pcdet_atlas.evaluation.results.archive import (
    archive_name,
    archive_results,
    archive_run_results,
)
from pcdet_atlas.evaluation.results.build import paired_from_results
from pcdet_atlas.evaluation.results.report import (
    code_cell,
    collect_results,
    lot_ablation_table,
    report_figures,
    rpn_cell,
    summary_table,
    write_report,
)
from pcdet_atlas.evaluation.results.seeds import (
    one_per_model_config,
    seed_groups,
    seed_spread_text,
)
from pcdet_atlas.evaluation.results.tables import variant_label
from pcdet_atlas.utils.files import NotARegularFileError
from pcdet_atlas.utils.hashing import file_sha256
from pcdet_atlas.utils.paths import UnsafePathError

sys.path.insert(0, str(REPO_ROOT / "tests" / "models"))
from model_batches import load_tool  # noqa: E402

CLASSES = ["Vehicle", "Pedestrian", "Cyclist"]
TARGET = np.array([20.0, 2.0, 1.0, 4.0, 2.0, 2.0, 0.3], dtype=np.float32)
WINDOW = 2
SCORING = {
    "injection": {"success_if_detected": True, "confidence": "injection",
                  "rank_group": "injection"},
    "removal": {"success_if_detected": False, "confidence": "removal", "rank_group": "removal"},
}  # fmt: skip


def metrics(l2: float) -> dict:
    out = {"L1/mAP": l2, "L1/mAPH": l2, "L2/mAP": l2, "L2/mAPH": l2 - 0.01}
    for cls in CLASSES:
        for key in ("L1/AP", "L1/APH", "L2/AP", "L2/APH"):
            out[f"{cls}/{key}"] = out[key.replace("AP", "mAP")]
    return out


def attacked_entry(variant: str, family: str, p_detect: float, seed: int, l2: float) -> dict:
    """A variant entry from real attack metrics: 4 spoof runs of the lifecycle k = 0..2W, the
    target detected with probability ``p_detect`` at a random score; the clean run detects a
    removal target at 0.95 and never sees a phantom."""
    rng = np.random.default_rng(seed)
    dets, infos, clean = [], [], []
    for run in range(4):
        box = TARGET + np.array([0, 10.0 * run, 0, 0, 0, 0, 0], np.float32)
        for k in range(2 * WINDOW + 1):
            frame_id = f"{variant}_r{run}_k{k}"
            shadow = not 1 <= k <= WINDOW
            hit = rng.random() < (p_detect if not shadow else 0.5 * p_detect)
            score = np.float32(rng.uniform(0.3, 1.0))
            dets.append({"frame_id": frame_id, "name": np.array(["Vehicle"] * hit),
                         "boxes_lidar": np.array([box] * hit, np.float32).reshape(-1, 7),
                         "score": np.full(int(hit), score, np.float32)})  # fmt: skip
            clean_hit = family == "removal"
            clean.append({"frame_id": frame_id, "name": np.array(["Vehicle"] * clean_hit),
                          "boxes_lidar": np.array([box] * clean_hit, np.float32).reshape(-1, 7),
                          "score": np.full(int(clean_hit), 0.95, np.float32)})  # fmt: skip
            infos.append(make_meta(variant, family, spoofed=not shadow, sequence_name="seq_0",
                                   run_id=run, run_position=k - 1, lifecycle_k=k, target_box=box,
                                   target_is_shadow=shadow, num_visible=100,
                                   **SCORING[family]))  # fmt: skip
    attack = evaluate_attack(dets, infos, clean_det_annos=clean, window=WINDOW,
                             recorded_window=WINDOW)  # fmt: skip
    return build_variant_result(
        variant, family=family, num_frames=len(dets), metrics=metrics(l2), class_names=CLASSES,
        attack=attack, rank_group=family, num_reused_frames=0,
    )  # fmt: skip


VARIANTS = {"inj_rel_easy": "injection", "inj_global_hard": "injection", "rem_10": "removal",
            "rem_40": "removal"}  # fmt: skip


def model(name: str, l2: float, p_inj: float, p_rem: float, ms: float, skip=()) -> dict:
    variants = {
        "clean": build_variant_result(
            "clean",
            family="clean",
            num_frames=200,
            metrics=metrics(l2),
            class_names=CLASSES,
            extra={"timing_s": {"model": ms * 200 / 1000.0}},
        )  # fmt: skip
    }
    for i, (variant, family) in enumerate(VARIANTS.items()):
        if variant not in skip:
            p = p_inj if family == "injection" else 1.0 - p_rem
            seed = zlib.crc32(name.encode()) % 1000 + i  # not hash(): salted per process
            variants[variant] = attacked_entry(variant, family, p, seed=seed,
                                               l2=l2 - 0.01 * (i + 1))  # fmt: skip
    return build_results(
        model=name, config=f"cfgs/{name}.yaml", checkpoint=None, class_names=CLASSES,
        variants=variants, created="2026-11-25T08:00:00+00:00", extra={"device": "cpu"},
    )  # fmt: skip


def md_table(table: str) -> dict[str, dict[str, str]]:
    """A Markdown table as row name -> column name -> cell."""
    lines = [line for line in table.splitlines() if line.startswith("|")]
    split = [[c.strip() for c in line.strip("|").split("|")] for line in lines]
    return {cells[0]: dict(zip(split[0], cells)) for cells in split[2:]}


def report_part(text: str, title: str) -> str:
    """The part of a report from the heading that starts with ``title`` to the next heading."""
    return text.split(title, 1)[1].split("\n#", 1)[0]


@pytest.fixture(scope="module")
def models():
    return [
        model("CenterPoint", 0.60, 0.3, 0.8, 40.0),
        model("CP-4f", 0.70, 0.5, 0.6, 60.0, skip=("rem_40",)),  # not evaluated on rem_40
        model("PHiM", 0.65, 0.4, 0.7, 120.0),
        model("PHiM+LOT", 0.64, 0.45, 0.5, 150.0),
    ]


def test_report_has_every_table_row_and_figure(models, tmp_path):
    out = write_report(models, tmp_path, sources=[f"m{i}.json" for i in range(4)], latex=True,
                       command="python tools/report.py ...")  # fmt: skip
    text = out["report"].read_text()
    for section in ("## Models", "## Point injection (paper Table 3)",
                    "## Point removal (paper Table 4)", "## LOT ablation: PHiM vs PHiM+LOT",
                    "## Attack onset and decay (paper Finding 3)",
                    "## Phantoms detected with confidence above 0.7 (paper Fig. 5)",
                    "## Centre gap under removal", "## Robustness ranks", "## Figures",
                    "## Per-model results"):  # fmt: skip
        assert section in text, section
    for name in ("CenterPoint", "CP-4f", "PHiM", "PHiM+LOT"):
        assert f"| {name} |" in text
    first_table = "| Model | Config" + report_part(text, "| Model | Config").split("\n\n")[0]
    provenance = md_table(first_table)
    assert provenance["CP-4f"]["Code"] == models[1]["pcdet_atlas_version"]  # no commit recorded
    assert models[1]["created"] not in text  # provenance, not the time of the run
    # CP-4f lacks rem_40: shown as missing in the removal table, not as zero
    cp4f = md_table(report_part(text, "## Point removal"))["CP-4f"]
    assert cp4f["Removal 40 L2 mAP"] == cp4f["Removal 40 ASR"] == "missing"
    assert f"{models[1]['variants']['rem_10']['asr']:.2f}" in cp4f["Removal 10 ASR"]
    for name, result in out["figures"].items():
        assert isinstance(result, Path), (name, result)
        assert result.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and result.stat().st_size > 5000
        assert result.with_suffix(".pdf").read_bytes()[:5] == b"%PDF-"  # the PDF beside it
        assert f"]({name})" in text
    assert set(out["figures"]) == {f.file for f in report_figures()}
    tex = out["latex"].read_text()
    attributable = md_table(report_part(text, "## Attributable ASR, removal"))
    # the clean run detects every removal target and no phantom: nothing is confounded
    assert attributable["CP-4f"]["Removal 40"] == "missing"
    asr = models[1]["variants"]["rem_10"]["asr"]
    assert attributable["CP-4f"]["Removal 10"].startswith(f"{asr:.2f} [")
    assert attributable["CP-4f"]["Removal 10"].endswith("; 0")
    assert tex.count("\\begin{tabular}") == 9 and "\\textbf{" in tex and "PHiM+LOT" in tex
    removal_tex = tex.split("% Point removal")[1].split("\\end{tabular}")[0].splitlines()
    cp4f_tex = next(line for line in removal_tex if line.startswith("CP-4f & "))
    assert cp4f_tex.removesuffix(" \\\\").split(" & ")[3:] == ["missing", "missing"]


def test_model_table_names_each_models_rpn():
    msf = {"config": "cfgs/atlas/synthetic/msf_4f.yaml"}
    assert rpn_cell(msf) == "`cfgs/atlas/synthetic/cp4f.yaml` (`checkpoints/cp4f_synthetic.pth`)"
    assert "cfgs/atlas/cp4f_voxel.yaml" in rpn_cell({"config": "cfgs/atlas/ptt_32f.yaml"})
    assert rpn_cell({"config": "cfgs/atlas/synthetic/centerpoint.yaml"}) == "-"
    assert rpn_cell({"config": "cfgs/nowhere.yaml"}).startswith("? (config unreadable")


def test_model_table_names_the_code_that_wrote_each_file():
    commit = "0123456789abcdef" * 2 + "01234567"
    base = {"pcdet_atlas_version": "0.1.0", "source_commit": None, "source_dirty": None}
    assert code_cell(base) == "0.1.0"
    assert code_cell({**base, "source_commit": commit, "source_dirty": False}) == (
        "0.1.0 `0123456789ab`"
    )
    assert code_cell({**base, "source_commit": commit, "source_dirty": True}).endswith("(modified)")


def test_summary_lot_and_centre_gap_tables(models):
    summary = summary_table(models).splitlines()
    assert summary[0].startswith("| Model | L2 mAP | L2 mAPH | Frames | Clean rank | ms/frame")
    rows = {r.split("|")[1].strip(): [c.strip() for c in r.split("|")[2:-1]] for r in summary[2:]}
    assert rows["CP-4f"][:5] == ["70.0", "69.0", "2", "1", "60"]
    assert rows["CenterPoint"][3] == "4"  # lowest clean mAP of the four
    # a family mean over every variant of the family in the report, else missing: CP-4f has no
    # rem_40, PHiM (below) no ASR for inj_rel_easy
    asr = {n: v["asr"] for n, v in models[0]["variants"].items()}
    assert rows["CenterPoint"][6:] == [f"{(asr['inj_rel_easy'] + asr['inj_global_hard']) / 2:.2f}",
                                       f"{(asr['rem_10'] + asr['rem_40']) / 2:.2f}"]  # fmt: skip
    assert rows["CP-4f"][7] == "missing (1 of 2 variants)"
    no_asr = copy.deepcopy(models[2])
    no_asr["variants"]["inj_rel_easy"]["asr"] = None
    phim = md_table(summary_table([models[0], no_asr]))["PHiM"]
    assert phim["Mean inj. ASR"] == "missing (1 of 2 variants)" and phim["Mean rem. ASR"] != "-"
    lot = lot_ablation_table(models[2], models[3]).splitlines()
    assert lot[0] == ("| Variant | PHiM L2 mAP | PHiM ASR | PHiM+LOT L2 mAP | PHiM+LOT ASR | "
                      "ΔASR vs PHiM |")  # fmt: skip
    inj = next(r for r in lot if r.startswith("| Rel-Fixed Easy |")).split("|")
    a, b = models[2]["variants"]["inj_rel_easy"], models[3]["variants"]["inj_rel_easy"]
    assert inj[-2].strip() == f"{b['asr'] - a['asr']:+.2f}"
    assert inj[3].strip().startswith(f"{a['asr']:.2f} [")  # with its interval
    lifecycle = lifecycle_table(models).splitlines()
    assert lifecycle[0] == ("| Model | W | injection k=0 | injection k=1 | injection k=W | "
                            "injection k=W+1 | removal k=0 | removal k=1 | removal k=W | "
                            "removal k=W+1 |")  # fmt: skip
    row = next(r for r in lifecycle if r.startswith("| CenterPoint |")).split("|")[2:-1]
    lcs = [models[0]["variants"][n]["lifecycle"] for n in ("rem_10", "rem_40")]
    for cell, k in zip(row[5:], (0, 1, WINDOW, WINDOW + 1)):
        hits = sum(lc["num_success"][k] for lc in lcs)
        total = sum(lc["num_targets"][k] for lc in lcs)
        # the interval of each run's counts summed over the two variants (they share runs)
        pooled = {}
        for lc in lcs:
            for run in lc["runs"][k]:
                n, s = pooled.get((run["sequence"], run["run_id"]), (0, 0))
                pooled[(run["sequence"], run["run_id"])] = (
                    n + run["num_targets"],
                    s + run["num_success"],
                )
        lo, hi = asr_interval([
            {"sequence": q, "run_id": r, "num_targets": n, "num_success": s}
            for (q, r), (n, s) in pooled.items()
        ])  # fmt: skip
        assert cell.strip() == f"{hits / total:.2f} [{lo:.2f}, {hi:.2f}] ({hits}/{total})"
        assert total == 8
    assert row[0].strip() == str(WINDOW)
    # CP-4f was not evaluated on rem_40: its removal lifecycle is not pooled over rem_10 alone
    cp4f = [c.strip() for c in next(r for r in lifecycle if r.startswith("| CP-4f |")).split("|")]
    assert cp4f[2:-1] == [str(WINDOW)] + cp4f[3:7] + ["missing (1 of 2 variants)"] * 4
    assert cp4f[3] != "missing (1 of 2 variants)"
    no_lifecycle = copy.deepcopy(models[0])
    no_lifecycle["variants"]["rem_40"]["lifecycle"] = None
    cells = md_table(lifecycle_table([no_lifecycle, models[2]]))["CenterPoint"]
    assert cells["removal k=1"] == "missing (1 of 2 variants)"
    confident = confident_phantom_table(models).splitlines()
    assert confident[0] == "| Model | Rel-Fixed Easy | Global Hard |"
    conf = models[0]["variants"]["inj_global_hard"]["confidence"]
    assert conf["num_detected"] > 0  # scores drawn in [0.3, 1): some above 0.7, some not
    want = f"{conf['fraction_above']:.2f} ({conf['num_above']}/{conf['num_detected']})"
    assert want in next(r for r in confident if r.startswith("| CenterPoint |"))
    assert 0 < conf["num_above"] < conf["num_detected"]
    gap = centre_gap_table(models).splitlines()
    assert gap[0] == "| Model | Removal 10 | Removal 40 |"
    cp4f = next(r for r in gap if r.startswith("| CP-4f |"))
    assert cp4f.endswith("| missing |")
    peak = models[0]["variants"]["rem_10"]["confidence"]["peak_gap"]
    assert f"{peak:.3f}" in next(r for r in gap if r.startswith("| CenterPoint |"))


def test_lot_ablation_against_its_no_lot_control(models, tmp_path):
    """With the control (the same detector fine-tuned without LOT) the ablation's change is
    PHiM+LOT minus the control, per variant and per family mean, with the paired interval;
    without it the report says the change also counts the extra epochs."""
    control = model("PHiM (no-LOT control)", 0.66, 0.35, 0.75, 125.0)
    phim, lot = models[2], models[3]
    table = md_table(lot_ablation_table(phim, lot, control=control))
    col = "ΔASR vs PHiM (no-LOT control) [95% CI]"
    assert list(table["Clean"])[1:] == [
        "PHiM L2 mAP", "PHiM ASR", "PHiM (no-LOT control) L2 mAP", "PHiM (no-LOT control) ASR",
        "PHiM+LOT L2 mAP", "PHiM+LOT ASR", col, "ΔASR vs PHiM"]  # fmt: skip
    for name in VARIANTS:
        row = table[variant_label(name)]
        want = lot["variants"][name]["asr"] - control["variants"][name]["asr"]
        paired = paired_from_results([lot, control], [name])
        lo, hi = paired["ci"]["PHiM+LOT"]["PHiM (no-LOT control)"]
        assert row[col] == f"{want:+.2f} [{lo:+.2f}, {hi:+.2f}]"
        to_phim = lot["variants"][name]["asr"] - phim["variants"][name]["asr"]
        assert row["ΔASR vs PHiM"] == f"{to_phim:+.2f}"
    for family in ("injection", "removal"):
        names = [n for n, f in VARIANTS.items() if f == family]
        row = table[f"{family.capitalize()}, mean"]
        want = np.mean([lot["variants"][n]["asr"] - control["variants"][n]["asr"] for n in names])
        assert row[col].startswith(f"{want:+.2f} [")
        assert row["PHiM (no-LOT control) ASR"] == (
            f"{np.mean([control['variants'][n]['asr'] for n in names]):.2f}"
        )
    assert table["Clean"][col] == "-"
    # a control not scored on the same targets is named under the table, not paired
    other = copy.deepcopy(control)
    other["variants"]["rem_10"]["runs"][0]["num_targets"] += 1
    text = lot_ablation_table(phim, lot, control=other)
    assert md_table(text)[variant_label("rem_10")][col] == "-"
    assert "Not paired over rem_10: " in text and "not scored on the same" in text
    assert md_table(text)["Removal, mean"][col] == "-"
    text = write_report([phim, control, lot], tmp_path / "with")["report"].read_text()
    part = report_part(text, "## LOT ablation: PHiM, PHiM (no-LOT control) and PHiM+LOT")
    assert "what LOT does" in part and col in part
    text = write_report([phim, lot], tmp_path / "without")["report"].read_text()
    assert "also counts PHiM+LOT's extra fine-tuning epochs" in report_part(
        text, "## LOT ablation: PHiM vs PHiM+LOT"
    )
    tex = write_report([phim, control, lot], tmp_path / "tex", latex=True)["latex"].read_text()
    assert "ASR change vs PHiM (no-LOT control)" in tex and "ΔASR" not in tex


def test_paired_comparison_per_rank_group(models, tmp_path):
    """Per rank group, each model's mean ASR and every pair's difference with its paired
    interval (bold where it excludes 0), over the ranked variants every model has; a file
    without per-run counts (schema 4) is named, not guessed."""
    text = write_report(models, tmp_path)["report"].read_text()
    part = text.split("## Paired model comparison", 1)[1].split("\n## ", 1)[0]
    assert "### injection" in part and "### removal" in part
    removal = report_part(text, "### removal")
    assert (
        "Over 1 variant(s), clustered by 4 runs of one sequence; runs per variant: Removal 10: 4."
        in removal
    )  # CP-4f lacks rem_40
    out = paired_from_results(models, ["rem_10"])
    rows = md_table(removal)
    for a in out["models"]:
        assert rows[a]["mean ASR"] == f"{out['mean_asr'][a]:.2f}"
        assert out["mean_asr"][a] == pytest.approx(queries.mean_asr(
            next(r for r in models if r["model"] == a), ["rem_10"]))  # fmt: skip
        for b in out["models"]:
            if a == b:
                continue
            lo, hi = out["ci"][a][b]
            cell = f"{out['difference'][a][b]:+.2f} [{lo:+.2f}, {hi:+.2f}]"
            assert rows[a][b] == (f"**{cell}**" if lo > 0 or hi < 0 else cell)
            assert out["difference"][a][b] == pytest.approx(-out["difference"][b][a])
    # 4 runs of 2 targets in one sequence: 4 clusters, t with 3 degrees of freedom, so even
    # 0.88 vs 0.50 is not settled; the interval stays within [-1, 1]
    lo, hi = out["ci"]["CenterPoint"]["PHiM+LOT"]
    assert out["difference"]["CenterPoint"]["PHiM+LOT"] == pytest.approx(0.375)
    assert lo < 0 < hi
    assert all(-1 <= x <= 1 for a in out["ci"].values() for ci in a.values() for x in ci)
    settled = copy.deepcopy(models)  # the same runs, 12 times over in 12 sequences
    for r in settled:
        runs = r["variants"]["rem_10"]["runs"]
        r["variants"]["rem_10"]["runs"] = [{**x, "sequence": f"seq_{i}"} for i in range(12)
                                           for x in runs]  # fmt: skip
    cell = md_table(paired_table(settled, "removal", ["rem_10"]))["CenterPoint"]["PHiM+LOT"]
    assert cell.startswith("**+0.38 [+") and cell.endswith("]**")  # excludes 0: bold
    old = copy.deepcopy(models[2])
    old["variants"]["rem_10"]["runs"] = None
    assert paired_table([models[0], old], "removal", ["rem_10"]) == (
        "not computed: PHiM, variant 'rem_10': no per-run counts (a results.json from before "
        "schema 5; evaluate it again)"
    )
    assert "needs at least 2 models" in paired_table(models[:1], "removal", ["rem_10"])


def test_time_of_proposals_read_from_the_store_is_added_back(models, tmp_path):
    """A two-stage model that read its RPN's proposals from the prediction store is timed with
    the RPN's clean ms/frame for those batches, found through its config's MODEL.RPN; without
    its RPN in the report the time is a lower bound, marked and explained."""

    def stored(results, name, cfg, ckpt, ms, hits):
        out = copy.deepcopy(results)
        out.update(model=name, config=cfg, checkpoint=ckpt)
        clean = out["variants"]["clean"]
        clean["extra"] = {"timing_s": {"model": ms * 200 / 1000.0},
                          "prediction_store": {"hits": hits, "misses": 200 - hits}}  # fmt: skip
        return out

    rpn = stored(models[1], "CP-4f", "cfgs/atlas/synthetic/cp4f.yaml",
                 "checkpoints/cp4f_synthetic.pth", 80.0, 0)  # fmt: skip
    msf = stored(models[2], "MSF-4f", "cfgs/atlas/synthetic/msf_4f.yaml",
                 "checkpoints/msf_4f_synthetic.pth", 50.0, 150)  # fmt: skip
    assert queries.rpn_results(msf, [rpn, msf]) == (rpn, "")
    # written in another clone: the checkpoint's path differs, its recorded bytes are the same
    elsewhere = copy.deepcopy(rpn)
    elsewhere["checkpoint"] = "/elsewhere/clone/checkpoints/cp4f_synthetic.pth"
    assert queries.rpn_results(msf, [elsewhere, msf])[0] is None
    elsewhere["extra"] = {"checkpoint_sha256": file_sha256(REPO_ROOT / rpn["checkpoint"])}
    assert queries.rpn_results(msf, [elsewhere, msf]) == (elsewhere, "")
    ms, lower_bound, note = queries.frame_cost(msf, [rpn, msf])
    assert ms == pytest.approx(50.0 + 80.0 * 150 / 200) and not lower_bound
    assert note == (
        "MSF-4f: 50 ms of its own + 60 ms for the proposals of 150 of 200 clean batches read "
        "from the prediction store, at CP-4f's clean 80 ms/frame"
    )
    assert queries.frame_cost(rpn, [rpn, msf]) == (pytest.approx(80.0), False, None)
    text = summary_table([rpn, msf])
    assert md_table(text)["MSF-4f"]["ms/frame"] == "110" and f"ms/frame of {note}." in text
    # another RPN checkpoint, the RPN not given, or the RPN served by the store itself
    other = copy.deepcopy(rpn)
    other["checkpoint"] = "checkpoints/other.pth"
    served = stored(rpn, "CP-4f", rpn["config"], rpn["checkpoint"], 5.0, 200)
    cases = [
        (other, "its RPN (cfgs/atlas/synthetic/cp4f.yaml with checkpoints/cp4f_synthetic.pth) "
                "is not in the report"),
        (served, "its RPN CP-4f read clean batches from the store as well"),
    ]  # fmt: skip
    for given, why in cases:
        ms, lower_bound, note = queries.frame_cost(msf, [given, msf])
        assert ms == pytest.approx(50.0) and lower_bound
        assert note == ("MSF-4f: at least 50 ms; 150 of 200 clean batches were read from the "
                        f"prediction store, untimed: {why}")  # fmt: skip
        assert md_table(summary_table([given, msf]))["MSF-4f"]["ms/frame"] == "≥50"
    # a config that names no RPN: the model's own predictions came from the store
    ms, lower_bound, note = queries.frame_cost(served, [served])
    assert lower_bound and note.endswith("names no RPN (MODEL.RPN.CFG, CHECKPOINT)")
    assert "$\\geq$50" in summary_table([other, msf], fmt="latex")
    notes = []
    assert isinstance(figures.accuracy_vs_time([served, msf], tmp_path / "t.png", notes), Path)
    assert [n for n in notes if n.startswith("Model time per frame of")] == [
        f"Model time per frame of {queries.frame_cost(m, [served, msf])[2]}." for m in (served, msf)
    ]


def test_ranks_and_figures_name_what_they_leave_out(models, tmp_path):
    untimed = copy.deepcopy(models[3])
    del untimed["variants"]["clean"]["extra"]  # no clean timing
    text = write_report([*models[:3], untimed], tmp_path)["report"].read_text()
    used = "Ranked over 3 variant(s): inj_rel_easy, inj_global_hard, rem_10."
    left_out = "Left out of the ranks:\n- rem_40: not evaluated by CP-4f"
    for title in ("## Robustness ranks", "### Robustness rank correlation"):
        assert used in report_part(text, title) and left_out in report_part(text, title)
    accuracy = report_part(text, "### Clean L2 mAP against model time per frame")
    assert "Left out (no clean timing or clean L2 mAP): PHiM+LOT." in accuracy
    assert "Hollow grey marker, no mean ASR colour: CP-4f (missing (3 of 4 variants))." in accuracy
    heatmap = report_part(text, "### Target confidence over the lifecycle")
    assert "CP-4f: pooled without rem_40 (not evaluated)." in heatmap
    assert "pooled without" not in report_part(text, "### Phantom confidence over the lifecycle")
    # the reasons, one by one
    no_asr = copy.deepcopy(models[2])
    no_asr["variants"]["inj_rel_easy"]["asr"] = None
    assert queries.ranked_variants([models[0], models[1], no_asr]) == (
        ["inj_global_hard", "rem_10"],
        {"inj_rel_easy": "no ASR from PHiM", "rem_40": "not evaluated by CP-4f"},
    )
    mixed, bare = copy.deepcopy(models[0]), copy.deepcopy(models[2])
    mixed["variants"]["rem_40"]["lifecycle"]["window"] = 1
    mixed["variants"]["inj_global_hard"]["lifecycle"]["score_bin_edges"] = [0.0, 0.5, 1.0]
    for entry in bare["variants"].values():
        entry["lifecycle"] = None
    notes = []
    drawn = lifecycle_heatmaps([mixed, bare], "removal", tmp_path / "rem.png", notes)
    assert isinstance(drawn, Path) and notes == [
        "No panel (no removal variant with lifecycle data): PHiM.",
        "CenterPoint: pooled without rem_40 (window 1, not 2).",
    ]
    notes = []
    lifecycle_heatmaps([mixed], "injection", tmp_path / "inj.png", notes)
    assert notes == ["CenterPoint: pooled without inj_global_hard (score bins differ from "
                     "inj_rel_easy's)."]  # fmt: skip


def test_figures_that_need_more_say_why(models, tmp_path):
    out = write_report(models[:2], tmp_path)  # no LOT pair, 2 models: no rank fit
    text = out["report"].read_text()
    assert "LOT ablation" not in text
    assert isinstance(out["figures"]["rank_correlation.png"], str)
    assert "Not drawn: needs at least 3 models" in text
    assert isinstance(out["figures"]["lifecycle_removal.png"], Path)


def test_the_tool_reads_files_and_folders_and_refuses_duplicates(models, tmp_path):
    paths = [save_results(r, tmp_path / "runs" / f"m{i}" / "results.json")
             for i, r in enumerate(models)]  # fmt: skip
    report = load_tool("report")
    out = report.main(["--results", str(tmp_path / "runs"), "--out_dir", str(tmp_path / "rep")])
    assert out["report"].is_file() and out["latex"] is None
    assert [p for p, _ in collect_results([tmp_path / "runs"])] == paths
    save_results(models[0], tmp_path / "dup.json")
    with pytest.raises(ResultsError, match="'CenterPoint' appears twice"):
        collect_results([paths[0], tmp_path / "dup.json"])
    with pytest.raises(ResultsError, match="no such file"):
        collect_results([tmp_path / "nope"])
    with pytest.raises(ResultsError, match="no results.json under"):
        collect_results([tmp_path / "rep"])


def test_the_tool_refuses_an_out_that_is_a_file(models, tmp_path, capsys):
    save_results(models[0], tmp_path / "runs" / "results.json")
    out = tmp_path / "report.md"
    out.write_text("an earlier report")
    with pytest.raises(SystemExit) as exited:
        load_tool("report").main(["--results", str(tmp_path / "runs"), "--out_dir", str(out)])
    assert exited.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error.endswith(f"--out_dir {out}: an existing file, expected a folder (or a path to "
                          "create one)")  # fmt: skip
    assert out.read_text() == "an earlier report"


def test_reproduce_names_a_truncated_or_mistyped_run_json(tmp_path):
    reproduce = load_tool("reproduce")
    run_file = tmp_path / "run.json"
    run_file.write_text('{"runs": [{"config": "a.yaml", "resu')  # a write cut short
    with pytest.raises(ValueError, match=rf"^{re.escape(str(run_file))}: not valid JSON"):
        reproduce.main(["--out_dir", str(tmp_path), "--report_only"])
    data = tmp_path / "data"
    (data / "ImageSets").mkdir(parents=True)
    argv = ["--out_dir", str(tmp_path), "--data_path", str(data), "--attacks", "clean",
            "--cfgs", "cfgs/atlas/synthetic/centerpoint.yaml"]  # fmt: skip
    with pytest.raises(ValueError, match="not valid JSON"):  # read before anything is evaluated
        reproduce.main(argv)
    good = {"setting": {}, "command": "", "total_wall_s": 2.0, "calls": 1, "cpus": ["x"],
            "runs": [{"config": "a.yaml", "results": "r.json", "wall_s": 1.0}],
            "model_wall_s": {"a.yaml": 1.0}}  # fmt: skip
    run_file.write_text(json.dumps(good))
    assert reproduce.read_run_record(run_file) == good
    for mutate, key, expected in [
        (lambda r: r.update(total_wall_s="12 min"), "total_wall_s", "int or float"),
        (lambda r: r.update(calls=True), "calls", "int"),
        (lambda r: r.update(runs={}), "runs", "list"),
        (lambda r: r["runs"][0].pop("results"), "runs[0].results", "str"),
        (lambda r: r["runs"][0].update(wall_s="1"), "runs[0].wall_s", "int or float"),
        (lambda r: r["runs"][0].update(earlier_run=1), "runs[0].earlier_run", "bool"),
        (lambda r: r["model_wall_s"].update({"a.yaml": None}), "model_wall_s.a.yaml", "a number"),
        (lambda r: r["cpus"].append(3), "cpus[1]", "a CPU model name"),
        (lambda r: r.update(earlier_run_models=[1]), "earlier_run_models[0]", "a model config"),
    ]:
        bad = copy.deepcopy(good)
        mutate(bad)
        run_file.write_text(json.dumps(bad))
        with pytest.raises(ValueError) as err:
            reproduce.read_run_record(run_file)
        assert str(err.value).startswith(f"{run_file}: key {key!r} holds "), key
        assert f"expected {expected}" in str(err.value), key
    run_file.write_text("[]")
    with pytest.raises(ValueError, match="holds a JSON list, expected an object"):
        reproduce.main(["--out_dir", str(tmp_path), "--report_only"])


@pytest.mark.slow
def test_reproduce_evaluates_and_reports(synthetic_root, tmp_path, monkeypatch):
    """tools/reproduce.py end to end on the fixture data: two models evaluated at once, clean and
    one removal variant on 5 frames; the report and its run record with the wall time and reuse
    counts; a second call resumes (predicts nothing, scores the kept predictions again), a model
    stopped mid-way goes on from its last finished variant, a retrained checkpoint or a changed
    --set evaluates again."""
    reproduce = load_tool("reproduce")
    cfgs = [REPO_ROOT / "cfgs" / "atlas" / "synthetic" / f"{name}.yaml"
            for name in ("centerpoint", "cp4f")]  # fmt: skip

    def argv(interval: int) -> list[str]:
        return [
            "--data_path", str(synthetic_root), "--out_dir", str(tmp_path / "report"),
            "--cfgs", *map(str, cfgs), "--attacks", "clean,rem_30", "--workers", "0",
            "--device", "cpu", "--jobs", "2", "--threads", "1",
            "--eval_dir", str(tmp_path / "output"),
            "--set", "DATA_CONFIG.SAMPLED_INTERVAL", f"train:1,test:{interval}",
            "DATA_CONFIG.POINT_CLOUD_RANGE", "-20.48,-20.48,-2,20.48,20.48,4",
        ]  # fmt: skip

    out = reproduce.main(argv(14))
    text = out["report"].read_text()
    assert "## How these results were produced" in text and "| CenterPoint |" in text
    assert "2 model(s) at a time with 1 torch thread(s) each" in text
    assert f"({reproduce.cpu_model()}); total wall time" in text  # the CPU it ran on
    # clean 5 frames + rem_30 2 recomputed (below) per model, its time spread over them
    appendix = text.split("## How these results were produced")[1].splitlines()
    row = next(line for line in appendix if line.startswith("| CP-4f | "))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2:4] == ["7", "3"] and float(cells[4]) > 0
    run = out["run"]
    # configs named from the repository root, as results.json and the report name them
    want = [f"cfgs/atlas/synthetic/{name}.yaml" for name in ("centerpoint", "cp4f")]
    assert run["total_wall_s"] > 0 and [r["config"] for r in run["runs"]] == want
    assert "| `cfgs/atlas/synthetic/cp4f.yaml` |" in text
    assert json.loads((tmp_path / "report" / "run.json").read_text())["runs"] == run["runs"]
    assert run["model_wall_s"] == {r["config"]: r["wall_s"] for r in run["runs"]}
    results = collect_results([run["runs"][0]["results"]])[0][1]
    # CenterPoint's config declares its checkpoint's seed; both record their model's digest
    assert results["training_seed"] == 666 and len(results["model_sha256"]) == 64
    # files inside the repository are named from its root, as the configs are (any clone)
    assert results["checkpoint"] == "checkpoints/centerpoint_synthetic.pth"
    assert "| `checkpoints/centerpoint_synthetic.pth` |" in text
    rem = results["variants"]["rem_30"]
    # frames 0, 14, 28, 42, 56: the run 32..63 spoofs 42 and 56, the other three are reused
    assert rem["num_reused_frames"] == 3 and rem["num_recomputed_frames"] == 2
    assert (tmp_path / "report" / "report.tex").is_file()
    assert not list(synthetic_root.glob("*.npz"))  # no trace library needed, none built
    log = Path(run["runs"][1]["results"]).parent.parent / "reproduce.log"
    assert "cp4f" in log.read_text()

    stamps = [Path(r["results"]).stat().st_mtime_ns for r in run["runs"]]

    def predicted(results: str) -> dict[str, int]:  # when each variant's result.pkl was written
        pkls = Path(results).parent.glob("*/result.pkl")
        return {p.parent.name: p.stat().st_mtime_ns for p in pkls}

    def variants_of(results: str) -> dict:
        return collect_results([results])[0][1]["variants"]

    predictions = [predicted(r["results"]) for r in run["runs"]]
    entries = [variants_of(r["results"]) for r in run["runs"]]
    # --report_only writes the same report again from run.json and the results, evaluating nothing
    out["report"].unlink()
    rewritten = reproduce.main(["--out_dir", str(tmp_path / "report"), "--report_only"])
    assert rewritten["report"].read_text() == text
    assert [Path(r["results"]).stat().st_mtime_ns for r in run["runs"]] == stamps
    with pytest.raises(FileNotFoundError, match="--report_only: no .*run.json"):
        reproduce.main(["--out_dir", str(tmp_path / "elsewhere"), "--report_only"])
    older = json.loads(Path(run["runs"][0]["results"]).read_text())  # as an older metric wrote
    older["variants"]["rem_30"]["L2/mAP"] = 0.5
    older["source_commit"] = "0" * 40  # another version (this one's results are not rescored)
    Path(run["runs"][0]["results"]).write_text(json.dumps(older))
    again = reproduce.main(argv(14))  # resumes: both models are done, scored again
    assert again["run"]["runs"] == run["runs"]
    assert again["run"]["total_wall_s"] >= run["total_wall_s"]
    assert [predicted(r["results"]) for r in run["runs"]] == predictions  # nothing predicted
    assert [variants_of(r["results"]) for r in run["runs"]] == entries  # the same numbers
    # a model stopped after its clean variant goes on from there (tools/test.py --resume)
    record = json.loads((tmp_path / "report" / "run.json").read_text())
    results_file = Path(record["runs"][0]["results"])
    stopped = json.loads(results_file.read_text())
    del stopped["variants"]["rem_30"], record["runs"][0]
    results_file.write_text(json.dumps(stopped))
    (tmp_path / "report" / "run.json").write_text(json.dumps(record))
    pkl = {v: results_file.parent / v / "result.pkl" for v in ("clean", "rem_30")}
    pkl_stamps = {v: p.stat().st_mtime_ns for v, p in pkl.items()}
    resumed = reproduce.main(argv(14))
    assert pkl["clean"].stat().st_mtime_ns == pkl_stamps["clean"]
    assert pkl["rem_30"].stat().st_mtime_ns > pkl_stamps["rem_30"]
    assert resumed["run"]["calls"] == 3 and "over 3 calls" in resumed["report"].read_text()
    assert resumed["run"]["cpus"] == [reproduce.cpu_model()]  # one entry per distinct CPU
    assert resumed["run"]["runs"][0]["wall_s"] > 0
    predictions = [predicted(r["results"]) for r in run["runs"]]
    # a retrained checkpoint (its SHA-256 differs from the one results.json records) is
    # evaluated again from scratch, the other model not
    stale = json.loads(results_file.read_text())
    stale["extra"]["checkpoint_sha256"] = "0" * 64
    results_file.write_text(json.dumps(stale))
    pkl_stamps = {v: p.stat().st_mtime_ns for v, p in pkl.items()}
    reproduce.main(argv(14))
    assert all(p.stat().st_mtime_ns > pkl_stamps[v] for v, p in pkl.items())
    assert predicted(run["runs"][1]["results"]) == predictions[1]  # the other model: kept
    predictions = [predicted(r["results"]) for r in run["runs"]]
    changed = reproduce.main(argv(20))  # another setting: evaluated again
    assert all(all(predicted(r["results"])[v] > t for v, t in p.items())
               for r, p in zip(changed["run"]["runs"], predictions))  # fmt: skip
    predictions = [predicted(r["results"]) for r in changed["run"]["runs"]]
    assert not any(r["earlier_run"] for r in changed["run"]["runs"])
    # another model set is another run: its time and calls are not added to this one's, and it
    # keeps the model an earlier call evaluated, marked in the report
    one = argv(20)
    del one[one.index("--cfgs") + 2]  # the first model only
    looked_up, evaluation_of = [], reproduce.evaluation_of

    def counted(cfg, *rest):
        looked_up.append(str(cfg))
        return evaluation_of(cfg, *rest)

    monkeypatch.setattr(reproduce, "evaluation_of", counted)  # a first call: once per model
    alone = reproduce.main(one)
    monkeypatch.setattr(reproduce, "evaluation_of", evaluation_of)
    assert looked_up == ["cfgs/atlas/synthetic/centerpoint.yaml"]
    assert alone["run"]["calls"] == 1 and len(alone["run"]["runs"]) == 1
    assert predicted(alone["run"]["runs"][0]["results"]) == predictions[0]  # nothing predicted
    assert alone["run"]["runs"][0]["earlier_run"] is True
    assert alone["run"]["runs"][0]["wall_s"] == changed["run"]["runs"][0]["wall_s"]
    text = alone["report"].read_text()
    assert "| CenterPoint † |" in text and "Models marked † were evaluated" in text
    # ... marked in the calls that continue that run too
    again = reproduce.main(one)
    assert again["run"]["calls"] == 2 and again["run"]["runs"][0]["earlier_run"] is True
    assert again["run"]["earlier_run_models"] == ["cfgs/atlas/synthetic/centerpoint.yaml"]
    # ... and a --no_reuse run evaluates it again: it times what reuse skips
    alone = reproduce.main(["--no_reuse", *one])
    assert all(predicted(alone["run"]["runs"][0]["results"])[v] > t
               for v, t in predictions[0].items())  # fmt: skip
    assert alone["run"]["runs"][0]["earlier_run"] is False


def test_reproduce_scores_again_what_another_version_wrote(tmp_path):
    """A finished model is scored again (tools/test.py --resume) unless this very commit, with no
    uncommitted change on either side, wrote its results."""
    from pcdet_atlas.utils.provenance import SourceRevision

    reproduce = load_tool("reproduce")
    results = tmp_path / "results.json"
    commit = "a" * 40
    results.write_text(json.dumps({"source_commit": commit, "source_dirty": False}))
    assert reproduce.scored_by(results, SourceRevision(commit=commit, dirty=False))
    assert not reproduce.scored_by(results, SourceRevision(commit=commit, dirty=True))
    assert not reproduce.scored_by(results, SourceRevision(commit="b" * 40, dirty=False))
    assert not reproduce.scored_by(results, None)  # not a git checkout: cannot tell
    results.write_text(json.dumps({"source_commit": commit, "source_dirty": True}))
    assert not reproduce.scored_by(results, SourceRevision(commit=commit, dirty=False))
    results.write_text(json.dumps({"source_commit": None, "source_dirty": None}))  # older file
    assert not reproduce.scored_by(results, SourceRevision(commit=commit, dirty=False))


def test_reproduce_starts_no_model_after_one_failed(capsys):
    """A failed model (an RPN, say) stops the models not started yet; the running ones finish;
    its error is raised."""
    reproduce = load_tool("reproduce")
    started, release = [], threading.Event()

    def evaluate(cfg):
        started.append(cfg)
        if cfg == "rpn":
            raise RuntimeError("rpn: tools/test.py exited with 1")
        if cfg == "running":
            assert release.wait(10)

    def release_soon():
        time.sleep(0.5)
        release.set()

    threading.Thread(target=release_soon, daemon=True).start()
    with pytest.raises(RuntimeError, match="rpn: tools/test.py exited with 1"):
        reproduce.evaluate_all(["running", "rpn", "two_stage", "other"], evaluate, jobs=2)
    assert started == ["running", "rpn"] and release.is_set()
    assert "2 model(s) not started are cancelled" in capsys.readouterr().out
    done = []
    reproduce.evaluate_all(["a", "b", "c"], done.append, jobs=2)
    assert sorted(done) == ["a", "b", "c"]


def test_reproduce_starts_rpns_then_the_longest_models_first():
    """The times an earlier run.json knows (its runs, and those it carried from before) order the
    models longest first; models without a time start first, in the given order."""
    reproduce = load_tool("reproduce")
    earlier = {"model_wall_s": {"a.yaml": 10.0, "b.yaml": 50.0, "c.yaml": 1.0},
               "runs": [{"config": "c.yaml", "wall_s": 90.0}]}  # fmt: skip
    known = reproduce.known_times(earlier)
    assert known == {"a.yaml": 10.0, "b.yaml": 50.0, "c.yaml": 90.0}
    cfgs = [Path(name) for name in ("a.yaml", "b.yaml", "new.yaml", "c.yaml", "other.yaml")]
    order = reproduce.start_order(cfgs, known)
    assert [str(c) for c in order] == ["new.yaml", "other.yaml", "c.yaml", "b.yaml", "a.yaml"]
    # another model's RPN starts first: its stored predictions are the others' proposals
    order = reproduce.start_order(cfgs, known, rpns={Path("a.yaml")})
    assert [str(c) for c in order] == ["a.yaml", "new.yaml", "other.yaml", "c.yaml", "b.yaml"]
    assert reproduce.known_times({}) == {}


def test_reproduce_shares_a_store_between_rpns_and_two_stage_models(tmp_path):
    reproduce = load_tool("reproduce")
    synthetic = Path("cfgs/atlas/synthetic")
    cfgs = [synthetic / f"{name}.yaml" for name in ("centerpoint", "cp4f", "msf_8f", "ptt_32f")]
    rpns = {reproduce.rpn_config(cfg) for cfg in cfgs} - {None}
    assert rpns == {synthetic / "cp4f.yaml"}
    args = reproduce.parse_args(["--eval_dir", str(tmp_path)])
    stores = [reproduce.store_of(cfg, rpns, args) for cfg in cfgs]
    assert stores == [None, *[tmp_path / "prediction_store"] * 3]
    argv = reproduce.test_argv(cfgs[2], args, tmp_path, 1, False, stores[2])
    assert argv[argv.index("--prediction_store") + 1] == str(tmp_path / "prediction_store")
    args = reproduce.parse_args(["--eval_dir", str(tmp_path), "--no_store"])
    assert all(reproduce.store_of(cfg, rpns, args) is None for cfg in cfgs)
    assert "--prediction_store" not in reproduce.test_argv(cfgs[2], args, tmp_path, 1, False)


def _same_report(a: Path, b: Path, sources: tuple[str, str]) -> None:
    """Two report folders hold the same report: report.md equal but for the command line and
    the Source column's folder, report.tex and every figure (PNG and PDF) byte for byte."""

    def text(folder: Path, source: str) -> str:
        lines = (folder / "report.md").read_text().replace(source, "<results>").splitlines()
        return "\n".join(line for line in lines if not line.startswith("Generated by `"))

    text_a, text_b = text(a, sources[0]), text(b, sources[1])
    assert text_a.count("<results>/") == 4
    assert text_a.replace(".json.gz`", ".json`") == text_b.replace(".json.gz`", ".json`")
    assert (a / "report.tex").read_bytes() == (b / "report.tex").read_bytes()
    assert sorted(p.name for p in a.glob("*.png")) == sorted(f.file for f in report_figures())
    assert sorted(p.stem for p in a.glob("*.pdf")) == sorted(p.stem for p in a.glob("*.png"))
    for figure in [*a.glob("*.png"), *a.glob("*.pdf")]:
        assert figure.read_bytes() == (b / figure.name).read_bytes(), figure.name


def test_report_rebuilds_from_archived_results_compressed_or_not(models, tmp_path):
    """The archive a report keeps of its results: gzip with deterministic bytes holding the
    file's own JSON; tools/report.py reads the folder of compressed files (--results_dir /
    --out_dir) and the one of plain files (--results / --out) to the same report."""
    plain = [save_results(r, tmp_path / "plain" / archive_name(r["model"]).removesuffix(".gz"))
             for r in models]  # fmt: skip
    archived = archive_results(plain, tmp_path / "gz")
    assert [p.name for p in archived] == [
        "centerpoint.results.json.gz",
        "cp-4f.results.json.gz",
        "phim.results.json.gz",
        "phim-lot.results.json.gz",
    ]
    for path, source in zip(archived, plain):
        data = path.read_bytes()
        assert data[:2] == b"\x1f\x8b" and data[4:8] == b"\0\0\0\0"  # gzip, time stamp 0
        assert gzip.decompress(data) == source.read_bytes()
    again = archive_results(plain, tmp_path / "gz_again")  # the same content, the same bytes
    assert [p.read_bytes() for p in again] == [p.read_bytes() for p in archived]
    loaded = {r["model"]: r for _, r in collect_results([tmp_path / "gz"])}
    assert loaded == {r["model"]: r for r in models}
    report = load_tool("report")
    report.main(["--results_dir", str(tmp_path / "gz"), "--out_dir", str(tmp_path / "a"),
                 "--latex"])  # fmt: skip
    report.main(["--results", str(tmp_path / "plain"), "--out_dir", str(tmp_path / "b"), "--latex"])
    text = (tmp_path / "a" / "report.md").read_text()
    assert "| CP-4f |" in text and "cp-4f.results.json.gz`" in text
    _same_report(tmp_path / "a", tmp_path / "b", (str(tmp_path / "gz"), str(tmp_path / "plain")))
    # archiving a smaller set removes the archived files of the models it no longer holds
    archive_results(plain[:2], tmp_path / "gz")
    assert sorted(p.name for p in (tmp_path / "gz").iterdir()) == [p.name for p in archived[:2]]
    with pytest.raises(ResultsError, match="would both be archived as .*phim-lot"):
        archive_results([plain[3], save_results({**models[0], "model": "PHiM LOT"},
                                                tmp_path / "x.json")], tmp_path / "gz")  # fmt: skip


@pytest.mark.parametrize(
    "content, match",
    [
        (lambda good: good[: len(good) // 2], "not a readable gzip file .*EOFError"),  # truncated
        (lambda good: b'{"model": "plain text"}', "not a readable gzip file .*BadGzipFile"),
        (lambda good: gzip.compress(b'{"model": ', mtime=0), "not valid JSON"),
        (lambda good: gzip.compress(b"\xff\xfe", mtime=0), "not UTF-8 text"),
    ],
)
def test_a_broken_archived_file_is_named(models, tmp_path, content, match):
    good = archive_results([save_results(models[0], tmp_path / "r.json")], tmp_path / "gz")[0]
    bad = tmp_path / "gz" / "bad.results.json.gz"
    bad.write_bytes(content(good.read_bytes()))
    with pytest.raises(ResultsError, match=rf"^{re.escape(str(bad))}: {match}"):
        collect_results([tmp_path / "gz"])


def test_reproduce_report_only_rebuilds_from_the_report_folder_alone(models, tmp_path):
    """A run record whose evaluation folders are gone (a clone of the committed report): the run's
    report is written again from the archived results run.json names, relative to its folder."""
    reproduce = load_tool("reproduce")
    out = tmp_path / "report"
    evaluated = [save_results(r, tmp_path / "output" / f"m{i}" / "results.json")
                 for i, r in enumerate(models)]  # fmt: skip
    runs = [{"config": r["config"], "results": str(p), "wall_s": 60.0}
            for r, p in zip(models, evaluated)]  # fmt: skip
    state = {"setting": {"data_path": "/data/val6"}, "command": "--out report", "jobs": 1,
             "threads": 2, "cpu_cores": 2, "machine": "x86_64", "cpus": ["cpu"],
             "total_wall_s": 240.0, "calls": 1, "runs": runs, "model_wall_s": {}}  # fmt: skip
    (out).mkdir()
    (out / "run.json").write_text(json.dumps(state))
    # archives, then reports; the run's results are read from under its --eval_dir only
    first = reproduce.main(
        ["--out_dir", str(out), "--report_only", "--eval_dir", str(tmp_path / "output")]
    )
    record = json.loads((out / "run.json").read_text())
    assert [r["archived"] for r in record["runs"]] == [
        f"results/{archive_name(r['model'])}" for r in models
    ]
    assert [r["results"] for r in record["runs"]] == [str(p) for p in evaluated]
    text = first["report"].read_text()
    assert f"| `{out / 'results' / 'centerpoint.results.json.gz'}` |" in text  # the source
    assert "## How these results were produced" in text
    for path in evaluated:
        path.unlink()
    (out / "report.md").unlink()
    again = reproduce.main(["--out_dir", str(out), "--report_only"])
    assert again["report"].read_text() == text
    # the tables and figures also come back from the archive alone, through tools/report.py
    load_tool("report").main(["--results", str(out / "results"), "--out_dir", str(tmp_path / "t")])
    rebuilt = (tmp_path / "t" / "report.md").read_text().splitlines()
    # the tables with a row per model (their order: the run's, not the file names')
    tables = text.split("\n## Models")[1].split("\n## Paired model")[0]
    tables += text.split("\n## Per-model results")[1].split("\n## How these")[0]
    rows = [line for line in tables.splitlines() if line.startswith("| ")]
    assert len(rows) > 50 and set(rows) <= set(rebuilt)
    (out / "results" / "cp-4f.results.json.gz").unlink()
    with pytest.raises(ResultsError, match=r"runs\[1\] \(cfgs/CP-4f.yaml\): neither its results"):
        reproduce.main(["--out_dir", str(out), "--report_only"])


def _run(results: dict, path: Path, archived: str | None = None) -> dict:
    run = {"config": results["config"], "results": str(path), "wall_s": 60.0}
    return run if archived is None else {**run, "archived": archived}


@contextlib.contextmanager
def _warnings_of(logger: logging.Logger):
    """The messages ``logger`` warns with inside the block (whatever the handlers above it)."""
    messages: list[str] = []
    handler = logging.Handler(logging.WARNING)
    handler.emit = lambda record: messages.append(record.getMessage())
    logger.addHandler(handler)
    try:
        yield messages
    finally:
        logger.removeHandler(handler)


def test_a_run_record_cannot_make_the_report_read_a_results_file_elsewhere(models, tmp_path):
    """run.json is data: a run's ``results`` that lies outside the evaluations' root (--eval_dir),
    also through a symlink inside it, is not read. With no archived copy that is an error naming
    the run, before anything is archived; with one, the archived copy is used, with a warning."""
    root, out = tmp_path / "output", tmp_path / "report"
    inside = save_results(models[0], root / "m0" / "results.json")
    secret = save_results(models[1], tmp_path / "elsewhere" / "results.json")
    (root / "m1").symlink_to(secret.parent)  # leads out of the root
    for path in (secret, root / "m1" / "results.json"):
        runs = [_run(models[0], inside), _run(models[1], path)]
        with pytest.raises(ResultsError) as err:
            archive_run_results(runs, out, eval_root=root)
        assert str(err.value) == (
            f"{out / 'run.json'}: runs[1] (cfgs/CP-4f.yaml): its results file {path} lies outside "
            f"the evaluations' root {root} (symlinks resolved) and is not read, and it has no "
            "archived copy; pass the --eval_dir the run evaluated into"
        )
        assert not (out / "results").exists()  # nothing archived, the secret not copied in
    archive_results([save_results(models[1], tmp_path / "copy.json")], out / "results")
    secret.write_text("{not JSON: reading it would be an error")
    runs = [_run(models[0], inside), _run(models[1], secret, "results/cp-4f.results.json.gz")]
    with _warnings_of(logging.getLogger("pcdet_atlas.evaluation.results.archive")) as warned:
        kept = archive_run_results(runs, out, eval_root=root)
    assert [r["archived"] for r in kept] == [
        "results/centerpoint.results.json.gz",
        "results/cp-4f.results.json.gz",
    ]
    assert warned == [
        f"{out / 'run.json'}: runs[1] (cfgs/CP-4f.yaml): its results file {secret} lies outside "
        f"the evaluations' root {root} (symlinks resolved) and is not read; the archived "
        f"{out / 'results' / 'cp-4f.results.json.gz'} is used (pass the --eval_dir the run "
        "evaluated into to read it)"
    ]
    # the tool's --eval_dir is that root: its default (<repo>/output) does not hold tmp_path
    reproduce = load_tool("reproduce")
    state = {"setting": {"data_path": "/data/val6"}, "command": "--out report", "jobs": 1,
             "threads": 2, "cpu_cores": 2, "machine": "x86_64", "cpus": ["cpu"],
             "total_wall_s": 120.0, "calls": 1, "model_wall_s": {},
             "runs": [_run(models[0], inside)]}  # fmt: skip
    (out / "run.json").write_text(json.dumps(state))
    outside = r"runs\[0\] \(cfgs/CenterPoint.yaml\): its results file .* lies outside .*/output "
    with pytest.raises(ResultsError, match=outside):
        reproduce.main(["--out_dir", str(out), "--report_only"])
    reproduce.main(["--out_dir", str(out), "--report_only", "--eval_dir", str(root)])


@pytest.mark.parametrize(
    "archived, error, match",
    [
        ("results/..", UnsafePathError, r"archived file name '\.\.' \(from .*run\.json: "
         r"runs\[0\]\.archived\) is not one file"),
        ("results/link.results.json.gz", UnsafePathError, r"results/link\.results\.json\.gz "
         r"\(from .*run\.json: runs\[0\]\.archived\) resolves to .*victim\.results\.json\.gz, "
         "outside its root"),
        ("../victim.results.json.gz", ResultsError, r"runs\[0\]\.archived holds "
         r"'\.\./victim\.results\.json\.gz', expected a file name under results/"),
    ],
)  # fmt: skip
def test_an_archived_path_of_run_json_stays_in_the_report_folder(
    models, tmp_path, archived, error, match
):
    out = tmp_path / "report"
    victim = archive_results([save_results(models[0], tmp_path / "r.json")], tmp_path)[0]
    victim = victim.rename(tmp_path / "victim.results.json.gz")
    (out / "results").mkdir(parents=True)
    (out / "results" / "link.results.json.gz").symlink_to(victim)
    runs = [_run(models[0], tmp_path / "gone" / "results.json", archived)]
    with pytest.raises(error, match=match):
        archive_run_results(runs, out, eval_root=tmp_path / "output")


def test_a_symlinked_archive_folder_is_refused_before_anything_is_written_or_removed(
    models, tmp_path
):
    """A received report folder whose ``results/`` links to another folder: archiving would
    remove that folder's ``*.results.json.gz`` of other models and write into it."""
    other = tmp_path / "other"
    kept = archive_results([save_results(models[1], tmp_path / "r1.json")], other)[0]
    out = tmp_path / "report"
    out.mkdir()
    (out / "results").symlink_to(other)
    runs = [_run(models[0], save_results(models[0], tmp_path / "output" / "results.json"))]
    refused = f"{out / 'results'}: a symlink to {other}, expected the folder of a report's archived"
    with pytest.raises(UnsafePathError, match=f"^{re.escape(refused)}"):
        archive_run_results(runs, out, eval_root=tmp_path / "output")
    assert sorted(p.name for p in other.iterdir()) == [kept.name]


def test_report_files_replace_planted_symlinks_instead_of_writing_through_them(
    models, tmp_path, monkeypatch
):
    """A received report folder (``--out_dir``, ``reproduce.py --report_only``) with
    ``report.md -> ~/.bashrc``: the report replaces the link, the target keeps its content."""
    monkeypatch.setattr(report_module, "report_figures", lambda: [])  # the tables only: fast
    out = tmp_path / "report"
    out.mkdir()
    for name in ("report.md", "report.tex"):
        (tmp_path / f"victim_{name}").write_text("IMPORTANT USER DATA\n")
        (out / name).symlink_to(tmp_path / f"victim_{name}")
    written = write_report(models, out, latex=True)
    for name in ("report.md", "report.tex"):
        assert (tmp_path / f"victim_{name}").read_text() == "IMPORTANT USER DATA\n"
        assert not (out / name).is_symlink()
    assert "| CenterPoint |" in written["report"].read_text()
    assert "\\begin{tabular}" in written["latex"].read_text()


def test_the_test_log_of_reproduce_refuses_a_symlink_and_appends_or_starts_anew(tmp_path):
    open_log = load_tool("reproduce").open_log
    victim = tmp_path / "victim"
    victim.write_text("IMPORTANT USER DATA\n")
    log = tmp_path / "reproduce.log"
    log.symlink_to(victim)
    for append in (True, False):
        with pytest.raises(NotARegularFileError, match=rf"^{re.escape(str(log))}: a symlink to "):
            open_log(log, append)
    assert victim.read_text() == "IMPORTANT USER DATA\n"
    log.unlink()
    for append, text in ((False, "one\n"), (True, "two\n")):
        with open_log(log, append) as stream:
            stream.write(text)
    assert log.read_text() == "one\ntwo\n"
    with open_log(log, append=False) as stream:
        stream.write("three\n")
    assert log.read_text() == "three\n"


def _seeded(results: dict, seed: int | None, digest: str | None = "c" * 64) -> dict:
    return {**results, "training_seed": seed, "model_sha256": digest}


def test_seed_to_seed_spread(models, tmp_path):
    """Two results of one model config with different training seeds (the second: CenterPoint
    drawn again at slightly other rates): per variant both ASRs with their intervals and the
    paired difference; per rank group the difference of the means; each other pair of models
    classed against the spread exactly as their paired differences and intervals say."""
    seed_a = _seeded(models[0], 666)
    seed_b = _seeded(model("CenterPoint seed 2", 0.61, 0.35, 0.75, 40.0), 2)
    sturdy = model("Sturdy", 0.70, 0.0, 0.0, 50.0)  # never attacked successfully
    results_list = [seed_a, *models[1:], sturdy, seed_b]
    text = write_report(results_list, tmp_path)["report"].read_text()
    part = report_part(text, "## Seed-to-seed spread")
    tables = part.split("\n\n| ")
    per_variant = md_table("| " + tables[1].split("\n\n")[0])
    a_label, b_label = "CenterPoint (seed 666)", "CenterPoint seed 2 (seed 2)"
    diff_col = f"{b_label} - seed 666"
    assert set(per_variant) == {"Rel-Fixed Easy", "Global Hard", "Removal 10", "Removal 40"}
    for name, label in (("inj_global_hard", "Global Hard"), ("rem_40", "Removal 40")):
        row = per_variant[label]
        for r, col in ((seed_a, a_label), (seed_b, b_label)):
            entry = r["variants"][name]
            lo, hi = entry["asr_ci"]
            assert row[f"{col} ASR"] == f"{entry['asr']:.2f} [{lo:.2f}, {hi:.2f}]"
        paired = paired_from_results([seed_a, seed_b], [name])
        d = seed_b["variants"][name]["asr"] - seed_a["variants"][name]["asr"]
        lo, hi = paired["ci"][seed_b["model"]][seed_a["model"]]
        assert row[diff_col] == f"{d:+.2f} [{lo:+.2f}, {hi:+.2f}]"
    per_group = md_table("| " + tables[2].split("\n\n")[0])
    spread = {}
    for group, names in (("injection", ["inj_rel_easy", "inj_global_hard"]),
                         ("removal", ["rem_10", "rem_40"])):  # fmt: skip
        d = np.mean([seed_b["variants"][n]["asr"] - seed_a["variants"][n]["asr"] for n in names])
        assert per_group[group][diff_col].startswith(f"{d:+.2f} [")
        spread[group] = abs(d)
    # the statement: every pair of different models in exactly the class its numbers put it in
    statement = part.split("pairs of one model's seeds are left out:")[1]
    classes = set()
    variants, _ = queries.ranked_variants(results_list)  # CP-4f lacks rem_40: over 3 variants
    assert variants == ["inj_rel_easy", "inj_global_hard", "rem_10"]
    for group, names in (("injection", variants[:2]), ("removal", variants[2:])):
        line = next(x for x in statement.splitlines() if x.startswith(f"- **{group}**"))
        s = abs(queries.mean_asr(seed_b, names) - queries.mean_asr(seed_a, names))
        assert f"(seed spread {s:.2f}:" in line
        beyond = line.split("Interval beyond the spread: ")[1].split(". Above")[0]
        above = line.split("its interval not: ")[1].split(". Within")[0]
        within = line.split("Within the spread: ")[1]
        out = paired_from_results(results_list, names)
        ms = out["models"]
        for i, x in enumerate(ms):
            for y in ms[i + 1 :]:
                a, b = (x, y) if out["difference"][x][y] >= 0 else (y, x)
                d, (lo, hi) = out["difference"][a][b], out["ci"][a][b]
                cell = f"{a} - {b} {d:+.2f} [{lo:+.2f}, {hi:+.2f}]"
                if {a, b} == {seed_a["model"], seed_b["model"]}:
                    assert cell not in line
                    continue
                kind = "beyond" if lo > s and d > s else "above" if d > s else "within"
                assert cell in {"beyond": beyond, "above": above, "within": within}[kind], cell
                classes.add(kind)
                assert sum(cell in part for part in (beyond, above, within)) == 1
    assert classes == {"beyond", "above", "within"}  # the fixture has pairs of each class
    assert seed_spread_text(models) is None  # no seed pair: no section
    # the ranks and their fit count a model once: its retraining is left out, and named
    left_out = ("One result per model config: left out CenterPoint seed 2 (a retraining of "
                "CenterPoint with seed 2)")  # fmt: skip
    ranks = report_part(text, "## Robustness ranks")
    assert left_out in ranks and "CenterPoint seed 2 |" not in ranks.split(left_out)[0]
    assert left_out in report_part(text, "### Robustness rank correlation")
    kept, note = one_per_model_config(results_list)
    assert kept == results_list[:-1] and note.startswith(left_out)
    assert one_per_model_config(models) == (list(models), None)


def test_seed_pairs_need_a_known_and_different_seed():
    a = _seeded(model("A", 0.6, 0.3, 0.8, 40.0), 1)
    assert seed_groups([a, _seeded(model("B", 0.6, 0.3, 0.8, 40.0), 2)])[0][0][1]["model"] == "B"
    groups, notes = seed_groups([a, _seeded(model("B", 0.6, 0.3, 0.8, 40.0), None)])
    assert not groups and "the training seed of B is not recorded" in notes[0]
    groups, notes = seed_groups([a, _seeded(model("B", 0.6, 0.3, 0.8, 40.0), 1)])
    assert not groups and "share a model config and a training seed" in notes[0]
    other_config = _seeded(model("B", 0.6, 0.3, 0.8, 40.0), 2, digest="d" * 64)
    assert seed_groups([a, other_config]) == ([], [])
    assert seed_spread_text([a, other_config]) is None
    assert seed_spread_text([a, _seeded(model("B", 0.6, 0.3, 0.8, 40.0), None)]).startswith(
        "No seed pair to measure."
    )
