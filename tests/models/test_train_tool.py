"""tools/train.py end to end on the tiny synthetic dataset: the loss falls, resume is exact."""

import shutil

import pytest
import torch
from model_batches import load_tool

from pcdet_atlas.config import REPO_ROOT

CFG = REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "centerpoint.yaml"


def train_args(root, out, epochs, extra_tag):
    return [
        "--cfg", str(CFG), "--output_root", str(out), "--extra_tag", extra_tag,
        "--epochs", str(epochs), "--batch_size", "2", "--workers", "0", "--no_progress",
        "--fix_random_seed", "--device", "cpu",
        "--set", "DATA_CONFIG.DATA_PATH", str(root),
        "DATA_CONFIG.DATA_AUGMENTOR.DISABLE_AUG_LIST", "gt_sampling",
        "DATA_CONFIG.SAMPLED_INTERVAL", "train:5,test:5",
        # a 64 x 64 pillar crop keeps the test fast; the model widths are the config's
        "DATA_CONFIG.POINT_CLOUD_RANGE", "-20.48,-20.48,-2,20.48,20.48,4",
        "OPTIMIZATION.LR", "0.01",
    ]  # fmt: skip


@pytest.mark.slow
def test_train_lowers_loss_and_resumes_bit_exactly(synthetic_root, tmp_path):
    train = load_tool("train")
    out = tmp_path / "output"
    full = train.main(train_args(synthetic_root, out, 3, "full"))
    run_dir = full["output_dir"]
    assert run_dir == out / "atlas" / "synthetic" / "centerpoint" / "full"
    history = full["state"].history
    assert len(history) == 3 and full["state"].it == 6  # 4 frames / batch 2 = 2 steps per epoch
    assert history[-1]["loss"] < history[0]["loss"]
    assert (run_dir / "centerpoint.yaml").is_file()
    assert list(run_dir.glob("train_*.log")) and list((run_dir / "tensorboard").iterdir())
    ckpts = sorted(p.name for p in (run_dir / "ckpt").iterdir())
    assert ckpts == [f"checkpoint_epoch_{e}.pth" for e in (1, 2, 3)]

    # an interrupted run (only epoch 2's checkpoint left) resumes to the same weights, bit for bit
    resumed_dir = out / "atlas" / "synthetic" / "centerpoint" / "resumed" / "ckpt"
    resumed_dir.mkdir(parents=True)
    shutil.copy(run_dir / "ckpt" / "checkpoint_epoch_2.pth", resumed_dir)
    resumed = train.main(train_args(synthetic_root, out, 3, "resumed"))
    assert resumed["state"].epoch == 3 and resumed["state"].it == 6
    assert len(resumed["state"].history) == 1  # only epoch 3 was trained here
    a = torch.load(run_dir / "ckpt" / "checkpoint_epoch_3.pth", weights_only=False)
    b = torch.load(resumed_dir / "checkpoint_epoch_3.pth", weights_only=False)
    assert a["model_state"].keys() == b["model_state"].keys()
    for k in a["model_state"]:
        assert torch.equal(a["model_state"][k], b["model_state"][k]), k
    assert a["scheduler_state"]["last_epoch"] == b["scheduler_state"]["last_epoch"] == 6
    assert history[-1] == resumed["state"].history[0]
