"""OpenPCDet checkpoints of CenterPoint / CP4F load (models/openpcdet_checkpoint.py and
tools/convert_openpcdet_ckpt.py).

OpenPCDet's side is written here from its architecture facts (module nesting, parameter names,
shapes, spconv 1.x's ``(kD, kH, kW, in, out)`` weights), not from the converter: a state_dict
OpenPCDet would save for the config is enumerated, converted, loaded strictly, and what the
model then computes is checked against references that read OpenPCDet's tensors directly.
"""

from __future__ import annotations

import copy

import pytest
import torch
import torch.nn.functional as F
from model_batches import load_tool, make_batch

from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.models import build_network, build_network_from_config, num_point_features_of
from pcdet_atlas.models.detectors.detector3d_template import CheckpointMismatchError
from pcdet_atlas.models.openpcdet_checkpoint import (
    SPCONV_LAYOUTS,
    atlas_to_openpcdet_state,
    detect_spconv_layout,
    openpcdet_to_atlas_state,
)
from pcdet_atlas.ops.spconv import SparseConvTensor

SYNTHETIC = REPO_ROOT / "cfgs" / "atlas" / "synthetic"
BN = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")


# ------------------------------------------------------------ OpenPCDet's names, from facts
def _bn(prefix: str, channels: int) -> dict[str, tuple]:
    return {f"{prefix}.{t}": (() if t == "num_batches_tracked" else (channels,)) for t in BN}


def _spconv(prefix: str, cin: int, cout: int, kernel=(3, 3, 3), bias=False) -> dict[str, tuple]:
    """spconv 1.x: weight (kD, kH, kW, in, out)."""
    out = {f"{prefix}.weight": (*kernel, cin, cout)}
    if bias:
        out[f"{prefix}.bias"] = (cout,)
    return out


def _sparse_basic_block(prefix: str, ch: int) -> dict[str, tuple]:
    # SparseBasicBlock: conv1 / conv2 submanifold 3x3x3 with bias, bn1 / bn2
    return {
        **_spconv(f"{prefix}.conv1", ch, ch, bias=True),
        **_bn(f"{prefix}.bn1", ch),
        **_spconv(f"{prefix}.conv2", ch, ch, bias=True),
        **_bn(f"{prefix}.bn2", ch),
    }


def voxel_res_backbone_8x(cin: int) -> dict[str, tuple]:
    """OpenPCDet's VoxelResBackBone8x under ``backbone_3d``."""
    p = "backbone_3d"
    names = {**_spconv(f"{p}.conv_input.0", cin, 16), **_bn(f"{p}.conv_input.1", 16)}
    names |= _sparse_basic_block(f"{p}.conv1.0", 16) | _sparse_basic_block(f"{p}.conv1.1", 16)
    for stage, (a, b) in zip((2, 3, 4), ((16, 32), (32, 64), (64, 128))):
        names |= _spconv(f"{p}.conv{stage}.0.0", a, b) | _bn(f"{p}.conv{stage}.0.1", b)
        names |= _sparse_basic_block(f"{p}.conv{stage}.1", b)
        names |= _sparse_basic_block(f"{p}.conv{stage}.2", b)
    names |= _spconv(f"{p}.conv_out.0", 128, 128, kernel=(3, 1, 1)) | _bn(f"{p}.conv_out.1", 128)
    return names


def base_bev_backbone(cin: int, bb) -> dict[str, tuple]:
    """OpenPCDet's BaseBEVBackbone: blocks = ZeroPad, conv, BN, ReLU, then (conv, BN, ReLU) x n;
    deblocks = ConvTranspose2d (or a strided Conv2d below stride 1), BN, ReLU."""
    names: dict[str, tuple] = {}
    c_in = [cin, *bb.NUM_FILTERS[:-1]]
    for level, (n, f, up, uf) in enumerate(
        zip(bb.LAYER_NUMS, bb.NUM_FILTERS, bb.UPSAMPLE_STRIDES, bb.NUM_UPSAMPLE_FILTERS)
    ):
        p = f"backbone_2d.blocks.{level}"
        names |= {f"{p}.1.weight": (f, c_in[level], 3, 3)} | _bn(f"{p}.2", f)
        for j in range(n):
            names |= {f"{p}.{4 + 3 * j}.weight": (f, f, 3, 3)} | _bn(f"{p}.{5 + 3 * j}", f)
        q = f"backbone_2d.deblocks.{level}"
        names |= {f"{q}.0.weight": (f, uf, up, up)} | _bn(f"{q}.1", uf)
    return names


def center_head(cin: int, head, num_class: int) -> dict[str, tuple]:
    """OpenPCDet's CenterHead with one SeparateHead: ``heads_list.0.<head>.<k>.0`` conv (bias
    when USE_BIAS_BEFORE_NORM), ``.<k>.1`` BN, and the output conv ``.<num_conv - 1>``."""
    c = head.SHARED_CONV_CHANNEL
    names = {"dense_head.shared_conv.0.weight": (c, cin, 3, 3)}
    names |= {"dense_head.shared_conv.0.bias": (c,)} | _bn("dense_head.shared_conv.1", c)
    heads = {k: (v.out_channels, v.num_conv) for k, v in head.SEPARATE_HEAD_CFG.HEAD_DICT.items()}
    heads["hm"] = (num_class, head.NUM_HM_CONV)
    for name, (out_ch, num_conv) in heads.items():
        p = f"dense_head.heads_list.0.{name}"
        for k in range(num_conv - 1):
            names |= {f"{p}.{k}.0.weight": (c, c, 3, 3), f"{p}.{k}.0.bias": (c,)}
            names |= _bn(f"{p}.{k}.1", c)
        names |= {
            f"{p}.{num_conv - 1}.weight": (out_ch, c, 3, 3),
            f"{p}.{num_conv - 1}.bias": (out_ch,),
        }
    return names


def dyn_pillar_vfe(cin: int, filters) -> dict[str, tuple]:
    """OpenPCDet's DynamicPillarVFE (USE_NORM): PFNLayerV2 ``linear`` (no bias) and ``norm``;
    every layer but the last outputs half its filters (the max is concatenated back)."""
    names: dict[str, tuple] = {}
    widths = [cin + 6, *filters]
    for i in range(len(filters)):
        last = i == len(filters) - 1
        out = widths[i + 1] if last else widths[i + 1] // 2
        names |= {f"vfe.pfn_layers.{i}.linear.weight": (out, widths[i])}
        names |= _bn(f"vfe.pfn_layers.{i}.norm", out)
    return names


def openpcdet_shapes(cfg) -> dict[str, tuple]:
    """Name -> shape of every tensor OpenPCDet's CenterPoint saves for ``cfg``."""
    m = cfg.MODEL
    nfeat = num_point_features_of(cfg.DATA_CONFIG)
    names = {"global_step": (1,)}
    if m.VFE.NAME == "MeanVFE":
        names |= voxel_res_backbone_8x(nfeat)
    else:
        names |= dyn_pillar_vfe(nfeat, m.VFE.NUM_FILTERS)
    names |= base_bev_backbone(m.MAP_TO_BEV.NUM_BEV_FEATURES, m.BACKBONE_2D)
    bev = sum(m.BACKBONE_2D.NUM_UPSAMPLE_FILTERS)
    return names | center_head(bev, m.DENSE_HEAD, len(cfg.CLASS_NAMES))


def openpcdet_state(cfg, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random values under OpenPCDet's names and shapes (BN variances positive)."""
    g = torch.Generator().manual_seed(seed)
    state = {}
    for name, shape in openpcdet_shapes(cfg).items():
        if name == "global_step" or name.endswith("num_batches_tracked"):
            state[name] = torch.randint(0, 1000, shape, generator=g)
        elif name.endswith("running_var"):
            state[name] = torch.rand(shape, generator=g) + 0.5
        else:
            state[name] = torch.randn(shape, generator=g) * 0.3
    return state


def cropped(cfg, cells: int = 64):
    """The model of ``cfg`` on a ``cells`` x ``cells`` crop: same tensors, fast forward."""
    half = cells * cfg.MODEL.VFE.VOXEL_SIZE[0] / 2
    pcr = cfg.DATA_CONFIG.POINT_CLOUD_RANGE
    return build_network(
        cfg.MODEL,
        class_names=cfg.CLASS_NAMES,
        point_cloud_range=[-half, -half, pcr[2], half, half, pcr[5]],
        num_point_features=num_point_features_of(cfg.DATA_CONFIG),
    )


def randomize(model: torch.nn.Module, seed: int) -> None:
    """Random weights and BN statistics (so that eval-mode BN is no identity); the loss weights
    stay the config's."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for key, value in model.state_dict().items():
            if value.is_floating_point() and key != "dense_head.code_weights":  # config
                noise = torch.rand(value.shape, generator=g)
                value.copy_(noise + 0.5 if key.endswith("running_var") else (noise - 0.5) * 0.6)


#: OpenPCDet's real-Waymo models (centerpoint.yaml, centerpoint_4frames.yaml, the dynamic-pillar
#: centerpoint_dyn_pillar_1x.yaml) and the synthetic sizes
CONFIGS = [
    "centerpoint_voxel.yaml",
    "cp4f_voxel.yaml",
    "centerpoint.yaml",
    "synthetic/centerpoint_voxel.yaml",
    "synthetic/cp4f_voxel.yaml",
    "synthetic/cp4f.yaml",
]


# ------------------------------------------------------------------------------ the tests
@pytest.mark.parametrize("name", CONFIGS)
def test_openpcdet_state_loads_strictly_and_exports_back(name):
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "atlas" / name)
    model = build_network_from_config(cfg)
    theirs = openpcdet_state(cfg)
    ours, layout = openpcdet_to_atlas_state(theirs, model)
    assert layout == ("spconv1" if "voxel" in name else None)
    model.load_state_dict(ours, strict=True)
    # the one tensor OpenPCDet does not save comes from the config
    weights = cfg.MODEL.DENSE_HEAD.LOSS_CONFIG.LOSS_WEIGHTS.code_weights
    assert torch.equal(ours["dense_head.code_weights"], torch.tensor(weights))
    # round trips: OpenPCDet -> ours -> OpenPCDet, and ours -> OpenPCDet -> ours, exactly
    back = atlas_to_openpcdet_state(ours, model, spconv_layout="spconv1")
    assert back.keys() == theirs.keys()
    assert all(torch.equal(back[k], theirs[k]) for k in theirs if k != "global_step")
    again, _ = openpcdet_to_atlas_state(back, model)
    assert again.keys() == ours.keys() and all(torch.equal(again[k], ours[k]) for k in ours)


def test_tensors_land_where_openpcdet_uses_them():
    """The converted head computes OpenPCDet's SeparateHead from its tensors (a functional
    reference), and the first sparse conv computes a dense conv3d whose weight is read the
    spconv 1.x way, ``w[kd, kh, kw, in, out]``, at the input sites."""
    cfg = cfg_from_yaml_file(SYNTHETIC / "cp4f_voxel.yaml")
    model = cropped(cfg).eval()  # 64 x 64 voxels: the head on 32 x 32 cells
    theirs = openpcdet_state(cfg, seed=1)
    model.load_state_dict(openpcdet_to_atlas_state(theirs, model)[0], strict=True)

    def t(key):
        return theirs[f"dense_head.{key}"]

    def conv_bn_relu(x, conv, bn):
        x = F.conv2d(x, t(f"{conv}.weight"), t(f"{conv}.bias"), padding=1)
        x = F.batch_norm(x, t(f"{bn}.running_mean"), t(f"{bn}.running_var"), t(f"{bn}.weight"),
                         t(f"{bn}.bias"), eps=1e-5)  # fmt: skip
        return torch.relu(x)

    x = torch.randn(1, sum(cfg.MODEL.BACKBONE_2D.NUM_UPSAMPLE_FILTERS), 32, 32)
    with torch.no_grad():
        got = model.dense_head({"spatial_features_2d": x})["head_outputs"]
        shared = conv_bn_relu(x, "shared_conv.0", "shared_conv.1")
        for name in ("center", "center_z", "dim", "rot", "vel", "hm"):
            p = f"heads_list.0.{name}"
            hidden = conv_bn_relu(shared, f"{p}.0.0", f"{p}.0.1")
            want = F.conv2d(hidden, t(f"{p}.1.weight"), t(f"{p}.1.bias"), padding=1)
            torch.testing.assert_close(got[name], want, rtol=1e-4, atol=1e-4)

    # the first submanifold conv against a dense conv3d (bias-free, 6 -> 16 channels)
    w1 = theirs["backbone_3d.conv_input.0.weight"]  # (3, 3, 3, in, out), spconv 1.x
    g = torch.Generator().manual_seed(0)
    dense = torch.zeros(1, w1.shape[3], 5, 6, 7)
    sites = torch.randperm(5 * 6 * 7, generator=g)[:40]
    z, y, xx = sites // 42, (sites // 7) % 6, sites % 7
    dense[0, :, z, y, xx] = torch.randn(w1.shape[3], 40, generator=g)
    indices = torch.stack([torch.zeros_like(z), z, y, xx], 1).int()
    sparse = SparseConvTensor(dense[0, :, z, y, xx].t(), indices, [5, 6, 7], 1)
    with torch.no_grad():
        out = model.backbone_3d.conv_input[0](sparse).features  # (40, 16)
        ref = F.conv3d(dense, w1.permute(4, 3, 0, 1, 2), padding=1)[0, :, z, y, xx].t()
    torch.testing.assert_close(out, ref, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("layout", sorted(SPCONV_LAYOUTS))
@pytest.mark.parametrize("name", ["cp4f_voxel.yaml", "cp4f.yaml"])
def test_forward_equals_the_model_with_the_same_weights(name, layout):
    """Model A's weights go out under OpenPCDet's names (any spconv layout) and come back into a
    fresh model B: B predicts exactly what A predicts, and B's loss equals A's."""
    cfg = cfg_from_yaml_file(SYNTHETIC / name)
    torch.manual_seed(0)
    a = cropped(cfg)
    randomize(a, seed=3)
    theirs = atlas_to_openpcdet_state(a.state_dict(), a, spconv_layout=layout)
    facts = openpcdet_shapes(cfg)
    assert theirs.keys() == facts.keys()
    for key, shape in facts.items():  # the sparse weights' axis order depends on the layout
        if layout == "spconv1" or not key.startswith("backbone_3d") or theirs[key].dim() < 5:
            assert tuple(theirs[key].shape) == shape, key
    torch.manual_seed(1)
    b = cropped(cfg)
    ours, found = openpcdet_to_atlas_state(theirs, b)
    assert found == (layout if "voxel" in name else None)  # read from the shapes
    b.load_state_dict(ours, strict=True)
    with_vel = a.dense_head.with_velocity
    half = 64 * cfg.MODEL.VFE.VOXEL_SIZE[0] / 2
    batch = make_batch(num_point_features=6, with_velocity=with_vel, extent=half, scale=half / 20)
    a.eval(), b.eval()
    pa, pb = a.predict(batch), b.predict(batch)
    assert sum(len(p["pred_boxes"]) for p in pa) > 0
    for x, y in zip(pa, pb):
        assert x.keys() == y.keys() and all(torch.equal(x[k], y[k]) for k in x)
    la, lb = a.loss(batch), b.loss(batch)
    assert torch.equal(la["loss"], lb["loss"])


def test_mismatches_name_the_keys():
    cfg = cfg_from_yaml_file(SYNTHETIC / "cp4f_voxel.yaml")
    model = build_network_from_config(cfg)
    good = openpcdet_state(cfg)

    extra = dict(good)
    extra["dense_head.heads_list.1.hm.1.weight"] = torch.zeros(1, 32, 3, 3)
    with pytest.raises(
        CheckpointMismatchError,
        match=r"x\.pth .*unexpected dense_head\.heads_list\.1\.hm\.1\.weight.*several CenterHead",
    ):
        openpcdet_to_atlas_state(extra, model, source="x.pth")

    lacking = dict(good)
    del lacking["dense_head.heads_list.0.vel.1.bias"]
    with pytest.raises(CheckpointMismatchError, match=r"missing dense_head\.heads_list\.0\.vel"):
        openpcdet_to_atlas_state(lacking, model)

    pillar = openpcdet_state(cfg_from_yaml_file(SYNTHETIC / "cp4f.yaml"))
    with pytest.raises(
        CheckpointMismatchError,
        match=r"unexpected keys: .*under vfe \(first vfe\.pfn_layers\.0\..*"
        r"missing keys: .*under backbone_3d \(first backbone_3d\.conv",
    ):
        openpcdet_to_atlas_state(pillar, model)  # a pillar checkpoint for the voxel config

    wide = dict(good)
    wide["backbone_2d.blocks.0.1.weight"] = torch.zeros(64, 999, 3, 3)
    with pytest.raises(
        CheckpointMismatchError, match=r"backbone_2d\.blocks\.0\.1\.weight: checkpoint \(64, 999"
    ):
        openpcdet_to_atlas_state(wide, model)

    odd = dict(good)
    odd["backbone_3d.conv_input.0.weight"] = torch.zeros(3, 3, 3, 16, 7)
    with pytest.raises(CheckpointMismatchError, match=r"conv_input\.0\.weight: .*fits no sparse"):
        openpcdet_to_atlas_state(odd, model)

    mixed = dict(good)  # one weight in spconv 2.x's layout, the rest in 1.x's
    mixed["backbone_3d.conv_input.0.weight"] = good["backbone_3d.conv_input.0.weight"].permute(
        4, 0, 1, 2, 3
    )
    with pytest.raises(
        CheckpointMismatchError,
        match=r"different layouts \(backbone_3d\.conv_input\.0\.weight \(16, 3, 3, 3, 6\): "
        r"\['spconv2'\]; backbone_3d\.conv2\.0\.0\.weight \(3, 3, 3, 16, 32\): \['spconv1'\]",
    ):
        openpcdet_to_atlas_state(mixed, model)

    with pytest.raises(CheckpointMismatchError, match=r"native = \(kD, kH, kW, out, in\)"):
        openpcdet_to_atlas_state(good, model, spconv_layout="spconv2-native")
    with pytest.raises(ValueError, match="spconv_layout 'spconv3'"):
        openpcdet_to_atlas_state(good, model, spconv_layout="spconv3")


def test_square_weights_need_the_layout_named():
    """in == out: spconv 1.x's (k, k, k, in, out) and 2.x native's (k, k, k, out, in) have one
    shape, so the shapes alone cannot tell; named, the layout converts."""
    cfg = cfg_from_yaml_file(SYNTHETIC / "centerpoint_voxel.yaml")
    model = build_network_from_config(cfg)
    state = openpcdet_state(cfg)
    own = model.state_dict()
    square = [k for k in own if k.startswith("backbone_3d.conv1.") and k.endswith("conv1.weight")]
    assert square and all(state[k].shape[3] == state[k].shape[4] for k in square)
    with pytest.raises(CheckpointMismatchError, match=r"one of \['spconv1', 'spconv2-native'\]"):
        detect_spconv_layout({k: (state[k].shape, own[k].shape) for k in square}, "x.pth")
    ours, layout = openpcdet_to_atlas_state(state, model, spconv_layout="spconv1")
    assert layout == "spconv1"
    k = square[0]
    assert torch.equal(ours[k], state[k].permute(4, 0, 1, 2, 3))


def test_convert_tool(tmp_path, capsys):
    cfg_path = SYNTHETIC / "cp4f_voxel.yaml"
    cfg = cfg_from_yaml_file(cfg_path)
    src = tmp_path / "openpcdet" / "checkpoint_epoch_36.pth"
    src.parent.mkdir()
    theirs = openpcdet_state(cfg)
    torch.save(
        {"epoch": 36, "it": 1234, "model_state": theirs, "optimizer_state": {"x": 1},
         "version": "pcdet+0.6.0"},
        src,
    )  # fmt: skip
    out = tmp_path / "converted.pth"
    tool = load_tool("convert_openpcdet_ckpt")
    tool.main(["--cfg", str(cfg_path), "--ckpt", str(src), "--out", str(out)])
    assert "loads strictly" in capsys.readouterr().out
    model = build_network_from_config(cfg)
    ckpt = model.load_params_from_file(out, strict=True)
    assert ckpt["epoch"] == 36 and ckpt["it"] == 1234 and "optimizer_state" not in ckpt
    assert ckpt["converted_from"] == {
        "file": str(src), "version": "pcdet+0.6.0", "spconv_layout": "spconv1",
    }  # fmt: skip
    key = "dense_head.head.branches.hm.3.bias"
    assert torch.equal(model.state_dict()[key], theirs["dense_head.heads_list.0.hm.1.bias"])

    with pytest.raises(FileExistsError, match="--overwrite"):
        tool.main(["--cfg", str(cfg_path), "--ckpt", str(src), "--out", str(out)])
    bad = copy.deepcopy(theirs)
    del bad["backbone_3d.conv_out.1.running_var"]
    torch.save({"model_state": bad}, src)
    with pytest.raises(
        CheckpointMismatchError, match=r"checkpoint_epoch_36\.pth.*missing backbone_3d\.conv_out"
    ):
        tool.main(["--cfg", str(cfg_path), "--ckpt", str(src), "--out", str(out), "--overwrite"])
    torch.save({"weights": theirs}, src)
    with pytest.raises(CheckpointMismatchError, match="no 'model_state'"):
        tool.main(["--cfg", str(cfg_path), "--ckpt", str(src), "--out", str(out), "--overwrite"])
