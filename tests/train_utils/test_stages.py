"""Staged training starts from a finished predecessor: a newest checkpoint short of the
predecessor's configured epochs is refused, naming it, unless asked."""

import re

import pytest
import torch

from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.train_utils.setup import load_cfg, output_dir_for
from pcdet_atlas.train_utils.stages import stage_from_config, stage_init_checkpoint
from pcdet_atlas.utils.common import load_tool

STAGES = REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "phim_lot"


def test_a_stage_refuses_a_predecessor_short_of_its_epochs(tmp_path):
    stage = stage_from_config(cfg_from_yaml_file(STAGES / "stage2_ssm.yaml"))
    stage1 = load_cfg(str(STAGES / "stage1_score.yaml"), None)
    ckpt_dir = output_dir_for(stage1, tmp_path, "x") / "ckpt"
    ckpt_dir.mkdir(parents=True)
    first = ckpt_dir / "checkpoint_epoch_1.pth"  # a 5-epoch run stopped after its first epoch
    torch.save({"epoch": 1, "train_settings": {"OPTIMIZATION": {"NUM_EPOCHS": 5}}}, first)

    def init(**kw):
        return stage_init_checkpoint(
            stage, output_root=tmp_path, extra_tag="x", pretrained_model=None, **kw
        )

    with pytest.raises(ValueError) as err:
        init()
    message = str(err.value)
    assert re.search(
        rf"stage2_ssm .*{re.escape(str(first))}, trained 1 of its 5 configured", message
    )
    assert "--allow_partial_stage_init" in message
    assert init(allow_partial=True) == first
    # without recorded settings the predecessor's config says how many epochs (5)
    torch.save({"epoch": 1}, first)
    with pytest.raises(ValueError, match=r"1 of its 5 configured epochs \(OPTIMIZATION"):
        init()
    # a run trained with --epochs 1 is finished: its checkpoint records the epochs in effect
    torch.save({"epoch": 1, "train_settings": {"OPTIMIZATION": {"NUM_EPOCHS": 1}}}, first)
    assert init() == first
    last = ckpt_dir / "checkpoint_epoch_5.pth"
    torch.save({"epoch": 5, "train_settings": {"OPTIMIZATION": {"NUM_EPOCHS": 5}}}, last)
    assert init() == last


def test_train_has_the_flag_with_its_help(capsys):
    train = load_tool("train")
    assert train.parse_args(
        ["--cfg", "x.yaml", "--allow_partial_stage_init"]
    ).allow_partial_stage_init
    assert not train.parse_args(["--cfg", "x.yaml"]).allow_partial_stage_init
    with pytest.raises(SystemExit):
        train.parse_args(["--help"])
    assert "short of the predecessor's configured epochs" in " ".join(
        capsys.readouterr().out.split()
    )
