"""Config values that would be ignored or misread are errors naming the key and the file: the
two-stage NMS section, the ROI sampler and loss weights, a voxel size that disagrees with the
data's, and a checkpoint that shares nothing with the model."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from pcdet_atlas.config import REPO_ROOT, ConfigError, cfg_from_yaml_file
from pcdet_atlas.models import build_network, build_network_from_config, num_point_features_of
from pcdet_atlas.models.detectors.detector3d_template import (
    CheckpointMismatchError,
    load_state_dict_checked,
)
from pcdet_atlas.models.model_utils.roi_sampler import RoiSamplerConfig
from pcdet_atlas.models.roi_heads.msf_head import MSFHead

SYNTHETIC = REPO_ROOT / "cfgs" / "atlas" / "synthetic"


def two_stage_yaml(tmp_path, post: str):
    path = tmp_path / "bad.yaml"
    path.write_text(
        f"_BASE_CONFIG_: {SYNTHETIC / 'msf_4f.yaml'}\nMODEL:\n  POST_PROCESSING:\n{post}"
    )
    return cfg_from_yaml_file(path)


@pytest.mark.parametrize(
    "post, match",
    [
        ("    NMS_CONFIG:\n      NMS_THRES: 0.5\n", r"'NMS_THRES'.*NMS_CONFIG.*bad\.yaml"),
        ("    NMS_CONFIG:\n      NMS_TYPE: nms_3d\n", r"NMS_TYPE = 'nms_3d'.*bad\.yaml"),
        ("    NMS_CONFIG:\n      MULTI_CLASSES_NMS: True\n", r"MULTI_CLASSES_NMS.*bad\.yaml"),
        ("    NOT_APPLY_NMS_FOR_VEL: 'no'\n", r"NOT_APPLY_NMS_FOR_VEL = 'no'.*bad\.yaml"),
    ],
)
def test_two_stage_nms_config_rejects_what_it_would_ignore(tmp_path, post, match):
    with pytest.raises(ConfigError, match=match):
        build_network_from_config(two_stage_yaml(tmp_path, post))


@pytest.mark.parametrize(
    "cfg, match",
    [
        ({"fg_ratio": 1.5}, "FG_RATIO must be a number in"),
        ({"roi_per_image": 0}, "ROI_PER_IMAGE must be >= 1"),
        ({"roi_per_image": 9.5}, "ROI_PER_IMAGE must be an integer"),
        ({"cls_fg_thresh": 0.2}, "CLS_BG_THRESH .* below CLS_FG_THRESH"),
        ({"hard_bg_ratio": "0.8"}, "HARD_BG_RATIO"),
        ({"by_class": "yes"}, "SAMPLE_ROI_BY_EACH_CLASS"),
    ],
)
def test_roi_sampler_config_rejects_bad_values(cfg, match):
    with pytest.raises(ValueError, match=match):
        RoiSamplerConfig(**cfg)
    RoiSamplerConfig()  # MSF's values are valid


@pytest.mark.parametrize(
    "weights, match",
    [
        ({"traj_reg_weight": [2.0]}, "traj_reg_weight needs 3"),
        ({"code_weights": [1.0]}, "code_weights needs 7"),  # would broadcast silently
        ({"code_weights": 1.0}, "code_weights needs 7"),
    ],
)
def test_roi_head_loss_weights_need_one_per_term(weights, match):
    kwargs = dict(
        num_class=3, num_point_features=6, num_frames=2, num_points=8, hidden_dim=16, nheads=2,
        point_nheads=2, enc_layers=1, bifa_layers=1, dim_feedforward=16, dropout=0.0,
        embed_dim=8,
    )  # fmt: skip
    with pytest.raises(ValueError, match=match):
        MSFHead(**kwargs, loss_weights=weights)
    MSFHead(**kwargs, loss_weights={"traj_reg_weight": [2.0] * 3, "code_weights": [1.0] * 7})


def test_mean_vfe_voxel_size_must_match_the_data_placeholder():
    cfg = cfg_from_yaml_file(SYNTHETIC / "centerpoint_voxel.yaml")
    args = dict(
        class_names=cfg.CLASS_NAMES,
        point_cloud_range=cfg.DATA_CONFIG.POINT_CLOUD_RANGE,
        num_point_features=num_point_features_of(cfg.DATA_CONFIG),
    )
    with pytest.raises(ConfigError, match=r"MODEL\.VFE\.VOXEL_SIZE .*centerpoint_voxel\.yaml"):
        build_network(cfg.MODEL, **args, voxel_size=(0.16, 0.16, 0.15))


def test_non_strict_load_of_a_foreign_checkpoint_raises():
    model = nn.Linear(2, 2)
    with pytest.raises(CheckpointMismatchError, match="shares no parameter name"):
        load_state_dict_checked(model, {"other.weight": torch.zeros(2)}, strict=False, source="x")
    partial = {"weight": torch.ones(2, 2)}  # a partial one still loads what it has
    load_state_dict_checked(model, partial, strict=False, source="x")
    assert torch.equal(model.weight, torch.ones(2, 2))
