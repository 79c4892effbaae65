"""tools/test.py end to end: two ATLAS variants -> complete results.json; torchrun (gloo, 2
processes) gives the same numbers as one process; bad input fails before anything is written;
results survive a failing variant; reruns and --resume; --eval_all, --save_to_file and
--launcher slurm."""

import copy
import json
import logging
import os
import pickle
import re
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from malicious_files import malicious_pickle
from model_batches import assert_annos_equal, load_tool

from pcdet_atlas.attacks.trace_library import TraceFilter, build_trace_library
from pcdet_atlas.config import REPO_ROOT, ConfigError, cfg_from_yaml_file
from pcdet_atlas.datasets.fingerprint import dataset_fingerprint
from pcdet_atlas.evaluation import load_results, save_results
from pcdet_atlas.evaluation.results import ResultsError
from pcdet_atlas.models import build_network_from_config
from pcdet_atlas.models.detectors.detector3d_template import CheckpointMismatchError
from pcdet_atlas.train_utils import atlas_run
from pcdet_atlas.train_utils.atlas_eval import attack_sha256, build_variant_attacks
from pcdet_atlas.train_utils.eval_caches import EvalCaches
from pcdet_atlas.train_utils.eval_folder import (
    changed_kept_file,
    finished_variants,
    proposal_hashes,
    resolve_checkpoint,
)
from pcdet_atlas.train_utils.setup import load_cfg
from pcdet_atlas.utils.hashing import file_sha256
from pcdet_atlas.utils.provenance import source_revision
from pcdet_atlas.utils.safe_pickle import RefusedGlobalError

CFG = REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "centerpoint.yaml"
ATTACKS = REPO_ROOT / "cfgs" / "attacks"


@pytest.fixture(scope="module")
def eval_setup(synthetic_root, tmp_path_factory):
    """A random-weight checkpoint and an injection variant reading a trace library in tmp."""
    tmp = tmp_path_factory.mktemp("test_tool")
    torch.manual_seed(0)
    model = build_network_from_config(cfg_from_yaml_file(CFG))
    ckpt = tmp / "random.pth"
    torch.save({"model_state": model.state_dict(), "epoch": 0}, ckpt)
    attack_cfg = cfg_from_yaml_file(ATTACKS / "inj_global_hard.yaml")
    attack_cfg.TRACE_LIBRARY.MIN_POINTS = 100
    lib = build_trace_library(synthetic_root, TraceFilter.from_config(attack_cfg.TRACE_LIBRARY))
    lib_path = lib.save(tmp / "lib.npz")
    variant = tmp / "inj_global_hard.yaml"
    variant.write_text(
        f"_BASE_CONFIG_: {ATTACKS / 'inj_global_hard.yaml'}\n"
        f"TRACE_LIBRARY:\n  PATH: {lib_path}\n  MIN_POINTS: 100\n"
    )
    return {"root": synthetic_root, "ckpt": ckpt, "variant": variant, "tmp": tmp}


def tool_args(setup, out, extra_tag):
    return [
        "--cfg", str(CFG), "--ckpt", str(setup["ckpt"]), "--attacks",
        f"clean,{setup['variant']}", "--out_dir", str(out), "--extra_tag", extra_tag,
        "--workers", "0", "--no_progress", "--device", "cpu",
        "--set", "DATA_CONFIG.DATA_PATH", str(setup["root"]),
        # frames 0, 14, 28, 42, 56 of the 70-frame val sequence: 42 and 56 lie in the run 32..63
        "DATA_CONFIG.SAMPLED_INTERVAL", "train:1,test:14",
        "DATA_CONFIG.POINT_CLOUD_RANGE", "-20.48,-20.48,-2,20.48,20.48,4",
    ]  # fmt: skip


def strip_runtime(results):
    out = copy.deepcopy(results)
    for key in ("created", "extra"):
        out.pop(key, None)
    for entry in out["variants"].values():
        entry.pop("extra", None)
    return out


@pytest.mark.slow
def test_two_variants_end_to_end_and_torchrun_agrees(eval_setup):
    test = load_tool("test")
    out = eval_setup["tmp"] / "output"
    ret = test.main(tool_args(eval_setup, out, "single"))
    eval_dir = ret["output_dir"]
    assert eval_dir == out / "atlas/synthetic/centerpoint/single/eval/random/val/default"
    results = load_results(eval_dir / "results.json")  # validates the schema
    assert list(results["variants"]) == ["clean", "inj_global_hard"]
    source = source_revision()  # the code that wrote it (None outside a git checkout)
    assert results["source_commit"] == (source and source.commit)
    assert results["source_dirty"] == (source and source.dirty)
    clean, inj = results["variants"]["clean"], results["variants"]["inj_global_hard"]
    assert clean["family"] == "clean" and clean["asr"] is None and clean["num_frames"] == 5
    assert inj["family"] == "injection" and inj["num_frames"] == 5
    assert inj["num_targets"] == 2 and inj["asr"] is not None  # spoofed frames 42 and 56
    assert inj["confidence"] is not None and inj["lifecycle"]["window"] == 1
    for v in ("clean", "inj_global_hard"):
        assert (eval_dir / v / "result.pkl").is_file()
    assert (eval_dir / "centerpoint.yaml").is_file() and list(eval_dir.glob("log_eval_*.txt"))

    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [
        sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2",
        "--master_port", "29517", str(REPO_ROOT / "tools" / "test.py"), "--launcher", "pytorch",
        "--batch_size", "2", *tool_args(eval_setup, out, "dist"),
    ]  # fmt: skip
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    dist_dir = out / "atlas/synthetic/centerpoint/dist/eval/random/val/default"
    dist_results = json.loads((dist_dir / "results.json").read_text())
    assert dist_results["extra"]["processes"] == 2
    assert strip_runtime(dist_results) == strip_runtime(results)


def test_bad_inputs_are_clear_errors(eval_setup, tmp_path):
    test = load_tool("test")
    args = tool_args(eval_setup, tmp_path, "bad")
    with pytest.raises(ConfigError, match="no_such_variant.*known variants"):
        test.main([*args[:5], "clean,no_such_variant", *args[6:]])
    cp4f = build_network_from_config(cfg_from_yaml_file(CFG.parent / "cp4f.yaml"))
    wrong = tmp_path / "cp4f.pth"
    torch.save({"model_state": cp4f.state_dict()}, wrong)
    with pytest.raises(CheckpointMismatchError, match="does not match CenterPoint"):
        test.main([*args[:2], "--ckpt", str(wrong), *args[4:]])
    assert not (tmp_path / "atlas").exists()  # a failed start-up writes nothing


def test_settings_are_the_flags_with_their_defaults():
    """tools/test.py maps its flags onto the library's EvalSettings: a call with only --cfg gets
    the settings' defaults; contradicting settings are refused by the library too."""
    test = load_tool("test")
    assert test.parse_args(["--cfg", str(CFG)]).settings == atlas_run.EvalSettings(str(CFG))
    flags = test.parse_args(["--cfg", str(CFG), "--no_reuse", "--no_progress", "--set", "A", "1"])
    assert flags.settings == atlas_run.EvalSettings(
        str(CFG), set_cfgs=("A", "1"), reuse_clean=False, show_progress=False
    )
    with pytest.raises(ValueError, match="--eval_all evaluates the checkpoints of --ckpt_dir"):
        atlas_run.EvalSettings(str(CFG), eval_all=True, ckpt="a.pth")


def test_ckpt_is_read_from_the_working_directory(tmp_path, monkeypatch):
    """--ckpt as typed (the working directory); ATLAS.CHECKPOINT from the repository root."""
    resolve = resolve_checkpoint
    atlas_cfg = cfg_from_yaml_file(CFG).ATLAS
    shipped = REPO_ROOT / atlas_cfg.CHECKPOINT
    monkeypatch.chdir(tmp_path)
    assert resolve(None, atlas_cfg) == shipped
    (tmp_path / "mine.pth").write_bytes(b"")
    assert resolve("mine.pth", atlas_cfg) == tmp_path / "mine.pth"
    with pytest.raises(FileNotFoundError, match="checkpoint"):  # no fallback to the repo root
        resolve(atlas_cfg.CHECKPOINT, atlas_cfg)


def with_attacks(args, attacks):
    out = list(args)
    out[out.index("--attacks") + 1] = attacks
    return out


def with_flags(args, *flags):
    """``args`` with ``flags`` before ``--set`` (which takes the rest of the line)."""
    at = args.index("--set")
    return [*args[:at], *flags, *args[at:]]


def test_startup_failures_write_nothing(eval_setup, tmp_path, capsys):
    test = load_tool("test")
    args = tool_args(eval_setup, tmp_path / "out", "startup")
    # VARIANT must be the file's name: checked before the model is built or anything written
    renamed = tmp_path / "my_injection.yaml"
    renamed.write_text(eval_setup["variant"].read_text())  # inherits VARIANT: inj_global_hard
    with pytest.raises(ConfigError, match="VARIANT 'inj_global_hard' .*set VARIANT: my_injection"):
        test.main(with_attacks(args, f"clean,{renamed}"))
    truncated = tmp_path / "cut.pth"
    truncated.write_bytes(eval_setup["ckpt"].read_bytes()[:1000])
    with pytest.raises(ValueError, match=f"checkpoint {truncated} cannot be read"):
        test.main([*args[:2], "--ckpt", str(truncated), *args[4:]])
    if not torch.cuda.is_available():
        cuda = list(args)
        cuda[cuda.index("--device") + 1] = "cuda"
        with pytest.raises(SystemExit):
            test.main(cuda)
        assert "argument --device: 'cuda': no CUDA GPU is visible" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_results_survive_a_failing_variant_and_reruns_need_overwrite(
    eval_setup, tmp_path, monkeypatch
):
    test = load_tool("test")
    args = tool_args(eval_setup, tmp_path, "rerun")
    eval_dir = tmp_path / "atlas/synthetic/centerpoint/rerun/eval/random/val/default"
    real = atlas_run.evaluate_variant

    def fail_on_injection(model, variant, *a, **kw):
        if variant == "inj_global_hard":
            raise RuntimeError("variant failed")
        return real(model, variant, *a, **kw)

    monkeypatch.setattr(atlas_run, "evaluate_variant", fail_on_injection)
    with pytest.raises(RuntimeError, match="variant failed"):
        test.main(args)
    kept = load_results(eval_dir / "results.json")  # the clean variant done before the failure
    assert list(kept["variants"]) == ["clean"]
    assert kept["extra"]["variants_requested"] == ["clean", "inj_global_hard"]
    assert not list(eval_dir.glob("*.tmp"))
    monkeypatch.setattr(atlas_run, "evaluate_variant", real)

    before = (eval_dir / "results.json").read_bytes()
    with pytest.raises(FileExistsError, match=f"{eval_dir} already holds .*--overwrite"):
        test.main(with_attacks(args, str(eval_setup["variant"])))
    assert (eval_dir / "results.json").read_bytes() == before

    ret = test.main(with_flags(with_attacks(args, str(eval_setup["variant"])), "--overwrite"))
    assert ret["output_dir"] == eval_dir
    assert list(load_results(eval_dir / "results.json")["variants"]) == ["inj_global_hard"]
    assert not (eval_dir / "clean").exists()  # no stale variant of the earlier run
    assert len(list(eval_dir.glob("log_eval_*.txt"))) == 1


def test_resume_goes_on_from_the_last_finished_variant(eval_setup, tmp_path, monkeypatch, capsys):
    """A call stopped after the clean variant; ``--resume`` evaluates only the injection variant
    (its frames untouched by the attack taking the saved clean predictions) and ends with the
    results of one uninterrupted call; ``--save_to_file`` writes the kept variants' files too.
    Another checkpoint, config, batch size or device is refused."""
    test = load_tool("test")
    ckpt = tmp_path / "random.pth"  # a copy, rewritten below
    ckpt.write_bytes(eval_setup["ckpt"].read_bytes())
    setup = {**eval_setup, "ckpt": ckpt}
    whole = test.main(tool_args(setup, tmp_path, "whole"))
    args = tool_args(setup, tmp_path, "resume")
    eval_dir = tmp_path / "atlas/synthetic/centerpoint/resume/eval/random/val/default"
    real = atlas_run.evaluate_variant
    called = []

    def fail_on_injection(model, variant, *a, **kw):
        called.append(variant)
        if variant == "inj_global_hard":
            raise RuntimeError("interrupted")
        return real(model, variant, *a, **kw)

    monkeypatch.setattr(atlas_run, "evaluate_variant", fail_on_injection)
    with pytest.raises(RuntimeError, match="interrupted"):
        test.main(args)
    assert list(load_results(eval_dir / "results.json")["variants"]) == ["clean"]
    monkeypatch.setattr(atlas_run, "evaluate_variant", real)
    with pytest.raises(FileExistsError, match="--overwrite"):
        test.main(args)  # neither --resume nor --overwrite

    called.clear()
    monkeypatch.setattr(
        atlas_run, "evaluate_variant", lambda model, variant, *a, **kw: (
            called.append(variant) or real(model, variant, *a, **kw)
        ),
    )  # fmt: skip
    ret = test.main(with_flags(args, "--resume"))
    assert called == ["inj_global_hard"]
    assert strip_runtime(ret["results"]) == strip_runtime(whole["results"])
    inj = ret["results"]["variants"]["inj_global_hard"]
    assert inj["num_reused_frames"] == whole["results"]["variants"]["inj_global_hard"][
        "num_reused_frames"] > 0  # fmt: skip
    for variant in ("clean", "inj_global_hard"):
        got, want = (pickle.loads((d / variant / "result.pkl").read_bytes())
                     for d in (eval_dir, whole["output_dir"]))  # fmt: skip
        assert sum(len(anno["score"]) for anno in got) > 0  # predictions to compare
        assert_annos_equal(got, want)
    logs = "".join(p.read_text() for p in eval_dir.glob("log_eval_*.txt"))
    assert "clean: kept from an earlier call (--resume)" in logs  # the calls' logs are kept

    called.clear()
    assert not list(eval_dir.glob("*/final_result"))
    # everything finished: nothing runs, and the kept variants' prediction files are written
    ret = test.main(with_flags(args, "--resume", "--save_to_file"))
    assert called == [] and strip_runtime(ret["results"]) == strip_runtime(whole["results"])
    for variant in ("clean", "inj_global_hard"):
        files = sorted((eval_dir / variant / "final_result" / "data").glob("*.txt"))
        assert len(files) == ret["results"]["variants"][variant]["num_frames"] > 0

    torch.save({**torch.load(ckpt), "epoch": 1}, ckpt)  # the same name, other bytes
    with pytest.raises(ValueError, match="--resume: .*results.json .*checkpoint_sha256"):
        test.main(with_flags(args, "--resume"))
    ckpt.write_bytes(eval_setup["ckpt"].read_bytes())
    with pytest.raises(ValueError, match="--resume: .*merged config"):
        thresh = "MODEL.DENSE_HEAD.POST_PROCESSING.SCORE_THRESH"
        test.main([*with_flags(args, "--resume"), thresh, "0.2"])
    with pytest.raises(ValueError, match="--resume: .*batch_size 1 \\(now 2\\)"):
        test.main(with_flags(args, "--resume", "--batch_size", "2"))
    results_file = eval_dir / "results.json"
    written = results_file.read_text()
    on_gpu = json.loads(written)
    on_gpu["extra"]["device"] = "cuda"  # as a call on a GPU records it
    results_file.write_text(json.dumps(on_gpu))
    with pytest.raises(ValueError, match="--resume: .*device 'cuda' \\(now 'cpu'\\)"):
        test.main(with_flags(args, "--resume"))
    results_file.write_text(written)
    capsys.readouterr()
    with pytest.raises(SystemExit):
        test.main(with_flags(args, "--resume", "--overwrite"))
    assert "--resume keeps an earlier call's variants, --overwrite deletes them" in (
        capsys.readouterr().err
    )
    assert called == []


def test_resume_scores_kept_variants_again_with_this_version(eval_setup, tmp_path, monkeypatch):
    """A kept variant's entry is scored again from its ``result.pkl`` by this version's metric
    and analyses (an entry written before an analysis existed gets it), without running the
    model; what only the prediction pass knew (timings, reuse counts) is kept."""
    test = load_tool("test")
    args = tool_args(eval_setup, tmp_path, "rescore")
    whole = test.main(args)
    variant = Path(eval_setup["variant"]).stem
    results_file = whole["output_dir"] / "results.json"
    older = json.loads(results_file.read_text())  # as an older version would have written it
    entry = older["variants"][variant]
    assert entry["attributable"] is not None and entry["L2/mAP"] != 0.5
    entry.update({"attributable": None, "L2/mAP": 0.5})
    entry["extra"]["timing_s"]["model"] = 1234.5
    results_file.write_text(json.dumps(older))
    real, called = atlas_run.evaluate_variant, []
    monkeypatch.setattr(
        atlas_run, "evaluate_variant", lambda model, variant, *a, **kw: (
            called.append(variant) or real(model, variant, *a, **kw)
        ),
    )  # fmt: skip
    ret = test.main(with_flags(args, "--resume"))
    assert called == []
    assert strip_runtime(ret["results"]) == strip_runtime(whole["results"])
    kept = ret["results"]["variants"][variant]
    assert kept["extra"]["timing_s"]["model"] == 1234.5
    assert kept["num_reused_frames"] == whole["results"]["variants"][variant]["num_reused_frames"]


def test_resume_evaluates_again_what_changed(eval_setup, tmp_path, monkeypatch):
    """``--resume`` keeps a finished variant only where one uninterrupted call gives the same
    entry: a removal variant evaluated without the clean predictions this call has (its
    confidence needs them), a variant whose attack YAML changed and an entry without
    ``attack_sha256`` (an older file) are evaluated again."""
    test = load_tool("test")
    whole = test.main(with_attacks(tool_args(eval_setup, tmp_path, "whole"), "clean,rem_30"))
    args = with_attacks(tool_args(eval_setup, tmp_path, "parts"), "rem_30")
    eval_dir = tmp_path / "atlas/synthetic/centerpoint/parts/eval/random/val/default"
    alone = test.main(args)["results"]["variants"]["rem_30"]
    assert alone["confidence"] is None and alone["extra"]["clean_predictions"] is False
    real, called = atlas_run.evaluate_variant, []
    monkeypatch.setattr(
        atlas_run, "evaluate_variant", lambda model, variant, *a, **kw: (
            called.append(variant) or real(model, variant, *a, **kw)
        ),
    )  # fmt: skip
    ret = test.main(with_flags(with_attacks(args, "clean,rem_30"), "--resume"))
    assert called == ["clean", "rem_30"]
    assert ret["results"]["variants"]["rem_30"]["confidence"] is not None
    assert strip_runtime(ret["results"]) == strip_runtime(whole["results"])
    called.clear()
    test.main(with_flags(with_attacks(args, "clean,rem_30"), "--resume"))
    assert called == []

    # the test split rewritten in place since (another fingerprint), or a file without one (an
    # older version's): nothing is kept
    written = load_results(eval_dir / "results.json")
    fingerprint = dataset_fingerprint(eval_setup["root"], "val")
    assert written["extra"]["dataset_fingerprint"] == fingerprint
    cfg = load_cfg(str(CFG), args[args.index("--set") + 1 :])
    requested = {name: e["extra"]["attack_sha256"] for name, e in written["variants"].items()}

    def finished(now):
        return finished_variants(
            eval_dir, cfg, file_sha256(eval_setup["ckpt"]), requested, batch_size=1, world=1,
            device="cpu", dataset_fingerprint=now,
        )  # fmt: skip

    assert set(finished(fingerprint)[0]) == {"clean", "rem_30"}
    kept, again = finished("0" * 64)
    assert kept == {} and set(again) == {"clean", "rem_30"}
    assert f"frame files changed (dataset_fingerprint {fingerprint}, now {'0' * 64})" in again[
        "clean"]  # fmt: skip
    older = copy.deepcopy(written)
    del older["extra"]["dataset_fingerprint"]
    save_results(older, eval_dir / "results.json")
    assert finished(fingerprint)[0] == {}
    test.main(with_flags(with_attacks(args, "clean,rem_30"), "--resume"))
    assert called == ["clean", "rem_30"]  # evaluated again, and the fingerprint recorded
    assert load_results(eval_dir / "results.json")["extra"]["dataset_fingerprint"] == fingerprint
    called.clear()

    variant = tmp_path / "rem_30.yaml"  # the same attack, then another budget
    variant.write_text(f"_BASE_CONFIG_: {ATTACKS / 'rem_30.yaml'}\n")
    resumed = with_flags(with_attacks(args, f"clean,{variant}"), "--resume")
    test.main(resumed)
    assert called == []
    variant.write_text(variant.read_text() + "P_REMOVE: 0.5\n")
    before = load_results(eval_dir / "results.json")["variants"]["rem_30"]["extra"]
    test.main(resumed)
    assert called == ["rem_30"]
    after = load_results(eval_dir / "results.json")["variants"]["rem_30"]["extra"]
    assert after["attack_sha256"] != before["attack_sha256"]

    called.clear()
    older = load_results(eval_dir / "results.json")
    del older["variants"]["rem_30"]["extra"]["attack_sha256"]
    save_results(older, eval_dir / "results.json")
    test.main(resumed)
    assert called == ["rem_30"]

    called.clear()  # a schema-4 file: no per-run counts, kept only where there are no targets
    older = load_results(eval_dir / "results.json")
    for entry in older["variants"].values():
        entry["runs"] = None
    save_results(older, eval_dir / "results.json")
    assert test.main(resumed)["results"]["variants"]["clean"]["runs"] == []
    assert called == ["rem_30"]
    logs = "".join(p.read_text() for p in eval_dir.glob("log_eval_*.txt"))
    again = "rem_30: finished by an earlier call, evaluated again: "
    assert f"{again}it was evaluated without the clean predictions this call has" in logs
    assert f"{again}its attack config or trace library changed (attack_sha256 " in logs
    assert f"{again}its entry has no extra.attack_sha256" in logs
    assert f"{again}its entry has no per-run counts (results.json schema 4 or older)" in logs
    assert not list(eval_dir.rglob("*.tmp"))

    called.clear()  # a call without clean keeps the entry as its clean predictions scored it
    scored = load_results(eval_dir / "results.json")["variants"]["rem_30"]
    alone = with_flags(with_attacks(args, str(variant)), "--resume")
    kept = test.main(alone)["results"]["variants"]["rem_30"]
    assert called == [] and kept["confidence"] == scored["confidence"] is not None
    assert kept["attributable"] == scored["attributable"] is not None
    logs = "".join(p.read_text() for p in eval_dir.glob("log_eval_*.txt"))
    assert "rem_30: kept from an earlier call (--resume), as scored then (no clean" in logs


def test_attack_sha256_follows_the_yaml_and_the_trace_library(eval_setup, tmp_path):
    library = tmp_path / "lib.npz"
    source = Path(cfg_from_yaml_file(eval_setup["variant"]).TRACE_LIBRARY.PATH)
    library.write_bytes(source.read_bytes())
    variant = tmp_path / "inj_global_hard.yaml"
    text = (
        f"_BASE_CONFIG_: {ATTACKS / 'inj_global_hard.yaml'}\n"
        f"TRACE_LIBRARY:\n  PATH: {library}\n  MIN_POINTS: 100\n"
    )
    variant.write_text(text)

    def sha() -> str:
        variants = [("inj_global_hard", variant)]
        return attack_sha256(variant, build_variant_attacks(variants, eval_setup["root"])[
            "inj_global_hard"])  # fmt: skip

    first = sha()
    assert sha() == first and len(first) == 64
    library.write_bytes(library.read_bytes() + b"\0")  # other bytes at the same path
    assert sha() != first
    library.write_bytes(source.read_bytes())
    assert sha() == first
    variant.write_text(text + "SEED: 1\n")
    assert sha() != first


def test_resume_names_a_corrupt_results_file(eval_setup, tmp_path):
    test = load_tool("test")
    eval_dir = tmp_path / "atlas/synthetic/centerpoint/corrupt/eval/random/val/default"
    eval_dir.mkdir(parents=True)
    (eval_dir / "results.json").write_text('{"variants": ')  # a write cut short
    args = with_flags(tool_args(eval_setup, tmp_path, "corrupt"), "--resume")
    with pytest.raises(ResultsError, match=re.escape(str(eval_dir / "results.json"))):
        test.main(args)


def resume_clean(tmp_path, clean_files):
    """``evaluate_checkpoint`` keeping a finished clean variant whose ``clean/`` holds
    ``clean_files`` (``{name: bytes}``), its entry recording their SHA-256."""
    clean = tmp_path / "clean"
    clean.mkdir(exist_ok=True)
    for name, data in clean_files.items():
        (clean / name).write_bytes(data)
    recorded = {"result_sha256": file_sha256(clean / "result.pkl"),
                "proposals_sha256": {name: file_sha256(clean / name)
                                     for name in clean_files if name != "result.pkl"}}  # fmt: skip
    run = atlas_run.EvalRun(
        settings=atlas_run.EvalSettings(cfg_file=str(CFG)), cfg=cfg_from_yaml_file(CFG),
        attacks={"clean": None}, fingerprints={}, dataset_fingerprint=None,
        device=torch.device("cpu"), batch_size=1, caches=EvalCaches(),
    )  # fmt: skip
    return lambda: atlas_run.evaluate_checkpoint(
        run, None, tmp_path / "a.pth", tmp_path, finished={"clean": {"extra": recorded}},
        ckpt_sha256="", logger=logging.getLogger("test_resume"),
    )  # fmt: skip


CLEAN_ANNOS = pickle.dumps([{"frame_id": "f", "score": np.zeros(0)}])


@pytest.mark.parametrize("evil", ["result.pkl", "proposals_rank0.pkl"])
def test_resume_refuses_kept_files_that_would_run_code(tmp_path, evil):
    """``--resume`` reads a finished variant's ``result.pkl`` and the clean run's proposals
    with the restricted unpickler."""
    marker = tmp_path / "marker"
    data = malicious_pickle(tmp_path / "evil.pkl", marker).read_bytes()
    resume = resume_clean(tmp_path, {"result.pkl": CLEAN_ANNOS, evil: data})
    path = tmp_path / "clean" / evil
    with pytest.raises(RefusedGlobalError, match=rf"{path}: refused to unpickle the global "):
        resume()
    assert not marker.exists()


@pytest.mark.parametrize(
    "proposals, message",
    [
        ([np.zeros((1, 11), np.float32)], "expected a dict"),
        ({"seq_0": np.zeros((1, 11), np.float32)}, "key 'seq_0' is not a (sequence_name"),
        ({("seq", 0): np.zeros((1, 9), np.float32)}, "float32 array of shape (1, 9)"),
        ({("seq", 0): np.zeros((1, 11), np.float64)}, "float64 array of shape (1, 11)"),
        ({("seq", 0): [[0.0] * 11]}, "expected float32 rows of shape (R, 11), got list"),
    ],
)  # fmt: skip
def test_resume_refuses_malformed_clean_proposals(tmp_path, proposals, message):
    """The clean proposals read back must be ``{(sequence_name, sample_idx): float32 (R, 11)}``,
    as the proposal bank gives them; the error names the file (and the key)."""
    resume = resume_clean(
        tmp_path, {"result.pkl": CLEAN_ANNOS, "proposals_rank0.pkl": pickle.dumps(proposals)}
    )
    part = tmp_path / "clean" / "proposals_rank0.pkl"
    with pytest.raises(ValueError, match=re.escape(str(part)) + ".*" + re.escape(message)):
        resume()


def test_resume_refuses_kept_files_changed_after_the_check(tmp_path):
    """A kept file whose bytes differ from the SHA-256 finished_variants compared (rewritten
    since) is an error naming it, not read."""
    rows = {("seq", 0): np.zeros((2, 11), np.float32)}
    resume = resume_clean(
        tmp_path, {"result.pkl": CLEAN_ANNOS, "proposals_rank0.pkl": pickle.dumps(rows)}
    )
    part = tmp_path / "clean" / "proposals_rank0.pkl"
    part.write_bytes(pickle.dumps({("seq", 0): np.ones((2, 11), np.float32)}))
    with pytest.raises(RuntimeError, match=re.escape(f"{part} changed since this call checked")):
        resume()


def test_resume_evaluates_again_a_variant_whose_kept_files_changed(
    eval_setup, tmp_path, monkeypatch
):
    """``results.json`` records the SHA-256 of each variant's ``result.pkl``; ``--resume``
    evaluates again a variant whose file differs from it (its clean predictions would stand
    for the attack variants' untouched frames) and keeps an untouched one, or one whose entry
    recorded none (an older version's, reused as that version did)."""
    test = load_tool("test")
    args = with_attacks(tool_args(eval_setup, tmp_path, "hashes"), "clean")
    eval_dir = tmp_path / "atlas/synthetic/centerpoint/hashes/eval/random/val/default"
    test.main(args)
    clean = eval_dir / "clean" / "result.pkl"
    entry = load_results(eval_dir / "results.json")["variants"]["clean"]
    assert entry["extra"]["result_sha256"] == file_sha256(clean)
    assert entry["extra"]["proposals_sha256"] == {}  # no proposal bank: no parts
    real, called = atlas_run.evaluate_variant, []
    monkeypatch.setattr(
        atlas_run, "evaluate_variant", lambda model, variant, *a, **kw: (
            called.append(variant) or real(model, variant, *a, **kw)
        ),
    )  # fmt: skip
    resumed = with_flags(with_attacks(args, "clean,rem_30"), "--resume")

    annos = pickle.loads(clean.read_bytes())
    assert sum(len(anno["score"]) for anno in annos) > 0
    annos[0]["score"] = annos[0]["score"] * 0.5  # another prediction, still a valid file
    recorded = file_sha256(clean)
    clean.write_bytes(pickle.dumps(annos))
    ret = test.main(resumed)
    assert called == ["clean", "rem_30"]
    assert ret["results"]["variants"]["clean"]["extra"]["result_sha256"] == file_sha256(clean)
    assert file_sha256(clean) == recorded  # evaluated again: the predictions of the model
    logs = "".join(p.read_text() for p in eval_dir.glob("log_eval_*.txt"))
    assert (f"clean: finished by an earlier call, evaluated again: the SHA-256 of {clean} "
            f"differs from the one its entry recorded ({recorded}, now ") in logs  # fmt: skip

    called.clear()
    test.main(resumed)  # untouched: both kept
    assert called == []

    older = load_results(eval_dir / "results.json")
    for variant in ("clean", "rem_30"):
        del older["variants"][variant]["extra"]["result_sha256"]
    del older["variants"]["clean"]["extra"]["proposals_sha256"]
    save_results(older, eval_dir / "results.json")
    test.main(with_attacks(resumed, "clean,rem_30,rem_40"))
    assert called == ["rem_40"]  # the older entries kept, their clean predictions reused


def test_changed_kept_file_compares_the_clean_proposal_parts(tmp_path):
    """The clean variant's proposal parts: each must be there with its recorded SHA-256, and
    none there unrecorded."""
    clean = tmp_path / "clean"
    clean.mkdir()
    for name in ("result.pkl", "proposals_rank0.pkl", "proposals_rank1.pkl"):
        (clean / name).write_bytes(name.encode())
    recorded = {"result_sha256": file_sha256(clean / "result.pkl"),
                "proposals_sha256": proposal_hashes(clean, [
                    file_sha256(clean / f"proposals_rank{r}.pkl") for r in range(2)])}  # fmt: skip
    assert changed_kept_file(clean, recorded, world=2) is None
    part = clean / "proposals_rank1.pkl"
    part.write_bytes(b"other")
    assert f"the SHA-256 of {part} differs from the one its entry recorded" in changed_kept_file(
        clean, recorded, world=2)  # fmt: skip
    part.unlink()
    missing = changed_kept_file(clean, recorded, world=2)
    assert missing == f"{part} is missing (its entry recorded its SHA-256)"
    rank0 = file_sha256(clean / "proposals_rank0.pkl")
    one = {**recorded, "proposals_sha256": {"proposals_rank0.pkl": rank0}}
    assert changed_kept_file(clean, one, world=2) is None
    part.write_bytes(b"planted")
    assert f"{part} is not recorded by its entry" in changed_kept_file(clean, one, world=2)
    assert changed_kept_file(clean, {"result_sha256": recorded["result_sha256"]}, world=2) is None
    assert changed_kept_file(clean, {}, world=2) is None  # an older version's entry


def test_eval_all_from_start_epoch_and_save_to_file(eval_setup, tmp_path, capsys, monkeypatch):
    test = load_tool("test")
    ckpt_dir = tmp_path / "ckpts"
    ckpt_dir.mkdir()
    for epoch in (1, 2, 10):
        (ckpt_dir / f"checkpoint_epoch_{epoch}.pth").write_bytes(eval_setup["ckpt"].read_bytes())
    args = tool_args(eval_setup, tmp_path, "all")
    args = [*args[:2], *args[4:]]  # no --ckpt
    args = with_attacks(args, "clean")
    args[args.index("train:1,test:14")] = "train:1,test:35"  # 2 frames
    ret = test.main(
        with_flags(args, "--eval_all", "--ckpt_dir", str(ckpt_dir), "--start_epoch", "2",
                   "--save_to_file")
    )  # fmt: skip
    eval_root = tmp_path / "atlas/synthetic/centerpoint/all/eval"
    assert [r["output_dir"] for r in ret["runs"]] == [
        eval_root / "epoch_2/val/default", eval_root / "epoch_10/val/default"
    ]  # fmt: skip
    assert sorted(p.name for p in eval_root.iterdir()) == ["epoch_10", "epoch_2"]
    for run in ret["runs"]:
        results = load_results(run["output_dir"] / "results.json")
        assert results["checkpoint"] == str(run["checkpoint"])
        det_annos = pickle.loads((run["output_dir"] / "clean" / "result.pkl").read_bytes())
        files = run["output_dir"] / "clean" / "final_result" / "data"
        assert sorted(p.stem for p in files.iterdir()) == sorted(a["frame_id"] for a in det_annos)
        assert sum(len(anno["name"]) for anno in det_annos) > 0  # lines to check
        for anno in det_annos:
            lines = (files / f"{anno['frame_id']}.txt").read_text().splitlines()
            assert len(lines) == len(anno["name"])
            for line, name, box, score in zip(
                lines, anno["name"], anno["boxes_lidar"], anno["score"]
            ):
                fields = line.split()
                assert fields[0] == name and len(fields) == 2 + box.shape[0]
                assert [float(v) for v in fields[1:]] == pytest.approx(
                    [*box.tolist(), float(score)], abs=1e-4
                )
    with pytest.raises(FileNotFoundError, match="N >= 11 in"):
        test.main(
            with_flags(args, "--eval_all", "--ckpt_dir", str(ckpt_dir), "--start_epoch", "11")
        )
    # a checkpoint rewritten between the hash results.json records and the load
    real_check = atlas_run.check_eval_dir

    def rewritten_then_check(*a, **kw):
        target = ckpt_dir / "checkpoint_epoch_10.pth"
        torch.save({**torch.load(target), "epoch": 11}, target)
        return real_check(*a, **kw)

    monkeypatch.setattr(atlas_run, "check_eval_dir", rewritten_then_check)
    with pytest.raises(RuntimeError, match="checkpoint_epoch_10.pth changed since this call"):
        test.main(with_flags(args, "--eval_all", "--ckpt_dir", str(ckpt_dir), "--start_epoch",
                             "10", "--overwrite"))  # fmt: skip
    capsys.readouterr()
    with pytest.raises(SystemExit):
        test.main(with_flags(args, "--start_epoch", "2"))  # --start_epoch without --eval_all
    assert "--ckpt_dir and --start_epoch apply to --eval_all only" in capsys.readouterr().err


def test_slurm_launcher_one_process(eval_setup, tmp_path):
    """``--launcher slurm`` as OpenPCDet's: the Slurm environment of a 1-task job and a
    ``scontrol`` on PATH that resolves the node list."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    calls = tmp_path / "scontrol_calls.txt"
    scontrol = bin_dir / "scontrol"
    scontrol.write_text(f'#!/bin/sh\necho "$@" >> {calls}\necho localhost\necho otherhost\n')
    scontrol.chmod(0o755)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = dict(
        os.environ, OMP_NUM_THREADS="1", PATH=f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
        SLURM_PROCID="0", SLURM_NTASKS="1", SLURM_NODELIST="node[01-02]",
    )  # fmt: skip
    for key in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(key, None)
    args = with_attacks(tool_args(eval_setup, tmp_path, "slurm"), "clean")
    args[args.index("train:1,test:14")] = "train:1,test:35"
    cmd = [sys.executable, str(REPO_ROOT / "tools" / "test.py"), "--launcher", "slurm",
           "--tcp_port", str(port), *args]  # fmt: skip
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert calls.read_text().split() == ["show", "hostname", "node[01-02]"]
    eval_dir = tmp_path / "atlas/synthetic/centerpoint/slurm/eval/random/val/default"
    results = load_results(eval_dir / "results.json")
    assert results["extra"]["processes"] == 1 and results["variants"]["clean"]["num_frames"] == 2
