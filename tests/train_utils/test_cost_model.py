"""The cost model's arithmetic on tiny inputs: frames from the spoof schedule (checked against
the counts the reuse benchmark measured on the 198-frame val sequence), from a results.json's
recorded counts, device-hours, and the tool end to end."""

import json
import subprocess
import sys

import pytest

from pcdet_atlas.attacks.base import attack_from_file
from pcdet_atlas.config import REPO_ROOT
from pcdet_atlas.train_utils.cost_model import (
    FrameCost,
    SuiteFrames,
    device_hours,
    parse_cost,
    read_bench_json,
    recorded_frames,
    scheduled_frames,
    sequence_lengths,
)

ATTACKS = REPO_ROOT / "cfgs" / "attacks"


def suite(*names):
    return {n: attack_from_file(ATTACKS / f"{n}.yaml") for n in names}


def test_schedule_counts_match_the_measured_reuse_frames():
    # docs/benchmarks.md "Evaluating only what an attack changes": per attacked variant of the
    # 198-frame sequence, a 1-frame model runs 96 frames, a 4-frame one 105, MSF-8f 116 and
    # PTT (reach 34) 166, its RPN 105
    attacks = suite("clean", "rem_40", "inj_global_hard")
    for reach, per_variant in ((0, 96), (3, 105), (7, 116), (34, 166)):
        got = scheduled_frames(attacks, [198], reach)
        assert (got.frames, got.total, got.variants) == (198 + 2 * per_variant, 3 * 198, 3)
        assert got.rpn_frames is None
    ptt = scheduled_frames(attacks, [198], 34, rpn_reach=3, proposal_history=31)
    assert (ptt.frames, ptt.rpn_frames) == (198 + 2 * 166, 198 + 2 * 105)


def test_batches_and_process_boundaries():
    attacks = suite("clean", "rem_40")
    # batches of 8: a batch with one attacked frame runs whole (runs 32-63, 96-127, 160-191
    # start and end on multiples of 8, so nothing changes; batches of 5 straddle them)
    assert scheduled_frames(attacks, [198], 0, batch_size=8).frames == 198 + 96
    assert scheduled_frames(attacks, [198], 0, batch_size=5).frames == 198 + 105
    # PTT's RPN pays its proposal history once per variant at each of world - 1 boundaries
    one = scheduled_frames(attacks, [198], 34, rpn_reach=3, proposal_history=31)
    two = scheduled_frames(attacks, [198], 34, rpn_reach=3, proposal_history=31, world=2)
    assert two.frames == one.frames and two.rpn_frames == one.rpn_frames + 2 * 31


def test_sequences_and_hours():
    assert sequence_lengths(39987, 198) == [198] * 201 + [189]
    with pytest.raises(ValueError, match="must be >= 1"):
        sequence_lengths(0, 198)
    frames = SuiteFrames(frames=1000, total=2000, variants=2)
    assert device_hours(FrameCost(0.036), frames) == pytest.approx(0.01)
    assert device_hours(FrameCost(0.036), frames, scale=10) == pytest.approx(0.1)
    cpu = FrameCost(3.6, device="cpu", threads=2)
    assert device_hours(cpu, frames) == pytest.approx(2.0)  # core-hours: 1 h wall x 2 threads
    two_stage = SuiteFrames(frames=100, total=200, variants=2, rpn_frames=50)
    cost = parse_cost("cfgs/atlas/synthetic/ptt_32f.yaml=0.72+2.88")
    assert cost[0] == "atlas/synthetic/ptt_32f.yaml"
    assert device_hours(cost[1], two_stage) == pytest.approx((50 * 0.72 + 100 * 2.88) / 3600)


def test_bad_costs_name_the_input(tmp_path):
    with pytest.raises(ValueError, match="expected CFG=SECONDS"):
        parse_cost("cfgs/atlas/synthetic/cp4f.yaml")
    with pytest.raises(ValueError, match="is not seconds"):
        parse_cost("cfgs/atlas/synthetic/cp4f.yaml=fast")
    with pytest.raises(ValueError, match="RPN 0.2 s > whole frame"):
        FrameCost(0.1, rpn_seconds=0.2)
    bad = tmp_path / "bench.json"
    bad.write_text(json.dumps({"version": 1, "device": "cuda", "threads": 1, "models": {"a": {}}}))
    with pytest.raises(ValueError, match=r"models\['a'\] has no 'latency_s'"):
        read_bench_json(bad)


def results_file(tmp_path, counts):
    variants = {
        name: {"num_frames": n, "num_recomputed_frames": r, "num_reused_frames": n - r,
               "extra": {"proposal_bank": {"rpn_frames": b}}}
        for name, (n, r, b) in counts.items()
    }  # fmt: skip
    return {"config": "cfgs/atlas/synthetic/ptt_32f.yaml", "variants": variants}


def test_recorded_counts(tmp_path):
    results = results_file(tmp_path, {"clean": (70, 70, 70), "rem_40": (70, 38, 35)})
    got = recorded_frames(results, "r.json")
    assert (got.frames, got.total, got.variants, got.rpn_frames) == (108, 140, 2, 105)
    results["variants"]["rem_40"]["num_recomputed_frames"] = None
    with pytest.raises(ValueError, match="r.json: variant 'rem_40' has num_recomputed_frames null"):
        recorded_frames(results, "r.json")


@pytest.mark.slow
def test_tool_reads_results_json(tmp_path):
    """The tool end to end on a results.json that tools/test.py wrote: its recorded counts,
    scaled to --frames, times the --cost."""
    from pcdet_atlas.train_utils.atlas_run import EvalSettings, run_evaluation

    data = REPO_ROOT / "data" / "synthetic_waymo"
    if not (data / "ImageSets" / "val.txt").is_file():
        pytest.skip("needs the demo dataset")
    out = run_evaluation(EvalSettings(
        cfg_file="cfgs/atlas/synthetic/centerpoint.yaml", attacks="clean,rem_40",
        output_root=str(tmp_path), set_cfgs=("DATA_CONFIG.DATA_PATH", str(data)),
        show_progress=False, workers=0,
    ))  # fmt: skip
    results = out["output_dir"] / "results.json"
    cmd = [sys.executable, str(REPO_ROOT / "tools" / "bench" / "cost_model.py"),
           "--results", str(results), "--frames", "1980",
           "--cost", "cfgs/atlas/synthetic/centerpoint.yaml=0.36"]  # fmt: skip
    proc = subprocess.run(cmd, cwd=REPO_ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    row = next(line for line in proc.stdout.splitlines() if line.startswith("| atlas/"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    # 198 clean + 96 rem_40 frames of 396, x10 frames: 2,940 frames x 0.36 s = 0.294 h
    assert cells[4] == "2,940" and cells[6] == "0.3"
