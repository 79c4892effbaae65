"""Smoke tests over every model config in cfgs/atlas/ (timm's test_models habit)."""

import copy
from pathlib import Path

import pytest
import torch
from device_params import DEVICES
from malicious_files import malicious_checkpoint
from model_batches import make_batch

from pcdet_atlas.config import REPO_ROOT, ConfigError, cfg_from_yaml_file
from pcdet_atlas.evaluation.results.archive import archive_name
from pcdet_atlas.models import build_network, build_network_from_config, num_point_features_of
from pcdet_atlas.models.detectors.detector3d_template import CheckpointMismatchError
from pcdet_atlas.registry import DETECTORS
from pcdet_atlas.train_utils import export_model_checkpoint
from pcdet_atlas.utils.safe_pickle import RefusedGlobalError

CONFIGS = sorted((REPO_ROOT / "cfgs" / "atlas").rglob("*.yaml"))
#: single-stage (CenterPoint) configs; two-stage ones are smoke-tested in test_msf.py
SINGLE_STAGE = [p for p in CONFIGS if cfg_from_yaml_file(p).MODEL.NAME == "CenterPoint"]
CELLS = 64  # smoke runs use a cropped grid of CELLS x CELLS pillars / voxels, same model widths
#: configs whose ATLAS.CHECKPOINT names the file a user trains (docs/model_zoo.md), not one that
#: ships
NOT_SHIPPED = {
    "synthetic/centerformer.yaml",
    "synthetic/centerpoint_voxel.yaml",
    "synthetic/dsvt.yaml",
}


def test_there_are_configs():
    names = {str(p.relative_to(REPO_ROOT / "cfgs" / "atlas")) for p in CONFIGS}
    assert {"centerpoint.yaml", "cp4f.yaml", "synthetic/centerpoint.yaml"} <= names
    assert "synthetic/cp4f.yaml" in names
    assert {"centerpoint_voxel.yaml", "cp4f_voxel.yaml"} | NOT_SHIPPED <= names


@pytest.mark.parametrize("folder", ["cfgs/atlas", "cfgs/atlas/synthetic"])
def test_models_that_can_be_reported_together_have_names_apart(folder):
    """A report (and make reproduce's archive) takes one results file per ATLAS.MODEL_NAME, and
    its archive one per name's letters and digits: the configs of one dataset whose checkpoint
    is named (shipped or to be trained; for real Waymo every config) must differ there, or
    reporting them together stops at the end of the evaluations."""
    paths = sorted((REPO_ROOT / folder).rglob("*.yaml") if "synthetic" in folder
                   else (REPO_ROOT / folder).glob("*.yaml"))  # fmt: skip
    named = {}
    for path in paths:
        atlas = cfg_from_yaml_file(path).get("ATLAS", {})
        if "synthetic" in folder and not atlas.get("CHECKPOINT"):
            continue  # a training stage or a development config: nothing evaluates it by default
        named.setdefault(archive_name(atlas.get("MODEL_NAME") or path.stem), []).append(
            str(path.relative_to(REPO_ROOT))
        )
    assert len(named) >= 8
    assert not {name: cfgs for name, cfgs in named.items() if len(cfgs) > 1}


def cropped_model(cfg):
    vs = cfg.MODEL.VFE.VOXEL_SIZE
    pcr = cfg.DATA_CONFIG.POINT_CLOUD_RANGE
    half = CELLS * vs[0] / 2
    crop = [-half, -half, pcr[2], half, half, pcr[5]]
    model_cfg = cfg.MODEL
    if model_cfg.get("BACKBONE_3D", {}).get("NAME") == "DSVT":  # DSVT states its grid thrice
        model_cfg = copy.deepcopy(model_cfg)
        layer = model_cfg.BACKBONE_3D.INPUT_LAYER
        layer.sparse_shape = [CELLS, CELLS, layer.sparse_shape[2]]
        model_cfg.BACKBONE_3D.output_shape = [CELLS, CELLS]
        model_cfg.MAP_TO_BEV.INPUT_SHAPE = [CELLS, CELLS, 1]
    return build_network(
        model_cfg,
        class_names=cfg.CLASS_NAMES,
        point_cloud_range=crop,
        num_point_features=num_point_features_of(cfg.DATA_CONFIG),
    )


@pytest.mark.parametrize("path", SINGLE_STAGE, ids=lambda p: str(p.relative_to(REPO_ROOT / "cfgs")))
def test_build_forward_loss_gradients(path: Path):
    cfg = cfg_from_yaml_file(path)
    full = build_network_from_config(cfg)  # the config as shipped builds
    assert type(full) is DETECTORS.get(cfg.MODEL.NAME)
    # the head's cells are the voxel grid over every stride before it (3D x 2D backbone)
    fms = cfg.MODEL.DENSE_HEAD.TARGET_ASSIGNER_CONFIG.FEATURE_MAP_STRIDE
    grid = full.vfe.grid.grid_size
    assert full.dense_head.feature_map_size == (grid[1] // fms, grid[0] // fms)
    stride_3d = full.backbone_3d.output_stride if full.backbone_3d is not None else 1
    assert stride_3d * full.backbone_2d.output_stride == fms
    torch.manual_seed(0)
    model = cropped_model(cfg)
    # the crop changes no parameter: a checkpoint of one loads strictly into the other
    assert {k: v.shape for k, v in model.state_dict().items()} == {
        k: v.shape for k, v in full.state_dict().items()
    }
    nfeat = model.vfe.num_point_features
    with_vel = model.dense_head.with_velocity
    assert with_vel == (nfeat == 6)  # CP4F: time column and velocity head together
    seq = cfg.DATA_CONFIG.get("SEQUENCE_CONFIG") or {}
    frames = seq.SAMPLE_OFFSET[1] - seq.SAMPLE_OFFSET[0] + 1 if seq.get("ENABLED") else 1
    assert cfg.ATLAS.TEMPORAL_WINDOW == frames  # the lifecycle W is the input window
    half = CELLS * cfg.MODEL.VFE.VOXEL_SIZE[0] / 2
    batch = make_batch(
        num_point_features=nfeat, with_velocity=with_vel, extent=half, scale=half / 20
    )

    model.train()
    ret, tb, disp = model(batch)  # OpenPCDet's training contract, through loss()
    assert set(ret) == {"loss"} and {"loss", "hm_loss", "loc_loss"} <= set(tb)
    assert all(torch.isfinite(torch.tensor(v)) for v in tb.values())
    ret["loss"].backward()
    for name, p in model.named_parameters():
        assert p.grad is not None, f"{name} received no gradient"
        assert torch.isfinite(p.grad).all(), name
    assert "head_outputs" not in batch and "pillar_features" not in batch  # input untouched
    assert "voxel_features" not in batch
    # every parameter is connected to the loss. The batch has 4 objects, and an output bias's
    # L1 gradient is a sum of one +-c per object, which cancels exactly when two residuals are
    # positive and two negative: such a parameter must get a gradient from the same batch with
    # 3 objects (an odd sum of +-c is never 0)
    silent = [name for name, p in model.named_parameters() if not p.grad.abs().sum() > 0]
    if silent:
        model.zero_grad()
        odd = dict(batch, gt_boxes=batch["gt_boxes"].clone())
        assert int((batch["gt_boxes"][..., 3] > 0).sum()) == 4
        odd["gt_boxes"][0, 2] = 0  # sample 0: 2 boxes and padding; sample 1: 1 box
        model(odd)[0]["loss"].backward()
        params = dict(model.named_parameters())
        for name in silent:
            assert params[name].grad.abs().sum() > 0, f"{name} received an all-zero gradient"

    model.eval()
    keep = batch["points"][:, 0] == 0  # sample 1 has no points: empty frames are legal
    preds, recall = model({"points": batch["points"][keep], "batch_size": 2})  # -> predict()
    assert len(preds) == 2 and recall == {}
    for p in preds:
        k = p["pred_boxes"].shape[0]
        assert p["pred_boxes"].shape == (k, 9 if with_vel else 7)
        assert p["pred_scores"].shape == (k,) and p["pred_labels"].shape == (k,)
        assert torch.isfinite(p["pred_boxes"]).all()
        assert ((p["pred_labels"] >= 1) & (p["pred_labels"] <= 3)).all()
        assert (p["pred_scores"][:-1] >= p["pred_scores"][1:]).all()


@pytest.mark.parametrize("name", ["synthetic/centerpoint.yaml", "synthetic/cp4f_voxel.yaml"])
def test_all_empty_batch_predicts_and_trains(name):
    """A batch of empty frames only (0 points, 0 boxes) is legal for a single-frame pillar and
    a multi-frame voxel model: predictions of the right shapes, a finite loss and gradients."""
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "atlas" / name)
    torch.manual_seed(0)
    model = cropped_model(cfg)
    nfeat = model.vfe.num_point_features
    with_vel = model.dense_head.with_velocity
    batch = {"points": torch.zeros(0, 1 + nfeat), "batch_size": 2}
    model.eval()
    with torch.no_grad():
        preds, _ = model(batch)
    assert len(preds) == 2
    for p in preds:
        k = p["pred_boxes"].shape[0]
        assert p["pred_boxes"].shape == (k, 9 if with_vel else 7)
        assert p["pred_scores"].shape == (k,) and torch.isfinite(p["pred_boxes"]).all()
    model.train()
    gt_boxes = torch.zeros(2, 1, 10 if with_vel else 8)  # padding rows only
    ret, tb, _ = model(dict(batch, gt_boxes=gt_boxes))
    assert torch.isfinite(ret["loss"]) and tb["loc_loss"] == 0
    ret["loss"].backward()
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in model.parameters())


def test_unknown_model_key_names_key_and_file(tmp_path):
    path = tmp_path / "bad.yaml"
    src = REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "centerpoint.yaml"
    path.write_text(f"_BASE_CONFIG_: {src}\nMODEL:\n  DENSE_HEAD:\n    NUM_HM_CONVS: 3\n")
    cfg = cfg_from_yaml_file(path)
    with pytest.raises(ConfigError, match=r"NUM_HM_CONVS.*bad\.yaml"):
        build_network_from_config(cfg)


def test_bad_stage_value_names_section_and_file(tmp_path):
    path = tmp_path / "bad.yaml"
    src = REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "centerpoint.yaml"
    path.write_text(f"_BASE_CONFIG_: {src}\nMODEL:\n  VFE:\n    VOXEL_SIZE: [0.7, 0.7, 6.0]\n")
    with pytest.raises(ConfigError, match=r"MODEL\.VFE \(.*bad\.yaml.*whole number of voxels"):
        build_network_from_config(cfg_from_yaml_file(path))


@pytest.mark.parametrize(
    "name,stride,wrong",
    [("centerpoint_voxel.yaml", 8, 1), ("synthetic/centerpoint_voxel.yaml", 2, 4)],
)
def test_head_stride_counts_the_3d_backbone(tmp_path, name, stride, wrong):
    """The head's stride is the 3D backbone's 8x times the BEV backbone's; OpenPCDet's real
    config (BEV backbone at stride 1) needs FEATURE_MAP_STRIDE 8, and another value fails."""
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "atlas" / name)
    model = build_network_from_config(cfg)
    assert model.backbone_3d.output_stride == 8
    assert model.backbone_2d.output_stride * 8 == stride == model.dense_head.feature_map_stride
    path = tmp_path / "bad.yaml"
    path.write_text(
        f"_BASE_CONFIG_: {REPO_ROOT / 'cfgs' / 'atlas' / name}\nMODEL:\n  DENSE_HEAD:\n"
        f"    TARGET_ASSIGNER_CONFIG:\n      FEATURE_MAP_STRIDE: {wrong}\n"
    )
    with pytest.raises(
        ConfigError, match=rf"FEATURE_MAP_STRIDE \({wrong}\) differs .* \({stride} voxels"
    ):
        build_network_from_config(cfg_from_yaml_file(path))


def test_bev_strides_must_divide_the_3d_backbone_output(tmp_path):
    """The BEV backbone sees the 3D backbone's 60 x 60 map (480 voxels / 8), which strides
    [1, 8] cannot divide although they divide the voxel grid."""
    path = tmp_path / "bad.yaml"
    src = REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "centerpoint_voxel.yaml"
    path.write_text(
        f"_BASE_CONFIG_: {src}\nMODEL:\n  BACKBONE_2D:\n    LAYER_STRIDES: [1, 8]\n"
        "    UPSAMPLE_STRIDES: [2, 16]\n"
    )
    with pytest.raises(ConfigError, match=r"product 8\) must divide the BEV map \(60, 60\)"):
        build_network_from_config(cfg_from_yaml_file(path))


def test_wrong_point_columns_raise():
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "centerpoint.yaml")
    model = cropped_model(cfg)
    batch = make_batch(num_point_features=6)
    with pytest.raises(ValueError, match=r"\(N, 1 \+ 5\)"):
        model.loss(batch)


def test_checkpoint_mismatch_is_a_clear_error(tmp_path):
    cfgs = REPO_ROOT / "cfgs" / "atlas" / "synthetic"
    cp = build_network_from_config(cfg_from_yaml_file(cfgs / "centerpoint.yaml"))
    cp4f = build_network_from_config(cfg_from_yaml_file(cfgs / "cp4f.yaml"))
    path = tmp_path / "cp.pth"
    torch.save({"model_state": cp.state_dict(), "epoch": 1}, path)
    with pytest.raises(
        CheckpointMismatchError, match=r"vfe\.pfn_layers\.0\.linear\.weight.*missing"
    ):
        cp4f.load_params_from_file(path)
    ckpt = cp.load_params_from_file(path)  # and a matching one loads strictly
    assert ckpt["epoch"] == 1
    torch.save({"model_state": cp.state_dict(), "optimizer_state": {"x": torch.zeros(9)}}, path)
    small = export_model_checkpoint(path, tmp_path / "small.pth")  # what a model zoo ships
    assert "optimizer_state" not in torch.load(small, weights_only=False)
    cp.load_params_from_file(small)


def test_a_checkpoint_that_would_run_code_or_holds_nan_is_refused(tmp_path):
    """What ``tools/test.py --ckpt``, ``ATLAS.CHECKPOINT`` and ``--pretrained_model`` load:
    read with ``weights_only=True`` (a file naming a global is refused before it runs), and
    NaN/inf weights are an error naming the tensor and the file, not a model scoring 0."""
    cp = build_network_from_config(
        cfg_from_yaml_file(REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "cp4f.yaml")
    )
    marker = tmp_path / "marker"
    path = malicious_checkpoint(tmp_path / "evil.pth", marker, model_state=cp.state_dict())
    with pytest.raises(RefusedGlobalError, match=rf"checkpoint {path} refused: it needs \S+"):
        cp.load_params_from_file(path)
    assert not marker.exists()

    state = cp.state_dict()
    name = "backbone_2d.blocks.0.2.running_var"
    state[name] = state[name].clone()
    state[name][3] = float("nan")
    torch.save({"model_state": state}, path)
    with pytest.raises(ValueError, match=rf"checkpoint {path} holds non-finite .* {name} \(1 of"):
        cp.load_params_from_file(path)
    torch.save({"model_state": [1, 2]}, path)
    with pytest.raises(ValueError, match=rf"checkpoint {path}: 'model_state' is a list"):
        cp.load_params_from_file(path)


@pytest.mark.parametrize("device", DEVICES)
def test_device_generic_and_autocast(device):
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "cp4f.yaml")
    torch.manual_seed(0)
    model = cropped_model(cfg).to(device).train()
    batch = make_batch(num_point_features=6, with_velocity=True, device=device)
    amp_dtype = torch.bfloat16 if device == "cpu" else torch.float16
    for amp in (False, True):
        with torch.autocast(device_type=device, dtype=amp_dtype, enabled=amp):
            losses = model.loss(batch)
        assert losses["loss"].dtype == torch.float32 and torch.isfinite(losses["loss"])
        losses["loss"].backward()
    model.eval()
    preds = model.predict(batch)
    assert preds[0]["pred_boxes"].device.type == device
    assert preds[0]["pred_boxes"].dtype == torch.float32


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: str(p.relative_to(REPO_ROOT / "cfgs")))
def test_shipped_checkpoint_loads_strictly(path: Path):
    cfg = cfg_from_yaml_file(path)
    ckpt = cfg.get("ATLAS", {}).get("CHECKPOINT")
    if ckpt is None or not str(ckpt).startswith("checkpoints/"):
        pytest.skip("this config ships no checkpoint (null, or a training output path)")
    name = str(path.relative_to(REPO_ROOT / "cfgs" / "atlas"))
    if name in NOT_SHIPPED and not (REPO_ROOT / ckpt).is_file():
        pytest.skip(f"{ckpt} is the file a user trains for {name}; it does not ship")
    assert (REPO_ROOT / ckpt).is_file(), f"{ckpt} named by {path.name} does not ship"
    build_network_from_config(cfg).load_params_from_file(REPO_ROOT / ckpt, strict=True)
