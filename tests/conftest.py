"""Shared pytest fixtures.

``synthetic_root``: a tiny synthetic Waymo-format dataset generated once per test session
(train: 2 sequences x 10 frames; val: 1 sequence x 70 frames, enough for one full 32-frame
attack run 32..63 plus 6 frames after it), in OpenPCDet's processed layout.

``real_rpn_checkpoint``: a checkpoint of the real-Waymo voxel CP-4f with random weights (the RPN of
the real two-stage configs, which does not ship).

``injection``: the loaded ``inj_global_hard`` attack config with a trace library built from
``synthetic_root`` (traces of at least 100 points).
"""

from __future__ import annotations

import pytest

SYNTHETIC_FIXTURE_SEED = 0
SYNTHETIC_FIXTURE_SEQUENCES = {"train": 2, "val": 1}
SYNTHETIC_FIXTURE_FRAMES = {"train": 10, "val": 70}


@pytest.fixture(scope="session")
def synthetic_root(tmp_path_factory):
    """Path of a session-cached tiny synthetic dataset (read it, do not modify it)."""
    from pcdet_atlas.datasets.synthetic import create_synthetic_waymo

    root = tmp_path_factory.mktemp("synthetic_waymo")
    create_synthetic_waymo(
        root,
        num_sequences=SYNTHETIC_FIXTURE_SEQUENCES,
        frames_per_sequence=SYNTHETIC_FIXTURE_FRAMES,
        seed=SYNTHETIC_FIXTURE_SEED,
        workers=2,
    )
    return root


@pytest.fixture(scope="session")
def injection(synthetic_root, tmp_path_factory):
    """``inj_global_hard`` on the fixture dataset (module docstring)."""
    from pcdet_atlas.attacks.trace_library import TraceFilter, build_trace_library
    from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file

    tmp = tmp_path_factory.mktemp("injection")
    attack_cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "attacks" / "inj_global_hard.yaml")
    attack_cfg.TRACE_LIBRARY.MIN_POINTS = 100
    lib = build_trace_library(synthetic_root, TraceFilter.from_config(attack_cfg.TRACE_LIBRARY))
    attack_cfg.TRACE_LIBRARY.PATH = str(lib.save(tmp / "lib.npz"))
    return attack_cfg


@pytest.fixture(scope="session")
def real_rpn_checkpoint(tmp_path_factory):
    """Random weights of ``cfgs/atlas/cp4f_voxel.yaml`` (module docstring)."""
    import torch

    from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
    from pcdet_atlas.models import build_network_from_config

    torch.manual_seed(0)
    rpn = build_network_from_config(cfg_from_yaml_file(REPO_ROOT / "cfgs/atlas/cp4f_voxel.yaml"))
    path = tmp_path_factory.mktemp("rpn") / "cp4f_random.pth"
    torch.save({"model_state": rpn.state_dict()}, path)
    return path
