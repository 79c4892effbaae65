"""Evaluating only what an attack changes: a frame whose whole model input (the frame, its point
history, PTT's proposal history) the attack leaves untouched takes the clean prediction, and the
variant's predictions, attack records and metrics are bitwise those of a full run, for a
single-frame, a 4-frame and a two-stage model with a 31-frame proposal history. A reusing run
keeps the full run's batches, and PTT's proposal bank proposes every frame with the frames of
its loader batch, so even an RPN whose output depends on its batch gives the full run's
detections, with any number of loader workers."""

from __future__ import annotations

import copy
import os
import pickle
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
from model_batches import assert_annos_equal, load_tool

from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.datasets.loader import ContiguousBatchSampler
from pcdet_atlas.evaluation import load_results, save_results
from pcdet_atlas.models import build_network_from_config
from pcdet_atlas.train_utils.atlas_eval import (
    EvalContext,
    build_attack_loader,
    evaluate_variant,
    frames_to_compute,
    input_reach,
)
from pcdet_atlas.train_utils.eval_caches import EvalCaches
from pcdet_atlas.train_utils.eval_utils import predict_dataset
from pcdet_atlas.train_utils.proposal_bank import ProposalBank

CFGS = REPO_ROOT / "cfgs" / "atlas" / "synthetic"
ATTACKS = REPO_ROOT / "cfgs" / "attacks"
CPU = torch.device("cpu")
# frames 0, 5, ..., 65 of the fixture's 70-frame val sequence; its spoof run is 32..63
INTERVAL = 5
FRAMES = list(range(0, 70, INTERVAL))
SPOOFED = [f for f in FRAMES if 32 <= f <= 63]


# PTT's tests crop tighter: its proposal bank runs the RPN on every frame of the 31-frame
# history, and a +-10.24 m crop keeps about 20 detections a frame to compare
PTT_HALF = 10.24
PTT_RANGE = f"-{PTT_HALF},-{PTT_HALF},-2,{PTT_HALF},{PTT_HALF},4"


def setup_model(name: str, root):
    """A shipped synthetic model (real weights: real detections to compare) on the fixture
    data, its BEV cropped to +-20.48 m (PTT: +-10.24 m)."""
    cfg = cfg_from_yaml_file(CFGS / f"{name}.yaml")
    half = PTT_HALF if name == "ptt_32f" else 20.48
    data_cfg = copy.deepcopy(cfg.DATA_CONFIG)
    data_cfg.DATA_PATH = str(root)
    data_cfg.SAMPLED_INTERVAL = {"train": 1, "test": INTERVAL}
    data_cfg.POINT_CLOUD_RANGE = [-half, -half, *cfg.DATA_CONFIG.POINT_CLOUD_RANGE[2:3], half,
                                  half, cfg.DATA_CONFIG.POINT_CLOUD_RANGE[5]]  # fmt: skip
    cfg.DATA_CONFIG = data_cfg
    model = build_network_from_config(cfg)
    model.load_params_from_file(REPO_ROOT / cfg.ATLAS.CHECKPOINT)
    return model.eval(), cfg


def caches_of(clean, *, reuse: bool, proposals=None) -> EvalCaches:
    """A run's caches holding the ``clean`` predictions and the ``proposals`` dict (the clean
    run's proposal bank: a clean variant fills it, an attack variant's bank starts from it)."""
    caches = EvalCaches(reuse=reuse)
    if proposals is not None:
        caches.clean_proposals = proposals
    if clean is not None:
        caches.keep_clean(clean)
    return caches


def run(model, cfg, attack, clean, *, reuse: bool, batch_size: int = 1, proposals=None,
        workers: int = 0):  # fmt: skip
    variant = attack.stem if hasattr(attack, "stem") else attack.VARIANT
    context = EvalContext(
        data_cfg=cfg.DATA_CONFIG, class_names=cfg.CLASS_NAMES, device=CPU, batch_size=batch_size,
        workers=workers, temporal_window=cfg.ATLAS.get("TEMPORAL_WINDOW"), show_progress=False,
    )  # fmt: skip
    caches = caches_of(clean, reuse=reuse, proposals=proposals)
    return evaluate_variant(model, variant, attack, context, caches=caches)


def strip(entry: dict) -> dict:
    out = {k: v for k, v in entry.items() if k != "extra"}
    out.pop("num_reused_frames"), out.pop("num_recomputed_frames")
    return out


def check_variant(model, cfg, attack, clean, proposals, *, batch_size: int) -> tuple[dict, dict]:
    """A full run and a reusing run of one variant, bitwise equal; their entries."""
    full_entry, full = run(model, cfg, attack, clean, reuse=False, batch_size=batch_size)
    reuse_entry, reused = run(model, cfg, attack, clean, reuse=True, batch_size=batch_size,
                              proposals=proposals)  # fmt: skip
    assert_annos_equal(reused, full)
    assert strip(reuse_entry) == strip(full_entry)
    assert full_entry["num_reused_frames"] == 0
    return full_entry, reuse_entry


@pytest.fixture(scope="module")
def removal():
    return cfg_from_yaml_file(ATTACKS / "rem_30.yaml")


# (model, recomputed frames): the spoofed frames, plus the clean frames whose history holds
# one (65: points 62..65 for a 4-frame input); frames before the run never need the model
CASES = {
    "centerpoint": SPOOFED,
    "cp4f": [*SPOOFED, 65],
    "ptt_32f": [*SPOOFED, 65],
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(CASES))
def test_reuse_equals_a_full_run_bitwise(name, synthetic_root, injection, removal):
    model, cfg = setup_model(name, synthetic_root)
    proposals = {}  # the clean run's proposal bank (PTT), seeding the reusing runs'
    _, clean = run(model, cfg, ATTACKS / "clean.yaml", None, reuse=False, proposals=proposals)
    assert sum(len(a["score"]) for a in clean) > 0  # real detections to compare
    assert bool(proposals) == (name == "ptt_32f")
    variants = [injection] + ([removal] if name == "centerpoint" else [])
    for attack in variants:
        full_entry, reuse_entry = check_variant(model, cfg, attack, clean, proposals, batch_size=1)
        if proposals:  # frames 0..31 from the clean bank (RPN input 28..31 clean); 32..65 not
            full_bank, bank = (
                full_entry["extra"]["proposal_bank"],
                reuse_entry["extra"]["proposal_bank"],
            )
            assert full_bank["seeded"] == 0 and full_bank["rpn_frames"] == 66
            assert bank["seeded"] == 32 and bank["rpn_frames"] == 66 - 32
        expected = len(FRAMES) - len(CASES[name])
        assert reuse_entry["num_reused_frames"] == expected
        assert reuse_entry["num_recomputed_frames"] == len(CASES[name])
        assert reuse_entry["num_targets"] > 0


def test_frames_to_compute_follows_the_input_reach(synthetic_root, injection):
    from pcdet_atlas.attacks.atlas_dataset import AtlasWaymoDataset

    cfg = cfg_from_yaml_file(CFGS / "cp4f.yaml")
    data_cfg = copy.deepcopy(cfg.DATA_CONFIG)
    data_cfg.DATA_PATH = str(synthetic_root)
    dataset = AtlasWaymoDataset(data_cfg, cfg.CLASS_NAMES, injection, training=False)
    frames = [int(info["point_cloud"]["sample_idx"]) for info in dataset.infos]
    assert frames == list(range(70))
    for reach, first_after in ((0, 64), (3, 67), (34, 70)):
        want = [32 <= f < first_after for f in frames]
        assert frames_to_compute(dataset, reach).tolist() == want, reach
    clean = AtlasWaymoDataset(data_cfg, cfg.CLASS_NAMES, ATTACKS / "clean.yaml", training=False)
    assert not frames_to_compute(clean, 34).any()
    with pytest.raises(ValueError, match="reach"):
        frames_to_compute(dataset, -1)
    ptt = cfg_from_yaml_file(CFGS / "ptt_32f.yaml")
    assert input_reach(torch.nn.Module(), cfg.DATA_CONFIG) == 3
    holder = torch.nn.Module()
    holder.proposal_history = 31
    assert input_reach(holder, ptt.DATA_CONFIG) == 34


def test_the_sampler_keeps_batch_composition():
    compute = [False] * 10
    compute[4] = compute[9] = True
    full = ContiguousBatchSampler(10, 3).batches
    kept = ContiguousBatchSampler(10, 3, compute=compute).batches
    assert full == [[0, 1, 2], [3, 4, 5], [6, 7, 8], [9]]
    assert kept == [[3, 4, 5], [9]]
    assert ContiguousBatchSampler(10, 3, num_workers=2, compute=compute).batches == kept
    with pytest.raises(ValueError, match="compute has 3 entries"):
        ContiguousBatchSampler(10, 3, compute=[True] * 3)


def test_attack_loader_draws_nothing_from_the_global_rng(synthetic_root):
    """Starting a pass draws the workers' base seed from the loader's own generator."""
    cfg = cfg_from_yaml_file(CFGS / "cp4f.yaml")
    cfg.DATA_CONFIG.DATA_PATH = str(synthetic_root)
    _, loader = build_attack_loader(
        cfg.DATA_CONFIG, cfg.CLASS_NAMES, ATTACKS / "clean.yaml", batch_size=1, dist=False,
        workers=0, seed=None,
    )  # fmt: skip
    torch.manual_seed(3)
    before = torch.get_rng_state()
    iter(loader)
    assert torch.equal(torch.get_rng_state(), before)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["centerpoint", "cp4f"])
def test_batch_composition_and_reuse_at_batch_size_3(name, synthetic_root, injection):
    """Batched with other frames, a frame's prediction differs from its prediction alone only
    at float32 rounding (the CPU convolution picks its kernel by batch size; no sample leaks into
    another), which is why reuse keeps the full run's batches: a reusing run at batch size 3
    equals a full run at batch size 3 bitwise."""
    model, cfg = setup_model(name, synthetic_root)
    preds = {}
    for batch_size in (1, 3):
        _, loader = build_attack_loader(
            cfg.DATA_CONFIG, cfg.CLASS_NAMES, injection, batch_size=batch_size, dist=False,
            workers=0, seed=0,
        )  # fmt: skip
        preds[batch_size], _ = predict_dataset(model, loader, device=CPU, show_progress=False)
    num_boxes = 0
    for single, batched in zip(preds[1], preds[3]):
        assert single["frame_id"] == batched["frame_id"]
        assert len(single["score"]) == len(batched["score"]), single["frame_id"]
        np.testing.assert_allclose(batched["score"], single["score"], rtol=0, atol=1e-5)
        np.testing.assert_allclose(batched["boxes_lidar"], single["boxes_lidar"], atol=1e-4)
        num_boxes += len(single["score"])
    assert num_boxes > 0
    _, clean = run(model, cfg, ATTACKS / "clean.yaml", None, reuse=False, batch_size=3)
    full_entry, full = run(model, cfg, injection, clean, reuse=False, batch_size=3)
    reuse_entry, reused = run(model, cfg, injection, clean, reuse=True, batch_size=3)
    assert_annos_equal(reused, full)
    assert strip(reuse_entry) == strip(full_entry)
    # batches [30, 35, 40] and [60, 65] run whole: 30 and (single-frame) 65 are recomputed
    assert 0 < reuse_entry["num_reused_frames"] < len(FRAMES) - len(CASES[name])


class BatchNamingRPN:
    """Stands in for a two-stage model: each proposal's box centre x names the frames it was
    proposed with (their sum) and its position among them (thousands)."""

    proposal_history = 2
    rpn_info = {"sha256": "0" * 64}

    def __init__(self):
        self.calls = []

    def propose(self, batch_dict):
        members = [int(i) for i in batch_dict["sample_idx"]]
        self.calls.append(members)
        return [
            {"pred_boxes": torch.full((1, 9), float(1000 * position + sum(members))),
             "pred_scores": torch.ones(1), "pred_labels": torch.ones(1)}
            for position in range(len(members))
        ]  # fmt: skip


class EvenFrames:
    """Frames 0..9 of one sequence; ``infos`` (what the loader yields) holds the even ones."""

    infos = [{"point_cloud": {"lidar_sequence": "seq", "sample_idx": i}} for i in range(0, 10, 2)]

    def frame_sample(self, sequence_name, sample_idx):
        return {"sequence_name": sequence_name, "sample_idx": sample_idx}

    @staticmethod
    def collate_batch(samples):
        return {
            "sequence_name": [s["sequence_name"] for s in samples],
            "sample_idx": np.array([s["sample_idx"] for s in samples]),
            "batch_size": len(samples),
        }


def test_the_bank_proposes_a_frame_with_its_loader_batch_in_any_order():
    batches = [[0, 1], [2, 3], [4]]  # infos indices: frames (0, 2), (4, 6), (8,)
    got = []
    for order in ([6, 4, 5, 0, 2, 8], [0, 2, 4, 5, 6, 8]):  # a history read first; loader order
        rpn = BatchNamingRPN()
        bank = ProposalBank(rpn, EvenFrames(), device=CPU, batches=batches)
        got.append({idx: bank.frame("seq", idx) for idx in order})
        assert sorted(rpn.calls) == [[0, 2], [4, 6], [5], [8]]  # 5: no batch holds it, alone
        assert bank.stats()["rpn_frames"] == 6 and bank.stats()["hits"] == 2
        assert set(bank.seedable()) == {("seq", i) for i in (0, 2, 4, 5, 6, 8)}
    for idx, rows in got[0].items():
        np.testing.assert_array_equal(rows, got[1][idx])
    assert got[0][6][0, 0] == 1000 + 4 + 6 and got[0][5][0, 0] == 5
    with pytest.raises(ValueError, match="seedable needs the loader's batches"):
        ProposalBank(BatchNamingRPN(), EvenFrames(), device=CPU).seedable()
    with pytest.raises(ValueError, match=r"frame \('seq', 2\) is in two batches"):
        ProposalBank(BatchNamingRPN(), EvenFrames(), device=CPU, batches=[[0, 1], [1]])
    with pytest.raises(ValueError, match="index 5 outside the dataset's 5 frames"):
        ProposalBank(BatchNamingRPN(), EvenFrames(), device=CPU, batches=[[4, 5]])


def composition_sensitive_rpn(model, monkeypatch) -> None:
    """Make the model's RPN depend on its batch on purpose: each sample's proposals move (scores
    shrink, boxes shift along x) by an amount set by the frames it is proposed with and its
    position among them, so a frame proposed in another batch than a full run proposes it in
    changes the detections, as the current frame or as history (the real CPU RPN differs only at
    float32 rounding, and on the fixture not at all)."""
    real = model.propose

    def propose(batch_dict):
        out = real(batch_dict)
        members = [int(i) for i in batch_dict["sample_idx"]]
        for position, proposal in enumerate(out):
            nudge = 1e-4 * (len(members) - 1 + position) + 1e-6 * (sum(members) % 97)
            proposal["pred_scores"] = proposal["pred_scores"] * (1.0 - nudge)
            proposal["pred_boxes"] = proposal["pred_boxes"].clone()
            proposal["pred_boxes"][:, 0] += 100 * nudge  # metres
        return out

    monkeypatch.setattr(model, "propose", propose)


@pytest.mark.slow
def test_ptt_at_batch_size_3_with_any_workers(synthetic_root, injection, monkeypatch):
    """PTT at batch size 3, with an RPN whose output depends on its batch: a reusing run whose
    proposal bank starts from the clean run's is bitwise a full run. Every frame is proposed
    with the frames of its loader batch (a frame no batch holds, alone), wherever it is read
    first; a frame is seeded when its whole batch has a clean RPN input. With loader workers
    the batches arrive interleaved (worker k reads the k-th contiguous chunk), so a worker's
    first batch reads history that another worker's batches hold: those frames are still
    proposed with their own batch, and the clean and the reusing run with two workers equal
    those of one bitwise."""
    model, cfg = setup_model("ptt_32f", synthetic_root)
    composition_sensitive_rpn(model, monkeypatch)

    def predict(attack, clean, *, reuse, workers, proposals=None):
        return run(model, cfg, attack, clean, reuse=reuse, batch_size=3, proposals=proposals,
                   workers=workers)  # fmt: skip

    proposals = {}
    _, clean = predict(ATTACKS / "clean.yaml", None, reuse=False, workers=0, proposals=proposals)
    full_entry, full = predict(injection, clean, reuse=False, workers=0)
    reuse_entry, reused = predict(injection, clean, reuse=True, workers=0, proposals=proposals)
    assert_annos_equal(reused, full)
    assert strip(reuse_entry) == strip(full_entry)
    bank = reuse_entry["extra"]["proposal_bank"]
    assert full_entry["extra"]["proposal_bank"]["rpn_frames"] == 66
    # seeded: frames 0..31 but 30, whose batch (30, 35, 40) has attacked RPN inputs; through
    # the RPN, each once: 30 (with 35 and 40) and 32..65
    assert bank["seeded"] == 31 and bank["rpn_frames"] == 1 + 34

    workers_bank = {}
    _, clean_two = predict(ATTACKS / "clean.yaml", None, reuse=False, workers=2,
                           proposals=workers_bank)  # fmt: skip
    assert_annos_equal(clean_two, clean)
    two_entry, reused_two = predict(injection, clean_two, reuse=True, workers=2,
                                    proposals=workers_bank)  # fmt: skip
    assert_annos_equal(reused_two, full)
    assert strip(two_entry) == strip(full_entry)


@pytest.mark.slow
def test_ptt_resume_seeds_from_the_saved_clean_bank(synthetic_root, injection, tmp_path):
    """``tools/test.py --resume`` on PTT: the clean variant's proposals, saved beside its
    ``result.pkl``, seed the bank of the injection variant evaluated by a later call, as in one
    uninterrupted call (same frames through the RPN, bitwise the same detections); a process
    reads its own part only."""
    test = load_tool("test")
    variant = tmp_path / "inj_global_hard.yaml"
    variant.write_text(
        f"_BASE_CONFIG_: {ATTACKS / 'inj_global_hard.yaml'}\n"
        f"TRACE_LIBRARY:\n  PATH: {injection.TRACE_LIBRARY.PATH}\n  MIN_POINTS: 100\n"
    )
    args = [
        "--cfg", str(CFGS / "ptt_32f.yaml"), "--attacks", f"clean,{variant}",
        "--out_dir", str(tmp_path), "--workers", "0", "--no_progress", "--device", "cpu",
        "--set", "DATA_CONFIG.DATA_PATH", str(synthetic_root),
        "DATA_CONFIG.SAMPLED_INTERVAL", f"train:1,test:{INTERVAL}",
        "DATA_CONFIG.POINT_CLOUD_RANGE", PTT_RANGE,
    ]  # fmt: skip
    whole = test.main(args)
    eval_dir = whole["output_dir"]
    saved = pickle.loads((eval_dir / "clean" / "proposals_rank0.pkl").read_bytes())
    # another process's part (proposals 5 m off): this one-process call must not read it
    (eval_dir / "clean" / "proposals_rank1.pkl").write_bytes(pickle.dumps({
        frame: rows + np.float32(5.0) for frame, rows in saved.items()
    }))  # fmt: skip
    want = whole["results"]["variants"]["inj_global_hard"]
    want_pkl = (eval_dir / "inj_global_hard" / "result.pkl").read_bytes()
    # as if the call had stopped after the clean variant
    stopped = load_results(eval_dir / "results.json")
    del stopped["variants"]["inj_global_hard"]
    save_results(stopped, eval_dir / "results.json")
    shutil.rmtree(eval_dir / "inj_global_hard")

    got = test.main([*args[:-7], "--resume", *args[-7:]])["results"]["variants"]["inj_global_hard"]
    assert got["extra"]["proposal_bank"]["seeded"] == 32
    assert got["extra"]["proposal_bank"]["rpn_frames"] == 66 - 32
    assert want["extra"]["proposal_bank"] == got["extra"]["proposal_bank"]
    assert {k: v for k, v in got.items() if k != "extra"} == {
        k: v for k, v in want.items() if k != "extra"
    }  # fmt: skip
    assert_annos_equal(
        pickle.loads((eval_dir / "inj_global_hard" / "result.pkl").read_bytes()),
        pickle.loads(want_pkl),
    )


@pytest.mark.slow
def test_ptt_two_processes_equal_one(synthetic_root, injection, tmp_path):
    """PTT's proposal history crosses the boundary between two processes' shards of a sequence
    (the second process's first frame reads 31 frames the first process evaluates): under
    torchrun with 2 processes each process proposes the history before its first frame itself,
    and the clean bank seeds the injection variant per process, giving the results and
    predictions of one process exactly."""
    variant = tmp_path / "inj_global_hard.yaml"
    variant.write_text(
        f"_BASE_CONFIG_: {ATTACKS / 'inj_global_hard.yaml'}\n"
        f"TRACE_LIBRARY:\n  PATH: {injection.TRACE_LIBRARY.PATH}\n  MIN_POINTS: 100\n"
    )

    def args(out):
        return [
            "--cfg", str(CFGS / "ptt_32f.yaml"), "--attacks", f"clean,{variant}",
            "--out_dir", str(out), "--workers", "0", "--no_progress", "--device", "cpu",
            "--set", "DATA_CONFIG.DATA_PATH", str(synthetic_root),
            "DATA_CONFIG.SAMPLED_INTERVAL", "train:1,test:10",  # 7 frames, 4 + 3 per process
            "DATA_CONFIG.POINT_CLOUD_RANGE", PTT_RANGE,
        ]  # fmt: skip

    one = load_tool("test").main(args(tmp_path / "one"))
    cmd = [
        sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2",
        "--master_port", "29531", str(REPO_ROOT / "tools" / "test.py"), "--launcher", "pytorch",
        *args(tmp_path / "two"),
    ]  # fmt: skip
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    two_dir = tmp_path / "two" / one["output_dir"].relative_to(tmp_path / "one")
    two = load_results(two_dir / "results.json")
    assert two["extra"]["processes"] == 2
    for name, want in one["results"]["variants"].items():
        got = two["variants"][name]
        assert {k: v for k, v in got.items() if k != "extra"} == {
            k: v for k, v in want.items() if k != "extra"
        }, name  # fmt: skip
        assert_annos_equal(
            pickle.loads((two_dir / name / "result.pkl").read_bytes()),
            pickle.loads((one["output_dir"] / name / "result.pkl").read_bytes()),
        )
    banks = [two["variants"][n]["extra"]["proposal_bank"] for n in ("clean", "inj_global_hard")]
    assert banks[1]["seeded"] > 0  # each process seeded its part of the injection variant
