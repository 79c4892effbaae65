"""A third attack family, registered here and nowhere else, runs end to end through
``tools/test.py`` into ``results.json``, the printed table and the robustness ranks: how it is
scored travels with its class (``SUCCESS_IF_DETECTED``, ``CONFIDENCE``, ``RANK_GROUP``)."""

import copy

import numpy as np
import pytest
import torch
from model_batches import load_tool

from pcdet_atlas.attacks.base import BaseAttack, FrameAttack
from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.evaluation import load_results, ranks_from_results
from pcdet_atlas.models import build_network_from_config
from pcdet_atlas.ops.boxes import points_in_boxes_mask
from pcdet_atlas.registry import ATTACKS

CFG = REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "centerpoint.yaml"


class BoxEraser(BaseAttack):
    """Erases every point of the nearest vehicle on spoofed frames; succeeds when it is missed."""

    family = "box_eraser"
    SUCCESS_IF_DETECTED = False
    CONFIDENCE = None
    RANK_GROUP = "erasure"

    @classmethod
    def from_config(cls, cfg, data_root=None):
        return cls(**cls._common_kwargs(cfg))

    def prepare_run(self, seq, run_id):
        return run_id

    def attack_frame(self, scene_xyz, seq, frame_idx, run, state):
        labels = seq.labels(frame_idx)
        vehicles = np.flatnonzero(labels.names == "Vehicle")
        if vehicles.size == 0:
            return FrameAttack(None, np.zeros((0, 5), np.float32), self.meta(state))
        nearest = vehicles[np.argmin(np.linalg.norm(labels.boxes[vehicles, :2], axis=1))]
        box = labels.boxes[nearest]
        inside = points_in_boxes_mask(np.asarray(scene_xyz, np.float64), box[None])[0]
        meta = self.meta(state, target_box=box, num_removed=int(inside.sum()), fired=True)
        return FrameAttack(~inside, np.zeros((0, 5), np.float32), meta)

    def shadow_meta(self, seq, frame_idx, run, state):
        return self.meta(state)


@pytest.fixture(scope="module")
def registered():
    if "TestBoxEraser" not in ATTACKS:
        ATTACKS.register("TestBoxEraser")(BoxEraser)


@pytest.mark.slow
def test_third_family_reaches_results_table_and_ranks(registered, synthetic_root, tmp_path, capsys):
    torch.manual_seed(0)
    model = build_network_from_config(cfg_from_yaml_file(CFG))
    ckpt = tmp_path / "random.pth"
    torch.save({"model_state": model.state_dict(), "epoch": 0}, ckpt)
    variant = tmp_path / "erase_nearest.yaml"
    variant.write_text(
        f"_BASE_CONFIG_: {REPO_ROOT / 'cfgs/attacks/_base_/common.yaml'}\n"
        "NAME: TestBoxEraser\nVARIANT: erase_nearest\n"
    )
    out = load_tool("test").main([
        "--cfg", str(CFG), "--ckpt", str(ckpt), "--attacks", f"clean,{variant}",
        "--out_dir", str(tmp_path / "output"), "--workers", "0", "--no_progress",
        "--device", "cpu", "--set", "DATA_CONFIG.DATA_PATH", str(synthetic_root),
        "DATA_CONFIG.SAMPLED_INTERVAL", "train:1,test:14",  # frames 42 and 56 are spoofed
    ])  # fmt: skip
    printed = capsys.readouterr().out
    results = load_results(out["output_dir"] / "results.json")
    entry = results["variants"]["erase_nearest"]
    assert entry["family"] == "box_eraser" and entry["rank_group"] == "erasure"
    assert entry["num_targets"] == 2 and entry["confidence"] is None
    # a random-weight detector misses the erased vehicles: every target is a success
    assert entry["num_success"] == 2 and entry["asr"] == 1.0
    assert results["variants"]["clean"]["rank_group"] is None
    row = next(line for line in printed.splitlines() if "erase_nearest" in line)
    assert "1.00" in row.split()
    other = copy.deepcopy(results)
    other["model"] = "other"
    other["variants"]["erase_nearest"]["asr"] = 0.5
    ranks = ranks_from_results([results, other])
    assert ranks["group_ranks"] == {"erasure": {"other": 1.0, results["model"]: 2.0}}
