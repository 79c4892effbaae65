"""OpenPCDet's own names load: the ``DynPillarVFE`` stage and the
``transform_points_to_voxels_placeholder`` processor whose ``VOXEL_SIZE`` the model reads."""

import copy

import numpy as np
import pytest
import torch

from pcdet_atlas.config import REPO_ROOT, ConfigError, cfg_from_yaml_file
from pcdet_atlas.datasets.augmentor.base import DataProcessor
from pcdet_atlas.models import build_network_from_config
from pcdet_atlas.registry import MODEL_STAGES

CFG = REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "centerpoint.yaml"


def openpcdet_style(cfg, voxel_size):
    """The config as OpenPCDet writes a dynamic-pillar model: the voxel size in the data
    processor, none in MODEL.VFE, the stage named DynPillarVFE."""
    cfg = copy.deepcopy(cfg)
    del cfg.MODEL.VFE["VOXEL_SIZE"]
    cfg.MODEL.VFE.NAME = "DynPillarVFE"
    cfg.DATA_CONFIG.DATA_PROCESSOR.append(
        {"NAME": "transform_points_to_voxels_placeholder", "VOXEL_SIZE": list(voxel_size)}
    )
    return cfg


def test_dyn_pillar_vfe_and_the_placeholder_build_the_same_model():
    ours = cfg_from_yaml_file(CFG)
    assert MODEL_STAGES.get("DynPillarVFE") is MODEL_STAGES.get("DynamicPillarVFE")
    theirs = openpcdet_style(ours, ours.MODEL.VFE.VOXEL_SIZE)
    torch.manual_seed(0)
    a = build_network_from_config(ours)
    torch.manual_seed(0)
    b = build_network_from_config(theirs)
    assert a.vfe.grid == b.vfe.grid
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    # the placeholder leaves the points as they are in the loader's processor chain
    processor = DataProcessor.from_config(
        theirs.DATA_CONFIG.DATA_PROCESSOR[-1:], training=False, point_cloud_range=np.zeros(6)
    )
    points = np.random.default_rng(0).random((50, 5)).astype(np.float32)
    out = processor.forward({"points": points.copy()}, ("seq", 0))
    np.testing.assert_array_equal(out["points"], points)


def test_placeholder_voxel_size_is_checked_and_must_agree_with_the_vfe():
    ours = cfg_from_yaml_file(CFG)
    bad = openpcdet_style(ours, [0.64, 0.64])
    with pytest.raises(ConfigError, match=r"placeholder\.VOXEL_SIZE = \[0\.64, 0\.64\]"):
        build_network_from_config(bad)
    both = openpcdet_style(ours, [0.32, 0.32, 6.0])
    both.MODEL.VFE.VOXEL_SIZE = [0.64, 0.64, 6.0]
    with pytest.raises(ConfigError, match="differs from the DATA_PROCESSOR placeholder"):
        build_network_from_config(both)
    neither = copy.deepcopy(ours)
    del neither.MODEL.VFE["VOXEL_SIZE"]
    with pytest.raises(ConfigError, match="MODEL.VFE needs VOXEL_SIZE"):
        build_network_from_config(neither)
