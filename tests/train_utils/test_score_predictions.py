"""Scoring predictions made anywhere (``tools/evaluate_predictions.py``): the shipped CP-4f's own
``result.pkl`` files, and the same predictions written as JSON, npz and Waymo's submission
``.bin``, score exactly as the evaluation
scored them (ASR, targets, successes and per-run counts equal; AP within 1e-9); bad input is one
clear error naming the file, the frame and the field."""

from __future__ import annotations

import copy
import json
import logging
import re
from pathlib import Path

import numpy as np
import pytest

from pcdet_atlas.attacks.atlas_dataset import AtlasWaymoDataset
from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.datasets.waymo_submission import write_waymo_bin
from pcdet_atlas.evaluation import build_results, load_results, save_results
from pcdet_atlas.evaluation.results.schema import METRIC_KEYS
from pcdet_atlas.models import build_network_from_config
from pcdet_atlas.train_utils.atlas_eval import EvalContext, evaluate_variant
from pcdet_atlas.train_utils.eval_caches import EvalCaches
from pcdet_atlas.train_utils.score_predictions import (
    PredictionError,
    is_generated_spec,
    load_generated_variant,
    match_predictions,
    score_predictions,
)
from pcdet_atlas.utils.common import load_tool, save_pickle
from pcdet_atlas.utils.safe_pickle import RefusedGlobalError, load_pickle

CFG = REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "cp4f.yaml"
DATA_CFG = REPO_ROOT / "cfgs" / "dataset_configs" / "synthetic_waymo_multiframe.yaml"
ATTACKS = REPO_ROOT / "cfgs" / "attacks"
CLASSES = ["Vehicle", "Pedestrian", "Cyclist"]
INTERVAL = 2  # every 2nd frame of the 70-frame val sequence: 16 in the attack run 32..63
SUBSET = ["DATA_CONFIG.SAMPLED_INTERVAL", f"train:1,test:{INTERVAL}",
          "DATA_CONFIG.POINT_CLOUD_RANGE", "-20.48,-20.48,-2,20.48,20.48,4"]  # fmt: skip


@pytest.fixture(scope="module")
def normal_run(synthetic_root, injection, tmp_path_factory):
    """CP-4f evaluated as tools/test.py evaluates it (clean first, its predictions reused and
    scoring the removal confidence) on clean, an injection and a removal variant; each
    variant's ``result.pkl`` and results.json entry."""
    tmp = tmp_path_factory.mktemp("score_predictions")
    inj = tmp / "inj_global_hard.yaml"
    inj.write_text(
        f"_BASE_CONFIG_: {ATTACKS / 'inj_global_hard.yaml'}\n"
        f"TRACE_LIBRARY:\n  PATH: {injection.TRACE_LIBRARY.PATH}\n  MIN_POINTS: 100\n"
    )
    cfg = cfg_from_yaml_file(CFG)
    model = build_network_from_config(cfg)
    model.load_params_from_file(REPO_ROOT / cfg.ATLAS.CHECKPOINT)
    model.eval()
    data_cfg = copy.deepcopy(cfg.DATA_CONFIG)
    data_cfg.DATA_PATH = str(synthetic_root)
    data_cfg.SAMPLED_INTERVAL = {"train": 1, "test": INTERVAL}
    data_cfg.POINT_CLOUD_RANGE = [-20.48, -20.48, -2.0, 20.48, 20.48, 4.0]
    context = EvalContext(
        data_cfg=data_cfg, class_names=cfg.CLASS_NAMES, device=__import__("torch").device("cpu"),
        temporal_window=cfg.ATLAS.TEMPORAL_WINDOW, show_progress=False,
    )  # fmt: skip
    caches = EvalCaches(reuse=True)
    entries, files = {}, {}
    for variant, attack in [("clean", ATTACKS / "clean.yaml"), ("inj_global_hard", inj),
                            ("rem_40", ATTACKS / "rem_40.yaml")]:  # fmt: skip
        entry, det_annos = evaluate_variant(
            model, variant, attack, context, caches=caches, out_dir=tmp / variant
        )
        if variant == "clean":
            caches.keep_clean(det_annos)
        entries[variant] = entry
        files[variant] = tmp / variant / "result.pkl"
    return {"tmp": tmp, "entries": entries, "files": files, "inj": inj, "root": synthetic_root}


def tool_args(run, out, predictions):
    return ["--data_cfg", str(CFG), "--data_path", str(run["root"]),
            "--predictions", *predictions, "--out_dir", str(out), "--set", *SUBSET]  # fmt: skip


def assert_same_scores(got: dict, want: dict):
    """Every field of the entry equal, the Waymo AP/APH within 1e-9 (the evaluation's reuse
    counts and ``extra`` are the run's, not the predictions')."""
    runtime = ("extra", "num_reused_frames", "num_recomputed_frames")
    assert set(got) == set(want)
    for key in set(want) - set(runtime) - set(METRIC_KEYS) - {"per_class"}:
        assert got[key] == want[key], key
    for key in METRIC_KEYS:
        assert got[key] == pytest.approx(want[key], abs=1e-9), key
    for name, levels in want["per_class"].items():
        for k, v in levels.items():
            if v is None:
                assert got["per_class"][name][k] is None
            else:
                assert got["per_class"][name][k] == pytest.approx(v, abs=1e-9), (name, k)


def to_json(path: Path, out: Path, *, drop_frame_id=False) -> Path:
    """A result.pkl as the documented JSON: per frame frame_id (or metadata), name, score,
    boxes_lidar; float32 values written as their float64 values (exact)."""
    frames = []
    for anno in load_pickle(path):
        frame = {"name": anno["name"].tolist(), "score": anno["score"].astype(float).tolist(),
                 "boxes_lidar": anno["boxes_lidar"].astype(float).tolist()}  # fmt: skip
        if drop_frame_id:
            frame["metadata"] = dict(anno["metadata"])
        else:
            frame["frame_id"] = anno["frame_id"]
        frames.append(frame)
    out.write_text(json.dumps(frames[::-1]))  # any order
    return out


@pytest.mark.slow
def to_npz(path: Path, out: Path) -> Path:
    """A result.pkl as a folder of one .npz per frame (frame_id as a 0-d string array)."""
    out.mkdir()
    for k, anno in enumerate(load_pickle(path)):
        np.savez(out / f"{k:04d}.npz", frame_id=np.array(anno["frame_id"]), name=anno["name"],
                 score=anno["score"], boxes_lidar=anno["boxes_lidar"])  # fmt: skip
    return out


def test_result_pkl_and_json_score_as_the_evaluation(normal_run, tmp_path):
    run, files = normal_run, normal_run["files"]
    want = run["entries"]
    assert want["inj_global_hard"]["num_targets"] > 0 and want["rem_40"]["num_targets"] > 0
    tool = load_tool("evaluate_predictions")
    preds = [f"clean={files['clean']}", f"{run['inj']}={files['inj_global_hard']}",
             f"rem_40={files['rem_40']}"]  # fmt: skip
    results = tool.main(tool_args(run, tmp_path / "pkl", preds))
    written = load_results(tmp_path / "pkl" / "results.json")  # validates the schema
    assert written["variants"].keys() == results["variants"].keys() == want.keys()
    for variant, entry in want.items():
        assert_same_scores(written["variants"][variant], entry)
    assert written["model"] == "CP-4f" and written["checkpoint"] is None
    assert written["variants"]["rem_40"]["confidence"] is not None  # needs the clean run
    report = load_tool("report")
    report.main(["--results", str(tmp_path / "pkl"), "--out_dir", str(tmp_path / "rep")])
    assert "CP-4f" in (tmp_path / "rep" / "report.md").read_text()

    # JSON, clean frames found by (context_name, timestamp_micros) instead of frame_id
    json_preds = [
        f"clean={to_json(files['clean'], tmp_path / 'clean.json', drop_frame_id=True)}",
        f"{run['inj']}={to_json(files['inj_global_hard'], tmp_path / 'inj.json')}",
        f"rem_40={to_json(files['rem_40'], tmp_path / 'rem.json')}",
    ]
    tool.main(tool_args(run, tmp_path / "json", json_preds))
    written = load_results(tmp_path / "json" / "results.json")
    for variant, entry in want.items():
        assert_same_scores(written["variants"][variant], entry)

    # npz per frame
    npz_preds = [f"clean={to_npz(files['clean'], tmp_path / 'clean_npz')}",
                 f"rem_40={to_npz(files['rem_40'], tmp_path / 'rem_npz')}"]  # fmt: skip
    written = tool.main(tool_args(run, tmp_path / "npz", npz_preds))
    for variant in ("clean", "rem_40"):
        assert_same_scores(written["variants"][variant], want[variant])

    # a DATA_CONFIG file (not a model config): classes and lifecycle window from flags
    data_args = ["--data_cfg", str(DATA_CFG), "--data_path", str(run["root"]),
                 "--temporal_window", "4", "--class_names", ",".join(CLASSES),
                 "--predictions", *json_preds, "--out_dir", str(tmp_path / "data_cfg"),
                 "--set", "SAMPLED_INTERVAL", f"train:1,test:{INTERVAL}",
                 "POINT_CLOUD_RANGE", "-20.48,-20.48,-2,20.48,20.48,4"]  # fmt: skip
    written = tool.main(data_args)
    assert written["model"] == "predictions"
    for variant, entry in want.items():
        assert_same_scores(written["variants"][variant], entry)


def test_waymo_submission_bin_scores_as_the_evaluation(normal_run, tmp_path):
    """The predictions as a submission .bin (no object for a frame without detections; found by
    context name and timestamp) give the evaluation's entries; the format is told by content."""
    run, files = normal_run, normal_run["files"]
    want = run["entries"]
    bins = {v: write_waymo_bin(load_pickle(f), tmp_path / f"{v}.bin") for v, f in files.items()}
    bins["rem_40"] = bins["rem_40"].rename(tmp_path / "rem_40.objects")  # no extension
    preds = [f"clean={bins['clean']}", f"{run['inj']}={bins['inj_global_hard']}",
             f"rem_40={bins['rem_40']}"]  # fmt: skip
    written = load_tool("evaluate_predictions").main(tool_args(run, tmp_path / "bin", preds))
    for variant, entry in want.items():
        assert_same_scores(written["variants"][variant], entry)


def test_attack_records_of_a_generate_atlas_output_score_as_drawn_on_the_fly(
    normal_run, tmp_path, monkeypatch
):
    """A variant named by its tools/data/generate_atlas.py output folder takes the targets, runs and
    lifecycle from the records written there (nothing simulated) and scores exactly as the
    attack drawn on the fly: the evaluation's entries, the same attack fingerprint."""
    run, files = normal_run, normal_run["files"]
    data_yaml = tmp_path / "source.yaml"
    data_yaml.write_text(f"_BASE_CONFIG_: {DATA_CFG}\nDATA_PATH: {run['root']}\n")
    generate = load_tool("data/generate_atlas")
    folders = {}
    for variant, attack in [("inj_global_hard", run["inj"]), ("rem_40", ATTACKS / "rem_40.yaml")]:
        folders[variant] = tmp_path / variant
        generate.main(["--data_cfg", str(data_yaml), "--attack", str(attack),
                       "--out_dir", str(folders[variant])])  # fmt: skip

    def no_simulation(self, *args, **kwargs):
        raise AssertionError("a generated variant's records are read, not simulated")

    monkeypatch.setattr(AtlasWaymoDataset, "simulate_frame", no_simulation)
    preds = [f"clean={files['clean']}", f"{folders['inj_global_hard']}={files['inj_global_hard']}",
             f"{folders['rem_40']}={files['rem_40']}"]  # fmt: skip
    tool = load_tool("evaluate_predictions")
    written = tool.main(tool_args(run, tmp_path / "scored", preds))
    for variant, entry in run["entries"].items():
        assert_same_scores(written["variants"][variant], entry)
    assert written["variants"]["rem_40"]["extra"]["attack_records"].startswith(str(tmp_path))
    monkeypatch.undo()
    on_the_fly = tool.main(tool_args(run, tmp_path / "fly", [f"clean={files['clean']}",
                                     f"rem_40={files['rem_40']}"]))  # fmt: skip
    assert (written["variants"]["rem_40"]["extra"]["attack_sha256"]
            == on_the_fly["variants"]["rem_40"]["extra"]["attack_sha256"])  # fmt: skip

    # records generated from other labels (a same-named sequence of another dataset) are refused
    meta = folders["rem_40"] / "atlas_attack_metadata.pkl"
    summary = load_pickle(meta)
    recorded = summary["source_label_sha256"]
    assert recorded and all(re.fullmatch(r"[0-9a-f]{64}", sha) for sha in recorded.values())
    save_pickle({**summary, "source_label_sha256": dict.fromkeys(recorded, "0" * 64)}, meta)
    with pytest.raises(PredictionError, match=r"atlas_attack_metadata\.pkl: generated from other "
                       r"labels than the test split's for \d+ of its \d+ sequences"):  # fmt: skip
        tool.main(tool_args(run, tmp_path / "other", [f"{folders['rem_40']}={files['rem_40']}"]))
    save_pickle(summary, meta)

    # a bare variant name is the attack even beside a folder of that name (predictions in it)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "clean").mkdir()
    (tmp_path / "clean" / "result.pkl").write_bytes(files["clean"].read_bytes())
    assert not is_generated_spec("clean") and is_generated_spec("./clean")
    written = tool.main(tool_args(run, tmp_path / "cwd", ["clean=clean/result.pkl"]))
    assert_same_scores(written["variants"]["clean"], run["entries"]["clean"])

    # records of another split, and a folder that is no generator output
    (tmp_path / "empty").mkdir()
    with pytest.raises(PredictionError, match=r"empty: no atlas_attack_metadata\.pkl"):
        tool.main(tool_args(run, tmp_path / "bad", [f"{tmp_path / 'empty'}={files['rem_40']}"]))
    meta = load_pickle(folders["rem_40"] / "atlas_attack_metadata.pkl")
    meta["frames"] = dict(list(meta["frames"].items())[1:])
    save_pickle(meta, folders["rem_40"] / "atlas_attack_metadata.pkl")
    with pytest.raises(PredictionError, match=r"no attack record of 1 of the test split's"):
        tool.main(
            tool_args(
                run,
                tmp_path / "bad",
                [f"clean={files['clean']}", f"{folders['rem_40']}={files['rem_40']}"],
            )
        )
    assert not (tmp_path / "bad").exists()


def test_scoring_benchmark_runs_on_an_evaluation_folder(normal_run, tmp_path):
    """tools/bench/bench_scoring.py times both sides on a tools/test.py-like folder and finds the
    scored entries equal to the run's."""
    run = normal_run
    entries = {v: run["entries"][v] for v in ("clean", "rem_40")}
    for variant in entries:
        (tmp_path / variant).mkdir()
        (tmp_path / variant / "result.pkl").write_bytes(run["files"][variant].read_bytes())
    results = build_results(
        model="CP-4f", config=str(CFG), checkpoint=None, class_names=CLASSES, variants=entries
    )
    save_results(results, tmp_path / "results.json")
    out = load_tool("bench/bench_scoring").main(
        [
            "--cfg",
            str(CFG),
            "--eval_dir",
            str(tmp_path),
            "--data_path",
            str(run["root"]),
            "--set",
            *SUBSET,
        ]  # fmt: skip
    )
    assert out["equal"] and out["metric_s"] > 0 and out["scoring_s"] > 0


@pytest.mark.slow
def test_a_changed_prediction_changes_the_score(normal_run, tmp_path):
    """The scores follow the predictions: with no detections on the spoofed frames, every
    target of the removal succeeds (the evaluation measured fewer)."""
    run = normal_run
    annos = load_pickle(run["files"]["rem_40"])
    want = run["entries"]["rem_40"]
    for anno in annos:
        if anno["attack"]["spoofed"]:
            for key in ("name", "score", "boxes_lidar", "pred_labels"):
                anno[key] = anno[key][:0]
    save_pickle(annos, tmp_path / "emptied.pkl")
    results = score_predictions(
        run_data_cfg(run), CLASSES,
        {"clean": run["files"]["clean"], "rem_40": tmp_path / "emptied.pkl"}, tmp_path,
        model="m", config="c", temporal_window=4,
    )  # fmt: skip
    got = results["variants"]["rem_40"]
    assert want["num_targets"] == got["num_targets"] == got["num_success"] == 16
    assert want["num_success"] < 16 and got["asr"] == 1.0


def run_data_cfg(run):
    data_cfg = copy.deepcopy(cfg_from_yaml_file(CFG).DATA_CONFIG)
    data_cfg.DATA_PATH = str(run["root"])
    data_cfg.SAMPLED_INTERVAL = {"train": 1, "test": INTERVAL}
    return data_cfg


@pytest.mark.slow
def test_removal_without_clean_predictions_is_an_error(normal_run, tmp_path):
    with pytest.raises(PredictionError, match=r"rem_40.*clean=FILE"):
        score_predictions(
            run_data_cfg(normal_run), CLASSES,
            {"rem_40": normal_run["files"]["rem_40"]}, tmp_path, model="m", config="c",
        )  # fmt: skip
    assert not (tmp_path / "results.json").exists()


def _infos():
    return [{"frame_id": f"seq_{i:03d}", "metadata": {"context_name": "ctx",
             "timestamp_micros": 1000 + i}} for i in range(3)]  # fmt: skip


def _frame(i, **over):
    frame = {
        "frame_id": f"seq_{i:03d}",
        "name": np.array(["Vehicle"]),
        "score": np.array([0.5], np.float32),
        "boxes_lidar": np.zeros((1, 7), np.float32),
    }
    frame.update(over)
    return frame


@pytest.mark.parametrize(
    "frames, pattern",
    [
        ([_frame(0), _frame(1)], r"f\.pkl: 1 of the test split's 3 frames .* first 'seq_002'"),
        ([_frame(0), _frame(1), _frame(2), _frame(1)],
         r"f\.pkl \[frame 3 \('seq_001'\)\]: frame 'seq_001' is there twice \(also frame 1"),
        ([_frame(0), _frame(1), _frame(7)], r"\[frame 2 \('seq_007'\)\]: field 'frame_id' 'seq_007'"
         r" is not a frame of the test split"),
        ([_frame(0), _frame(1), _frame(2, frame_id="x")],
         r"\[frame 2 \('x'\)\]: field 'frame_id' 'x' is not a frame"),
        ([_frame(0), _frame(1), _frame(2, score=np.array([np.nan]))],
         r"\[frame 2 \('seq_002'\)\]: field 'score' holds a NaN or infinite value"),
        ([_frame(0), _frame(1), _frame(2, boxes_lidar=np.array([[0, 0, 0, 1, 1, np.inf, 0]]))],
         r"\[frame 2 \('seq_002'\)\]: field 'boxes_lidar' holds a NaN or infinite value"),
        ([_frame(0), _frame(1, boxes_lidar=np.zeros((1, 8)))],
         r"\[frame 1 \('seq_001'\)\]: field 'boxes_lidar' has shape \(1, 8\), expected \(1, 7\) "
         r"or \(1, 9\)"),
        ([_frame(0, name=np.array(["Truck"]))],
         r"\[frame 0 \('seq_000'\)\]: field 'name' holds unknown class name\(s\) \['Truck'\]"),
        ([_frame(0), _frame(1, score=np.array([1.5]))],
         r"\[frame 1 \('seq_001'\)\]: field 'score' holds 1\.5, outside \[0, 1\]"),
        ([_frame(0), _frame(1, score=np.array([-0.1]))], r"field 'score' holds -0\.1"),
        ([{k: v for k, v in _frame(0).items() if k != "frame_id"}],
         r"\[frame 0\]: no field 'frame_id' and no 'metadata'"),
        ([{k: v for k, v in _frame(0).items() if k != "frame_id"}
          | {"metadata": {"context_name": "ctx", "timestamp_micros": 5}}],
         r"field 'metadata' \(context_name 'ctx', timestamp_micros 5\) is not a frame"),
        ([_frame(0, metadata={"context_name": "ctx", "timestamp_micros": 1001})],
         r"field 'metadata' .* names another frame than its frame_id 'seq_000'"),
        ([_frame(0, metadata={"context_name": "other", "timestamp_micros": 1000})],
         r"field 'metadata' \(context_name 'other', timestamp_micros 1000\) is not a frame"),
        ([_frame(0, pred_labels=np.array([2]))], r"field 'pred_labels' disagrees with 'name'"),
        ([_frame(0), "frame"], r"\[frame 1\]: a str, expected a dict"),
    ],
)  # fmt: skip
def test_bad_predictions_are_clear_errors(frames, pattern):
    with pytest.raises(PredictionError, match=pattern):
        match_predictions(frames, _infos(), CLASSES, "f.pkl")


def test_absent_frames_of_a_submission_are_frames_without_detections(caplog, monkeypatch):
    monkeypatch.setattr(logging.getLogger("pcdet_atlas"), "propagate", True)  # create_logger: off
    infos = [{**info, "point_cloud": {"lidar_sequence": "seq_a" if i < 2 else "seq_b"}}
             for i, info in enumerate(_infos())]  # fmt: skip
    with caplog.at_level(logging.WARNING, logger="pcdet_atlas"):
        out = match_predictions(
            [_frame(0), _frame(2)], infos, CLASSES, "f.bin", absent_is_empty=True
        )
    assert "f.bin: 1 of the test split's 3 frames have no predictions there" in caplog.text
    assert out[1]["frame_id"] == "seq_001" and out[1]["boxes_lidar"].shape == (0, 7)
    assert out[1]["name"].shape == out[1]["score"].shape == out[1]["pred_labels"].shape == (0,)
    with pytest.raises(PredictionError, match=r"f\.bin: 1 of the test split's 2 sequences have "
                       r"no detection in any frame, the first 'seq_b'"):  # fmt: skip
        match_predictions([_frame(0)], infos, CLASSES, "f.bin", absent_is_empty=True)
    with pytest.raises(PredictionError, match=r"1 of the test split's 3 frames have no pred"):
        match_predictions([_frame(0), _frame(2)], infos, CLASSES, "f.pkl")


@pytest.mark.parametrize(
    "frames, pattern",
    [
        ([], r"expected a dict with 'variant' \(a name\) and 'frames'"),
        ({"seq_000": {"spoofed": True}, "seq_001": [1, 2]},
         r"'frames'\['seq_001'\] is a list, expected a dict \(the frame's attack record\)"),
    ],
)  # fmt: skip
def test_generated_variant_records_must_be_dicts(tmp_path, frames, pattern):
    """Each attack record of a generate_atlas output is a dict, or an error naming the file
    and the frame (``{**record}`` of a list was a bare TypeError when the variant was scored)."""
    meta = save_pickle({"variant": "rem_40", "attack_cfg": {}, "frames": frames},
                       tmp_path / "atlas_attack_metadata.pkl")  # fmt: skip
    (tmp_path / "atlas_attack.yaml").write_text("NAME: rem_40\n")
    with pytest.raises(PredictionError, match=rf"{re.escape(str(meta))}: {pattern}"):
        load_generated_variant(tmp_path)


def test_frames_are_matched_in_any_order_and_by_time():
    by_time = {k: v for k, v in _frame(0).items() if k != "frame_id"}
    by_time["metadata"] = {"context_name": "ctx", "timestamp_micros": 1000}
    empty = _frame(1, name=[], score=[], boxes_lidar=[])
    out = match_predictions([_frame(2), empty, by_time], _infos(), CLASSES, "f.json")
    assert [a["frame_id"] for a in out] == ["seq_000", "seq_001", "seq_002"]
    assert out[1]["boxes_lidar"].shape == (0, 7) and out[0]["pred_labels"].tolist() == [1]
    assert out[0]["score"].dtype == np.float32


@pytest.mark.slow
def test_files_that_are_not_predictions_are_named(tmp_path, normal_run):
    from malicious_files import malicious_pickle

    evil = malicious_pickle(tmp_path / "evil.pkl", tmp_path / "ran")
    args = dict(model="m", config="c")
    cfg = run_data_cfg(normal_run)
    with pytest.raises(RefusedGlobalError, match="evil.pkl"):
        score_predictions(cfg, CLASSES, {"clean": evil}, tmp_path, **args)
    assert not (tmp_path / "ran").exists()
    bad = tmp_path / "bad.json"
    bad.write_text('{"frames": []}')
    with pytest.raises(PredictionError, match=r"bad\.json: holds a dict, expected a list"):
        score_predictions(cfg, CLASSES, {"clean": bad}, tmp_path, **args)
    folder = tmp_path / "npz"
    folder.mkdir()
    (folder / "0000.npz").write_bytes(b"not a zip")
    with pytest.raises(PredictionError, match=r"0000\.npz: not a readable \.npz"):
        score_predictions(cfg, CLASSES, {"clean": folder}, tmp_path, **args)
    (folder / "0000.npz").unlink()
    np.savez(folder / "0000.npz", frame_id=np.array("x"), name=np.array(["Vehicle"]),
             score=np.array([0.5]), boxes_lidar=np.zeros((1, 7)))  # fmt: skip
    with pytest.raises(
        PredictionError, match=r"npz/0000\.npz \[frame 0 \('x'\)\]: field 'frame_id'"
    ):
        score_predictions(cfg, CLASSES, {"clean": folder}, tmp_path, **args)
    with pytest.raises(PredictionError, match=r"clean,rem_40=\.\.\.: names 2 variants"):
        score_predictions(cfg, CLASSES, {"clean,rem_40": bad}, tmp_path, **args)
    odd = tmp_path / "preds.dat"
    odd.write_text("frames")
    with pytest.raises(PredictionError, match=r"preds\.dat: cannot tell the predictions format"):
        score_predictions(cfg, CLASSES, {"clean": odd}, tmp_path, **args)
    assert not (tmp_path / "results.json").exists()
