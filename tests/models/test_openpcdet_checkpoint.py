"""OpenPCDet checkpoints of CenterPoint / CP4F load (models/openpcdet_checkpoint.py and
tools/data/convert_openpcdet_ckpt.py).

OpenPCDet's side is written here from its architecture facts (module nesting, parameter names,
shapes, spconv 1.x's ``(kD, kH, kW, in, out)`` weights), not from the converter: a state_dict
OpenPCDet would save for the config is enumerated, converted, loaded strictly, and what the
model then computes is checked against references that read OpenPCDet's tensors directly.
"""

from __future__ import annotations

import collections
import copy

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from malicious_files import malicious_checkpoint
from model_batches import load_tool, make_batch, two_stage_batch

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
from pcdet_atlas.utils.safe_pickle import RefusedGlobalError

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
    return released_state(openpcdet_shapes(cfg), seed)


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

    square_first = {  # a square weight (two layouts) before one that fits a third
        "a.conv1.weight": ((3, 3, 3, 16, 16), (16, 3, 3, 3, 16)),
        "b.conv2.weight": ((32, 3, 3, 3, 16), (32, 3, 3, 3, 16)),
    }
    with pytest.raises(
        CheckpointMismatchError,
        match=r"y\.pth: .*different layouts \(b\.conv2\.weight \(32, 3, 3, 3, 16\): "
        r"\['spconv2'\]; a\.conv1\.weight \(3, 3, 3, 16, 16\): \['spconv1', 'spconv2-native'\]",
    ):
        detect_spconv_layout(square_first, "y.pth")

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


def test_convert_tool(tmp_path, capsys, monkeypatch):
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
    tool = load_tool("data/convert_openpcdet_ckpt")
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
    # a conversion that fails its strict load leaves no --out (nor its staged file) behind
    from pcdet_atlas.models.detectors.detector3d_template import Detector3DTemplate

    def fails(self, filename, **kw):
        raise RuntimeError(f"strict load of {filename} failed")

    with monkeypatch.context() as patch:
        patch.setattr(Detector3DTemplate, "load_params_from_file", fails)
        with pytest.raises(RuntimeError, match=r"c\.pth\.unchecked failed"):
            tool.main(
                ["--cfg", str(cfg_path), "--ckpt", str(src), "--out", str(tmp_path / "c.pth")]
            )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["converted.pth", "openpcdet"]
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


def openpcdet_file(path, model_state, *, numpy_1: bool = False) -> None:
    """A checkpoint as OpenPCDet's ``save_checkpoint`` writes it: the legacy (non-zip) format,
    an ``OrderedDict`` state, an ``optimizer_state`` whose ``lr`` and ``betas`` its
    ``adam_onecycle`` schedule set to numpy float64 scalars; ``numpy_1``: numpy 1.x's names."""
    param = torch.nn.Parameter(torch.ones(2))
    optimizer = torch.optim.Adam([param], lr=0.0)
    param.sum().backward()
    optimizer.step()
    optimizer.param_groups[0]["lr"] = np.float64(0.003) * np.cos(0.5)
    optimizer.param_groups[0]["betas"] = (np.float64(0.95), np.float64(0.99))
    state = {"epoch": 36, "it": 1234, "model_state": collections.OrderedDict(model_state),
             "optimizer_state": optimizer.state_dict(), "version": "pcdet+0.6.0"}  # fmt: skip
    torch.save(state, path, _use_new_zipfile_serialization=False)
    if numpy_1:
        path.write_bytes(path.read_bytes().replace(b"numpy._core.", b"numpy.core."))


@pytest.mark.parametrize("numpy_1", [False, True], ids=["numpy2", "numpy1"])
def test_convert_tool_reads_openpcdet_files_without_running_code(tmp_path, numpy_1):
    """OpenPCDet's own files convert under ``weights_only`` (the numpy scalars of its optimizer
    state allow-listed); a file naming anything else is refused before it runs."""
    cfg_path = SYNTHETIC / "cp4f.yaml"
    theirs = openpcdet_state(cfg_from_yaml_file(cfg_path))
    src, out = tmp_path / "checkpoint_epoch_36.pth", tmp_path / "converted.pth"
    openpcdet_file(src, theirs, numpy_1=numpy_1)
    assert (b"numpy.core.multiarray" in src.read_bytes()) == numpy_1
    tool = load_tool("data/convert_openpcdet_ckpt")
    tool.main(["--cfg", str(cfg_path), "--ckpt", str(src), "--out", str(out)])
    assert torch.load(out, weights_only=True)["epoch"] == 36

    marker = tmp_path / "marker"
    malicious_checkpoint(src, marker, model_state=theirs)
    with pytest.raises(RefusedGlobalError, match=rf"checkpoint {src} refused: it needs \S+"):
        tool.main(["--cfg", str(cfg_path), "--ckpt", str(src), "--out", str(out), "--overwrite"])
    assert not marker.exists()


def test_convert_tool_refuses_non_finite_weights_and_a_model_state_of_another_kind(tmp_path):
    cfg_path = SYNTHETIC / "cp4f.yaml"
    theirs = openpcdet_state(cfg_from_yaml_file(cfg_path))
    src, out = tmp_path / "checkpoint_epoch_36.pth", tmp_path / "converted.pth"
    args = ["--cfg", str(cfg_path), "--ckpt", str(src), "--out", str(out)]
    tool = load_tool("data/convert_openpcdet_ckpt")
    name = "dense_head.heads_list.0.hm.1.bias"
    for bad in (float("nan"), float("inf")):
        broken = {**theirs, name: theirs[name].clone()}
        broken[name][0] = bad
        openpcdet_file(src, broken)
        with pytest.raises(ValueError, match=rf"checkpoint {src} holds non-finite .*{name} \(1 of"):
            tool.main(args)
        assert not out.exists()
    for state, expected in (
        ([1, 2], r"'model_state' is a list, expected a mapping"),
        ({**theirs, "extra": 3}, r"'model_state' entries \['extra'\] are not tensors"),
    ):
        torch.save({"model_state": state}, src)
        with pytest.raises(ValueError, match=rf"checkpoint {src}: {expected}"):
            tool.main(args)


# ------------------------------------- the MSF and PTT repositories' second stages, from facts
# Their detectors (MSF; PTT's config names MPPNet) build only ``roi_head``: a checkpoint holds
# ``global_step`` and ``roi_head.*``; the CenterPoint-4f that proposed is a checkpoint of its own.
def _linear(prefix: str, cout: int, cin: int, bias: bool = True) -> dict[str, tuple]:
    return {f"{prefix}.weight": (cout, cin)} | ({f"{prefix}.bias": (cout,)} if bias else {})


def _conv1d(prefix: str, cout: int, cin: int) -> dict[str, tuple]:
    """``nn.Conv1d(cin, cout, 1)``: weight (out, in, 1), bias."""
    return {f"{prefix}.weight": (cout, cin, 1), f"{prefix}.bias": (cout,)}


def _ln(prefix: str, channels: int) -> dict[str, tuple]:
    return {f"{prefix}.weight": (channels,), f"{prefix}.bias": (channels,)}


def _mha(prefix: str, channels: int) -> dict[str, tuple]:
    """``nn.MultiheadAttention(channels, heads)``: packed in-projection, out-projection."""
    return {
        f"{prefix}.in_proj_weight": (3 * channels, channels),
        f"{prefix}.in_proj_bias": (3 * channels,),
        **_linear(f"{prefix}.out_proj", channels, channels),
    }


def _mlp(prefix: str, cin: int, hidden: int, cout: int, layers: int) -> dict[str, tuple]:
    """The repositories' ``MLP``: ``layers.<k>`` Linear, ``layers - 1`` of width ``hidden``."""
    dims = [cin, *[hidden] * (layers - 1), cout]
    return {
        k: v for i in range(layers) for k, v in _linear(f"{prefix}.layers.{i}", dims[i + 1],
                                                        dims[i]).items()
    }  # fmt: skip


def _pointnet_heads(prefix: str, width: int) -> dict[str, tuple]:
    """fc_ce / fc_s / fc_hr: width -> 256 -> 3, 3, 1 (the last without bias)."""
    names: dict[str, tuple] = {}
    for head, out in (("ce", 3), ("s", 3), ("hr", 1)):
        names |= _linear(f"{prefix}.fc_{head}1", 256, width)
        names |= _linear(f"{prefix}.fc_{head}2", out, 256, bias=False)
    return names


def msf_released_shapes(
    frames: int = 4, width: int = 256, ffn: int = 512, layers: int = 3, bifa_layers: int = 2
) -> dict[str, tuple]:
    """Name -> shape of every tensor of the MSF repository's checkpoint (msf_4frames.yaml sizes:
    TRANS_INPUT 256, dim_feedforward 512, enc_layers 3, num_groups 4). ``bifa_layers``: the
    encoder layers with BiFA (``cross_conv_*``), 2 for the first model built in a process."""
    p = "roi_head"
    names: dict[str, tuple] = {"global_step": (1,)}
    names |= _mlp(f"{p}.up_dimension_geometry", 29, 64, width, 3)
    names |= _mlp(f"{p}.up_dimension_motion", 30, 64, width, 3)
    names |= _mlp(f"{p}.jointembed", width * (frames + 1), width, 7, 4)
    q = f"{p}.seqboxembed"  # PointNet(8): PointNetfeat convs, fc1 / fc2, three heads
    names |= _bn(f"{q}.pre_bn", 8)
    for k, (cin, cout) in enumerate(zip((8, 64, 128, 256), (64, 128, 256, 512)), start=1):
        names |= _conv1d(f"{q}.feat.conv{k}", cout, cin) | _bn(f"{q}.feat.bn{k}", cout)
    names |= _linear(f"{q}.fc1", 256, 512) | _bn(f"{q}.bn1", 256)
    names |= _linear(f"{q}.fc2", width, 256) | _bn(f"{q}.bn2", width)
    names |= _pointnet_heads(q, width)
    names[f"{p}.transformer.token"] = (frames, 1, width)
    for layer in range(layers):
        e = f"{p}.transformer.encoder.layers.{layer}"
        names |= _mha(f"{e}.self_attn", width) | _ln(f"{e}.norm1", width) | _ln(f"{e}.norm2", width)
        names |= _linear(f"{e}.linear1", ffn, width) | _linear(f"{e}.linear2", width, ffn)
        if layer < bifa_layers:
            for k in (1, 2):
                names |= _linear(f"{e}.cross_conv_{k}", width, 2 * width)
                names |= _ln(f"{e}.cross_norm_{k}", width)
        m = f"{e}.mlp_mixer_3d"  # SpatialMixerBlock: 8 heads, feed-forward 2 x width
        names |= _mha(f"{m}.mixer", width) | _ln(f"{m}.norm", width)
        names |= _ln(f"{m}.norm_channel", width)
        names |= _linear(f"{m}.ffn.0", 2 * width, width) | _linear(f"{m}.ffn.3", width, 2 * width)
    names |= _linear(f"{p}.class_embed.0", 1, width)
    for group in range(frames):
        names |= _mlp(f"{p}.bbox_embed.{group}", width, width, 7, 4)
    return names


def ptt_released_shapes(width: int = 256) -> dict[str, tuple]:
    """Name -> shape of every tensor of the PTT repository's checkpoint (ptt_32frames.yaml:
    TRANS_INPUT 256, two POOL_RADIUS, ROI_GRID_POOL.MLPS [[128, 128]] x 2, num_groups 4,
    use_grid_pos index); the transformer ``PTTransformer(8)`` is ``roi_head.ptt``."""
    p, q = "roi_head", "roi_head.ptt"
    names: dict[str, tuple] = {"global_step": (1,)}
    names |= _mlp(f"{p}.jointembed", 2 * width, width, 7, 4)
    names |= _linear(f"{p}.fc", 256, 512) | _bn(f"{p}.bn", 256)
    names |= _mlp(f"{p}.up_dimension_geometry", 29, 64, width // 2, 3)
    names |= _mlp(f"{p}.up_dimension_motion", 30, 64, width // 2, 3)
    for i in range(2):  # StackSAModuleMSG: Conv2d(128 + 3, 128, 1, bias=False), BatchNorm2d
        names[f"{p}.roi_grid_pool_layer.mlps.{i}.0.weight"] = (128, 131, 1, 1)
        names |= _bn(f"{p}.roi_grid_pool_layer.mlps.{i}.1", 128)
    names |= _linear(f"{p}.class_embed.0", 1, width)
    for group in range(4):
        names |= _mlp(f"{p}.bbox_embed.{group}", width, width, 7, 4)
    names |= _mlp(f"{p}.grid_pos_embeded", 3, 256, width, 2)
    names |= _linear(f"{q}.fc1", 256, 512) | _linear(f"{q}.fc2", width, 256)
    names |= _bn(f"{q}.pre_bn", 8) | _bn(f"{q}.x_bn1", 256) | _bn(f"{q}.x_bn2", width)
    names |= _pointnet_heads(q, width)
    for conv, cout, cin in (
        ("conv1", 64, 8), ("conv2", 128, 96), ("conv2_p", 32, 256), ("conv2_long", 256, 128),
        ("conv2_short", 256, 128), ("conv2_future", 256, 128), ("conv_future", 64, 96),
        ("conv_point", 256, 768), ("conv_final", 512, 768), ("conv3", 256, 128),
        ("conv4", 512, 256),
    ):  # fmt: skip
        names |= _conv1d(f"{q}.{conv}", cout, cin)
    for bn, channels in (
        ("bn2_long", 256), ("bn2_short", 256), ("bn2_future", 256), ("bn_future", 64),
        ("bn_point", 256), ("bn_final", 512), ("bn1", 64), ("bn2", 128), ("bn2_p", 32),
        ("bn3", 256), ("bn4", 512),
    ):  # fmt: skip
        names |= _bn(f"{q}.{bn}", channels)
    for attn, dim in (
        ("attn1_long", 96), ("attn1_short", 96), ("attn1_future", 96), ("attn1", 64),
        ("attn2", 128), ("attn3", 256), ("attn3_point", 256), ("cross_long", 256),
        ("cross_short", 256), ("cross_future", 256),
    ):  # fmt: skip
        for part in ("q", "k", "v", "o"):
            names |= _linear(f"{q}.{attn}.fc_{part}", dim, dim)
    names[f"{q}.future_token"] = (1, 1, 32)
    return names


def released_state(shapes: dict[str, tuple], seed: int = 0) -> dict[str, torch.Tensor]:
    """Random values of ``shapes`` (BN variances positive, counters integer)."""
    g = torch.Generator().manual_seed(seed)
    state = {}
    for name, shape in shapes.items():
        if name == "global_step" or name.endswith("num_batches_tracked"):
            state[name] = torch.randint(0, 1000, shape, generator=g)
        elif name.endswith("running_var"):
            state[name] = torch.rand(shape, generator=g) + 0.5
        else:
            state[name] = torch.randn(shape, generator=g) * 0.3
    return state


def released_sizes(name: str):
    """``cfgs/atlas/<name>`` (the released head sizes) with the synthetic RPN of
    ``synthetic/<name>`` (a shipped checkpoint; the real RPN does not ship)."""
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "atlas" / name)
    cfg.MODEL.RPN = cfg_from_yaml_file(SYNTHETIC / name).MODEL.RPN
    return cfg


def _functional(theirs: dict[str, torch.Tensor], prefix: str = "roi_head."):
    """Linear, BatchNorm (channels second) and LayerNorm read from released tensors."""

    def t(key):
        return theirs[prefix + key]

    def linear(x, p):
        return F.linear(x, t(f"{p}.weight"), theirs.get(f"{prefix}{p}.bias"))

    def bn(x, p):
        return F.batch_norm(x, t(f"{p}.running_mean"), t(f"{p}.running_var"), t(f"{p}.weight"),
                            t(f"{p}.bias"), eps=1e-5)  # fmt: skip

    def ln(x, p):
        return F.layer_norm(x, x.shape[-1:], t(f"{p}.weight"), t(f"{p}.bias"))

    return t, linear, bn, ln


def test_msf_release_loads_strictly_and_exports_back():
    model = build_network_from_config(released_sizes("msf_4f.yaml"))
    facts = msf_released_shapes()
    exported = atlas_to_openpcdet_state(model.state_dict(), model)
    assert {k: tuple(v.shape) for k, v in exported.items()} == facts  # names and shapes
    theirs = released_state(facts)
    ours, layout = openpcdet_to_atlas_state(theirs, model)
    assert layout is None
    model.load_state_dict(ours, strict=True)
    token = model.roi_head.transformer.token  # (T, 1, 1, C) here, (T, 1, C) there
    assert torch.equal(token[:, 0], theirs["roi_head.transformer.token"])
    back = atlas_to_openpcdet_state(ours, model)
    assert back.keys() == theirs.keys()
    assert all(torch.equal(back[k], theirs[k]) for k in theirs if k != "global_step")


def test_msf_tensors_land_where_the_released_code_uses_them():
    """The trajectory branch, an encoder layer without BiFA and the output MLPs compute, with
    the converted weights, what the MSF repository's modules compute from its tensors."""
    model = build_network_from_config(released_sizes("msf_4f.yaml")).eval()
    theirs = released_state(msf_released_shapes(), seed=2)
    model.load_state_dict(openpcdet_to_atlas_state(theirs, model)[0], strict=True)
    head = model.roi_head
    t, linear, bn, ln = _functional(theirs)
    g = torch.Generator().manual_seed(0)

    # PointNet(8) of msf_utils.py: pre_bn, 4 convs (no ReLU after the 4th), max over frames, fc1 /
    # fc2 with BN and ReLU, then centre, size, heading
    seq = torch.randn(5, 8, 4, generator=g)  # (N, 8, T)
    x = bn(seq, "seqboxembed.pre_bn")
    for k in range(1, 5):
        c = f"seqboxembed.feat.conv{k}"
        x = bn(F.conv1d(x, t(f"{c}.weight"), t(f"{c}.bias")), f"seqboxembed.feat.bn{k}")
        x = torch.relu(x) if k < 4 else x
    x = torch.relu(bn(linear(x.max(2).values, "seqboxembed.fc1"), "seqboxembed.bn1"))
    feat = torch.relu(bn(linear(x, "seqboxembed.fc2"), "seqboxembed.bn2"))
    code = torch.cat([
        linear(torch.relu(linear(feat, f"seqboxembed.fc_{h}1")), f"seqboxembed.fc_{h}2")
        for h in ("ce", "s", "hr")
    ], 1)  # fmt: skip
    with torch.no_grad():
        got_code, got_feat = head.trajectory(seq)
    torch.testing.assert_close(got_feat, feat, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(got_code, code, rtol=1e-4, atol=1e-4)

    # the third encoder layer (no BiFA): the mixer (8 heads) over each group's points, then the
    # group's token attending to them (4 heads), post-norm
    def mha(p, heads):
        attn = torch.nn.MultiheadAttention(256, heads)
        attn.load_state_dict({k: t(f"{p}.{k}") for k in attn.state_dict()})
        return attn.eval()

    e = "transformer.encoder.layers.2"
    groups = torch.randn(4, 1 + 6, 3, 256, generator=g)  # (T groups, token + K points, N, C)
    src = groups.permute(1, 0, 2, 3).reshape(7, 12, 256)  # groups side by side on the batch axis
    with torch.no_grad():
        # the layer takes the tokens (T, N, C) and the points (T, N, K, C)
        got_token, got_points = head.transformer.layers[2](
            groups[:, 0], groups[:, 1:].permute(0, 2, 1, 3)
        )
        got = torch.cat([got_token[:, None], got_points.permute(0, 2, 1, 3)], 1)
        m = f"{e}.mlp_mixer_3d"
        pts = src[1:]
        pts = ln(pts + mha(f"{m}.mixer", 8)(pts, pts, pts)[0], f"{m}.norm")
        pts = ln(
            pts + linear(torch.relu(linear(pts, f"{m}.ffn.0")), f"{m}.ffn.3"), f"{m}.norm_channel"
        )
        token = src[:1]
        token = ln(token + mha(f"{e}.self_attn", 4)(token, pts, pts)[0], f"{e}.norm1")
        ffn = linear(torch.relu(linear(token, f"{e}.linear1")), f"{e}.linear2")
        token = ln(token + ffn, f"{e}.norm2")
    want = torch.cat([token, pts]).reshape(7, 4, 3, 256).permute(1, 0, 2, 3)
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-4)

    # jointembed on [4 group tokens, trajectory feature], class_embed[0], bbox_embed[g]
    def mlp(x, p, layers=4):
        for i in range(layers):
            x = linear(x, f"{p}.layers.{i}")
            x = torch.relu(x) if i < layers - 1 else x
        return x

    joint_in, token = torch.randn(5, 5 * 256, generator=g), torch.randn(5, 256, generator=g)
    with torch.no_grad():
        torch.testing.assert_close(head.joint_reg(joint_in), mlp(joint_in, "jointembed"))
        torch.testing.assert_close(head.class_embed(token), linear(token, "class_embed.0"))
        torch.testing.assert_close(head.frame_reg[3](token), mlp(token, "bbox_embed.3"))


def test_msf_forward_equals_the_model_with_the_same_weights():
    """Model A's weights go out under the MSF repository's names and come back into a fresh
    model B: B refines the same proposals exactly as A does, and its loss equals A's."""
    cfg = released_sizes("msf_4f.yaml")
    cfg.MODEL.ROI_HEAD.SAMPLER.NUM_POINTS = 16  # no tensor depends on these two
    cfg.MODEL.ROI_HEAD.TARGET_CONFIG.ROI_PER_IMAGE = 8
    torch.manual_seed(0)
    a = build_network_from_config(cfg)
    randomize(a, seed=4)
    theirs = atlas_to_openpcdet_state(a.state_dict(), a)
    torch.manual_seed(1)
    b = build_network_from_config(cfg)
    b.load_state_dict(openpcdet_to_atlas_state(theirs, b)[0], strict=True)
    batch = two_stage_batch(4)
    proposals = [
        {"pred_boxes": r[r[:, 10] > 0, :9], "pred_scores": r[r[:, 10] > 0, 9],
         "pred_labels": r[r[:, 10] > 0, 10].long()}
        for r in batch["roi_boxes"]
    ]  # fmt: skip
    a.eval(), b.eval()
    pa, pb = a.refine(batch, proposals), b.refine(batch, proposals)
    assert sum(len(p["pred_boxes"]) for p in pa) > 0
    for x, y in zip(pa, pb):
        assert x.keys() == y.keys() and all(torch.equal(x[k], y[k]) for k in x)
    la, lb = a.loss(batch), b.loss(batch)
    assert la.keys() == lb.keys() and all(torch.equal(la[k], lb[k]) for k in la)


def test_msf_mismatches_name_the_keys():
    cfg = released_sizes("msf_4f.yaml")
    model = build_network_from_config(cfg)

    # a second MSF built in the released process has no BiFA layers (a class-wide counter)
    second = released_state(msf_released_shapes(bifa_layers=0))
    with pytest.raises(
        CheckpointMismatchError,
        match=r"x\.pth .*16 missing keys: 16 under roi_head \(first roi_head\.transformer\."
        r"encoder\.layers\.0\.cross_conv_1\.bias\).*BIFA_LAYERS 0",
    ):
        openpcdet_to_atlas_state(second, model, source="x.pth")
    no_bifa = copy.deepcopy(cfg)
    no_bifa.MODEL.ROI_HEAD.TRANSFORMER.BIFA_LAYERS = 0
    model0 = build_network_from_config(no_bifa)
    model0.load_state_dict(openpcdet_to_atlas_state(second, model0)[0], strict=True)

    theirs = released_state(msf_released_shapes())
    eight = build_network_from_config(released_sizes("msf_8f.yaml"))
    with pytest.raises(
        CheckpointMismatchError,
        match=r"32 missing keys: 32 under roi_head \(first roi_head\.bbox_embed\.4\.layers\.0\."
        r"bias\).*written for 4 frames",
    ):
        openpcdet_to_atlas_state(theirs, eight)

    small = build_network_from_config(cfg_from_yaml_file(SYNTHETIC / "msf_4f.yaml"))
    with pytest.raises(
        CheckpointMismatchError,
        match=r"roi_head\.up_dimension_geometry\.layers\.0\.weight: checkpoint \(64, 29\) vs "
        r"model \(32, 29\)",
    ):
        openpcdet_to_atlas_state(theirs, small)  # the synthetic widths

    flat = dict(theirs)
    flat["roi_head.transformer.token"] = torch.zeros(4, 256)
    with pytest.raises(
        CheckpointMismatchError,
        match=r"roi_head\.transformer\.token: checkpoint \(4, 256\) vs \(4, 1, 256\) \(model "
        r"roi_head\.transformer\.token \(4, 1, 1, 256\)\)",
    ):
        openpcdet_to_atlas_state(flat, model)

    extra = dict(theirs)
    extra["roi_head.transformer.fusion_all_group.layers.0.weight"] = torch.zeros(256, 512)
    with pytest.raises(
        CheckpointMismatchError, match=r"unexpected roi_head\.transformer\.fusion_all_group"
    ):
        openpcdet_to_atlas_state(extra, model)

    rpn = openpcdet_state(cfg_from_yaml_file(SYNTHETIC / "cp4f_voxel.yaml"))
    with pytest.raises(CheckpointMismatchError, match=r"shares no tensor name.*MODEL\.RPN\.CFG"):
        openpcdet_to_atlas_state(rpn, model)  # the first stage's checkpoint for the second


def test_ptt_release_maps_where_the_structures_agree_and_names_the_rest():
    """Every released tensor that PTTHead has a counterpart of maps exactly (reshaped kernels,
    biases folded into the BatchNorm after them, the future token's input columns moved); the
    current-point features do not, and with them nothing loads: the error names both sides and
    the released modules that the released forward never reads."""
    model = build_network_from_config(released_sizes("ptt_32f.yaml")).eval()
    theirs = released_state(ptt_released_shapes(), seed=5)
    with pytest.raises(CheckpointMismatchError) as err:
        openpcdet_to_atlas_state(theirs, model, source="ptt.pth")
    msg = str(err.value)
    assert "unexpected roi_head" not in msg and "missing roi_head" not in msg
    for part in (
        "no counterpart of roi_head.point_pool.* in the released code (released "
        "roi_head.ptt.conv2_p, roi_head.ptt.bn2_p)",
        "no counterpart of roi_head.current_proj.*, roi_head.point_attn.* in the released code "
        "(released roi_head.ptt.attn3_point)",
        "released roi_head.fc, roi_head.bn, roi_head.up_dimension_motion, "
        "roi_head.grid_pos_embeded, roi_head.ptt.attn1, roi_head.ptt.attn3 without counterpart "
        "here: built by the released PTTHead, never called",
        "released roi_head.roi_grid_pool_layer without counterpart here",
        "released roi_head.bbox_embed without counterpart here: training-only",
    ):
        assert part in msg, part
    with pytest.raises(CheckpointMismatchError, match="have no counterpart in the released code"):
        atlas_to_openpcdet_state(model.state_dict(), model)

    ours, _ = openpcdet_to_atlas_state(theirs, model, partial=True)
    result = model.load_state_dict(ours, strict=False)
    assert not result.unexpected_keys
    assert {k.split(".")[1] for k in result.missing_keys} == {
        "point_pool", "point_attn", "current_proj"
    }  # fmt: skip

    head = model.roi_head
    t, linear, bn, ln = _functional(theirs)
    g = torch.Generator().manual_seed(0)

    def conv_bn(x, conv, norm):  # Conv1d(kernel 1) with bias, then BatchNorm1d
        return bn(F.conv1d(x, t(f"ptt.{conv}.weight"), t(f"ptt.{conv}.bias")), f"ptt.{norm}")

    def attention(query, key, p, heads):  # PTT's Attention: heads stacked on the batch axis
        q, k, v = linear(query, f"{p}.fc_q"), linear(key, f"{p}.fc_k"), linear(key, f"{p}.fc_v")
        split = q.shape[-1] // heads
        qh, kh, vh = (torch.cat(z.split(split, 2), 0) for z in (q, k, v))
        a = torch.softmax(qh.bmm(kh.transpose(1, 2)) / q.shape[-1] ** 0.5, 2)
        out = torch.cat((qh + a.bmm(vh)).split(query.shape[0], 0), 2)
        return out + torch.relu(linear(out, f"{p}.fc_o"))

    with torch.no_grad():
        # the box sequence path: pre_bn, conv1 + bn1 + ReLU
        box = torch.randn(6, 8, 5, generator=g)  # (N, 8, L)
        want = torch.relu(conv_bn(bn(box, "ptt.pre_bn"), "conv1", "bn1"))
        got = torch.relu(head.box_norm(head.box_embed(box.transpose(1, 2).reshape(-1, 8))))
        torch.testing.assert_close(got.reshape(6, 5, 64).transpose(1, 2), want, rtol=1e-4,
                                   atol=1e-4)  # fmt: skip

        # the future memory [token, conv_future] queries short + long memory (1 head there)
        future = torch.randn(6, 96, 16, generator=g)  # (N, C, F)
        memory = torch.randn(6, 32, 96, generator=g)  # (N, S + L, C)
        query = torch.cat([
            t("ptt.future_token").expand(6, 16, 32),
            torch.relu(conv_bn(future, "conv_future", "bn_future")).transpose(1, 2),
        ], 2)  # fmt: skip
        want = attention(query, memory, "ptt.attn1_future", heads=1)
        head.future_attn.heads = 1  # the released head count of this block
        query = torch.cat([
            head.future_proj(future.transpose(1, 2)), head.future_token.expand(6, 16, 32)
        ], 2)  # fmt: skip
        torch.testing.assert_close(head.future_attn(query, memory), want, rtol=1e-4, atol=1e-4)

        # the aggregator, the trajectory feature and its box, the refined box and confidence
        enhanced = torch.randn(6, 128, 48, generator=g)  # (N, C, L)
        current = torch.randn(6, 256, generator=g)
        x = conv_bn(torch.relu(conv_bn(enhanced, "conv3", "bn3")), "conv4", "bn4")
        x = torch.cat([x.max(2, keepdim=True).values, current[..., None]], 1)
        x = torch.relu(conv_bn(x, "conv_final", "bn_final"))[..., 0]
        x = torch.relu(bn(linear(x, "ptt.fc1"), "ptt.x_bn1"))
        feat = torch.relu(bn(linear(x, "ptt.fc2"), "ptt.x_bn2"))
        code = torch.cat([
            linear(torch.relu(linear(feat, f"ptt.fc_{h}1")), f"ptt.fc_{h}2")
            for h in ("ce", "s", "hr")
        ], 1)  # fmt: skip
        joint = torch.cat([current, feat], 1)
        for i in range(4):
            joint = linear(joint, f"jointembed.layers.{i}")
            joint = torch.relu(joint) if i < 3 else joint
        pooled = head.aggregate(enhanced.transpose(1, 2)).max(1).values
        got_feat = head.trajectory_fc(torch.cat([pooled, current], 1))
        got_code = torch.cat([
            head.traj_center(got_feat), head.traj_size(got_feat), head.traj_heading(got_feat)
        ], 1)  # fmt: skip
        torch.testing.assert_close(got_feat, feat, rtol=1e-4, atol=1e-4)
        torch.testing.assert_close(got_code, code, rtol=1e-4, atol=1e-4)
        got_joint = head.joint_reg(torch.cat([current, got_feat], 1))
        torch.testing.assert_close(got_joint, joint, rtol=1e-4, atol=1e-4)
        torch.testing.assert_close(head.class_embed(current), linear(current, "class_embed.0"))


def test_convert_tool_msf_records_the_rpn_and_refuses_ptt(tmp_path, capsys):
    rpn = ["MODEL.RPN.CFG", "cfgs/atlas/synthetic/cp4f.yaml",
           "MODEL.RPN.CHECKPOINT", "checkpoints/cp4f_synthetic.pth"]  # fmt: skip
    src = tmp_path / "msf" / "checkpoint_epoch_6.pth"
    src.parent.mkdir()
    theirs = released_state(msf_released_shapes())
    torch.save({"epoch": 6, "it": 99, "model_state": theirs, "version": "pcdet+0.6.0"}, src)
    out = tmp_path / "msf_4f_converted.pth"
    tool = load_tool("data/convert_openpcdet_ckpt")
    cfg_path = REPO_ROOT / "cfgs" / "atlas" / "msf_4f.yaml"
    tool.main(["--cfg", str(cfg_path), "--ckpt", str(src), "--out", str(out), "--set", *rpn])
    printed = capsys.readouterr().out
    assert "RPN checkpoints/cp4f_synthetic.pth recorded; loads strictly" in printed
    model = build_network_from_config(released_sizes("msf_4f.yaml"))
    ckpt = model.load_params_from_file(out, strict=True)  # the RPN's SHA-256 is checked
    assert ckpt["model_info"]["rpn"]["sha256"] == model.rpn_info["sha256"]
    assert ckpt["epoch"] == 6 and ckpt["converted_from"]["spconv_layout"] is None
    key = "roi_head.transformer.layers.1.point_attn.in_proj_weight"
    name = "roi_head.transformer.encoder.layers.1.mlp_mixer_3d.mixer.in_proj_weight"
    assert torch.equal(model.state_dict()[key], theirs[name])

    torch.save({"model_state": released_state(ptt_released_shapes())}, src)
    cfg_path = REPO_ROOT / "cfgs" / "atlas" / "ptt_32f.yaml"
    with pytest.raises(CheckpointMismatchError, match=r"no counterpart of roi_head\.point_pool"):
        tool.main(["--cfg", str(cfg_path), "--ckpt", str(src), "--out", str(tmp_path / "p.pth"),
                   "--set", *rpn])  # fmt: skip
    assert not (tmp_path / "p.pth").exists()
