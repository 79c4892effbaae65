"""tools/test.py end to end: two ATLAS variants -> complete results.json; torchrun (gloo, 2
processes) gives the same numbers as one process."""

import copy
import json
import os
import subprocess
import sys

import pytest
import torch
from model_batches import load_tool

from pcdet_atlas.attacks.trace_library import TraceFilter, build_trace_library
from pcdet_atlas.config import REPO_ROOT, ConfigError, cfg_from_yaml_file
from pcdet_atlas.evaluation import load_results
from pcdet_atlas.models import build_network_from_config
from pcdet_atlas.models.detectors.detector3d_template import CheckpointMismatchError

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
        f"clean,{setup['variant']}", "--output_root", str(out), "--extra_tag", extra_tag,
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
