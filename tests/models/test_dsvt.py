"""DSVT: its index ops against loops written here, set attention against dense masked attention,
the rotated partitions, the pooling, gradients, the OpenPCDet-named round trip, and the
synthetic config training on the fixture dataset."""

from __future__ import annotations

import copy
import math
from fractions import Fraction

import pytest
import torch
import torch.nn.functional as F
from model_batches import load_tool, make_batch

from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.datasets.loader import build_dataloader
from pcdet_atlas.models import (
    build_network,
    build_network_from_config,
    load_data_to_device,
    num_point_features_of,
)
from pcdet_atlas.models.backbones_3d.dsvt import (
    DSVTBlock,
    DSVTInputLayer,
    SetAttention,
    Stage_ReductionAtt_Block,
)
from pcdet_atlas.models.model_utils.dsvt_utils import (
    pooling_index,
    rank_in_group,
    set_key_mask,
    set_partition,
    window_coords,
)
from pcdet_atlas.models.openpcdet_checkpoint import (
    atlas_to_openpcdet_state,
    openpcdet_to_atlas_state,
)
from pcdet_atlas.ops.iou3d_nms import boxes_iou_bev

CFGS = REPO_ROOT / "cfgs" / "atlas"
SYN = CFGS / "synthetic" / "dsvt.yaml"
REAL = CFGS / "dsvt.yaml"


def random_voxels(n: int, shape=(40, 30, 6), batch: int = 2, seed: int = 0) -> torch.Tensor:
    """(n', 4) unique ``[b, z, y, x]`` voxels (n' <= n) on a grid ``(nx, ny, nz)``."""
    g = torch.Generator().manual_seed(seed)
    nx, ny, nz = shape
    c = torch.stack(
        [torch.randint(0, hi, (n,), generator=g) for hi in (batch, nz, ny, nx)], dim=1
    )  # (n, 4)
    return torch.unique(c, dim=0)[torch.randperm(torch.unique(c, dim=0).shape[0], generator=g)]


# ----------------------------------------------------------------- references (plain loops)
def windows_by_loop(coords, window, shift):
    """voxel -> (window key, (z, y, x) in window), by per-voxel floor division."""
    out = []
    for b, z, y, x in coords.tolist():
        p = (x + shift[0], y + shift[1], z + shift[2])
        out.append(((b, p[0] // window[0], p[1] // window[1], p[2] // window[2]),
                    (p[2] % window[2], p[1] % window[1], p[0] % window[0])))  # fmt: skip
    return out


def partition_by_loop(coords, window, shift, set_size):
    """The y-major and x-major set partitions, window by window in window-id order."""
    wins = windows_by_loop(coords, window, shift)
    groups: dict = {}
    for i, (key, inner) in enumerate(wins):
        groups.setdefault(key, []).append((i, inner))
    out = ([], [])
    for key in sorted(groups):
        members = groups[key]
        n = len(members)
        num_sets = -(-n // set_size)
        for part, order in enumerate(
            (lambda m: (m[1][1], m[1][2], m[1][0]), lambda m: (m[1][2], m[1][1], m[1][0]))
        ):
            ranked = [i for i, _ in sorted(members, key=order)]
            for s in range(num_sets):
                slots = range(s * set_size, (s + 1) * set_size)
                out[part].append(
                    [ranked[math.floor(Fraction(j * n, num_sets * set_size))] for j in slots]
                )
    return torch.tensor(out)


# --------------------------------------------------------------------------- index ops
def test_rank_in_group_matches_a_loop():
    g = torch.Generator().manual_seed(1)
    group = torch.randint(0, 7, (300,), generator=g) * 13  # sparse ids
    key = torch.randint(0, 40, (300,), generator=g)  # ties: input order decides
    expected = torch.empty(300, dtype=torch.long)
    seen: dict = {}
    for i in sorted(range(300), key=lambda i: (int(key[i]), i)):
        gid = int(group[i])
        expected[i] = seen.get(gid, 0)
        seen[gid] = expected[i] + 1
    assert torch.equal(rank_in_group(group, key), expected)
    assert rank_in_group(group[:0], key[:0]).numel() == 0


@pytest.mark.parametrize("shift", [(0, 0, 0), (6, 6, 0), (3, 5, 2)])
def test_windows_match_a_loop(shift):
    coords = random_voxels(400)
    window = (12, 12, 4)
    win, inner = window_coords(coords, (40, 30, 6), window, shift)
    ref = windows_by_loop(coords, window, shift)
    assert torch.equal(inner, torch.tensor([r[1] for r in ref]))
    # equal window ids exactly where the loop's windows are equal
    same = win[:, None] == win[None]
    keys = [r[0] for r in ref]
    assert torch.equal(same, torch.tensor([[a == b for b in keys] for a in keys]))


@pytest.mark.parametrize("set_size", [4, 9, 36])
@pytest.mark.parametrize("shift", [(0, 0, 0), (6, 6, 0)])
def test_set_partition_matches_a_loop(set_size, shift):
    coords = random_voxels(600, shape=(30, 30, 6), seed=set_size)
    window = (12, 12, 6)
    win, inner = window_coords(coords, (30, 30, 6), window, shift)
    got = set_partition(win, inner, window, set_size)
    assert torch.equal(got, partition_by_loop(coords, window, shift, set_size))


@pytest.mark.parametrize("set_size", [1, 5, 36])
def test_rotated_partitions_cover_every_voxel_exactly_once(set_size):
    coords = random_voxels(800, shape=(24, 24, 4), seed=3)
    n = coords.shape[0]
    win, inner = window_coords(coords, (24, 24, 4), (12, 12, 4), (0, 0, 0))
    parts = set_partition(win, inner, (12, 12, 4), set_size)
    mask = set_key_mask(parts)
    for part, m in zip(parts, mask):
        kept = part[~m]  # one unmasked slot per voxel: each voxel in exactly one set
        assert torch.equal(torch.sort(kept).values, torch.arange(n))
        assert (win[part] == win[part[:, :1]]).all()  # a set lies in one window
    # the two orders are different partitions (rotated sets), not relabelled copies
    as_sets = [{frozenset(s.tolist()) for s in p} for p in parts]
    assert set_size == 1 or as_sets[0] != as_sets[1]


def test_a_full_window_is_cut_into_rows_and_columns():
    """A fully occupied 4 x 4 window with sets of 4: y-major sets are rows (constant y), x-major
    sets columns (constant x)."""
    ys, xs = torch.meshgrid(torch.arange(4), torch.arange(4), indexing="ij")
    coords = torch.stack([torch.zeros(16), torch.zeros(16), ys.flatten(), xs.flatten()], 1).long()
    win, inner = window_coords(coords, (4, 4, 1), (4, 4, 1), (0, 0, 0))
    rows, cols = set_partition(win, inner, (4, 4, 1), 4)
    assert all(len(set(coords[s, 2].tolist())) == 1 for s in rows)
    assert all(len(set(coords[s, 3].tolist())) == 1 for s in cols)


def test_pooling_index_matches_a_loop():
    coords = random_voxels(500, shape=(20, 20, 16), seed=4)
    stride = (1, 2, 4)
    cell, index, pooled = pooling_index(coords, (20, 20, 16), stride)
    for i, (b, z, y, x) in enumerate(coords.tolist()):
        assert pooled[cell[i]].tolist() == [b, z // 4, y // 2, x]
        assert int(index[i]) == (x % 1) * 8 + (y % 2) * 4 + z % 4
    assert len({tuple(r) for r in pooled.tolist()}) == pooled.shape[0]  # one row per cell


# ----------------------------------------------------------------------------- attention
def dense_set_attention(layer: SetAttention, src, pos, sets, mask):
    """The same layer as dense attention over all voxels, a voxel seeing only its set's
    members (each once)."""
    n, c = src.shape
    allowed = torch.zeros(n, n, dtype=torch.bool)
    for s, m in zip(sets.tolist(), mask.tolist()):
        members = [v for v, dup in zip(s, m) if not dup]
        for v in members:
            allowed[v, members] = True
    qk = (src + pos)[None]
    attn = layer.self_attn
    q = F.linear(qk, attn.in_proj_weight[:c], attn.in_proj_bias[:c])
    k = F.linear(qk, attn.in_proj_weight[c : 2 * c], attn.in_proj_bias[c : 2 * c])
    v = F.linear(src[None], attn.in_proj_weight[2 * c :], attn.in_proj_bias[2 * c :])
    h = attn.num_heads
    q, k, v = (t.view(n, h, c // h).transpose(0, 1) for t in (q[0], k[0], v[0]))
    logits = q @ k.transpose(1, 2) / math.sqrt(c // h)
    logits = logits.masked_fill(~allowed[None], float("-inf"))
    out = (logits.softmax(-1) @ v).transpose(0, 1).reshape(n, c)
    out = attn.out_proj(out)
    x = layer.norm1(src + out)
    return layer.norm2(x + layer.linear2(F.gelu(layer.linear1(x))))


def test_set_attention_equals_dense_masked_attention():
    torch.manual_seed(0)
    coords = random_voxels(300, shape=(24, 24, 1), seed=5)
    win, inner = window_coords(coords, (24, 24, 1), (12, 12, 1), (6, 6, 0))
    sets = set_partition(win, inner, (12, 12, 1), 7)[1]  # x-major, with repeated slots
    mask = set_key_mask(sets)
    assert mask.any()  # some window is not a multiple of 7: duplicates are masked
    layer = SetAttention(16, 4, 0.0, 32, "gelu").double().eval()
    src = torch.randn(coords.shape[0], 16, dtype=torch.float64)
    pos = torch.randn(coords.shape[0], 16, dtype=torch.float64)
    got = layer(src, pos, mask, sets)
    want = dense_set_attention(layer, src, pos, sets, mask)
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)


def test_consecutive_blocks_alternate_shifts_and_rotate_sets():
    """Block ``b`` runs its first encoder on shift ``b % 2``'s y-major sets and its second on
    the x-major sets of the same shift."""
    torch.manual_seed(0)
    coords = random_voxels(300, shape=(24, 24, 1), seed=6)
    layer = DSVTInputLayer(
        sparse_shape=(24, 24, 1), window_shape=[(6, 6, 1)], downsample_stride=[],
        d_model=[16], set_info=[(5, 2)], hybrid_factor=(2, 2, 1), shifts_list=[[(0, 0, 0),
        (3, 3, 0)]],
    ).eval()  # fmt: skip
    stage = layer(coords)["stages"][0]
    block = DSVTBlock(16, 4, 32, 0.0, "gelu").eval()
    src = torch.randn(coords.shape[0], 16)
    for block_id in (0, 1):
        pos = stage["pos_embed"][block_id]
        got = block(src, stage["set_voxel_inds"], stage["set_voxel_masks"], pos, block_id)
        x = src
        for i, enc in enumerate(block.encoder_list):
            inds = stage["set_voxel_inds"][block_id][i]
            x = enc(x, inds, stage["set_voxel_masks"][block_id][i], pos[i])
        torch.testing.assert_close(got, x)
    assert not torch.equal(stage["set_voxel_inds"][0][0][:3], stage["set_voxel_inds"][1][0][:3])


def test_attention_pooling_matches_a_per_cell_reference():
    torch.manual_seed(0)
    pool = Stage_ReductionAtt_Block(16, 4).double().eval()
    x = torch.randn(5, 4, 16, dtype=torch.float64)
    x[1, 2:] = 0  # empty positions hold zeros and still take part
    got = pool(x)
    for m in range(5):
        query = x[m].max(dim=0).values[None, None]
        out = pool.self_attn(query, (x[m] + pool.pos_embedding)[None], x[m][None])[0]
        torch.testing.assert_close(got[m], pool.norm(out + query)[0, 0])


# ------------------------------------------------------------------------------- models
def cropped(path, cells: int = 48):
    """The model of ``path`` on a ``cells`` x ``cells`` crop: the same tensors."""
    cfg = cfg_from_yaml_file(path)
    m = copy.deepcopy(cfg.MODEL)
    layer = m.BACKBONE_3D.INPUT_LAYER
    layer.sparse_shape = [cells, cells, layer.sparse_shape[2]]
    m.BACKBONE_3D.output_shape = [cells, cells]
    m.MAP_TO_BEV.INPUT_SHAPE = [cells, cells, 1]
    half = cells * m.VFE.VOXEL_SIZE[0] / 2
    pcr = cfg.DATA_CONFIG.POINT_CLOUD_RANGE
    model = build_network(
        m, class_names=cfg.CLASS_NAMES, point_cloud_range=[-half, -half, pcr[2], half, half,
        pcr[5]], num_point_features=num_point_features_of(cfg.DATA_CONFIG),
    )  # fmt: skip
    return model, cfg, half


def test_every_parameter_gets_a_gradient():
    torch.manual_seed(0)
    model, _, half = cropped(SYN)
    batch = make_batch(num_point_features=5, extent=half, scale=half / 20)
    # 3 objects: an output bias's L1 gradient (one +-c per object) cannot cancel to 0
    batch["gt_boxes"][0, 2] = 0
    model.train()
    losses = model.loss(batch)
    assert {"hm_loss", "loc_loss", "iou_loss", "iou_reg_loss"} <= set(losses)
    losses["loss"].backward()
    silent = [n for n, p in model.named_parameters() if p.grad is None or not p.grad.abs().sum()]
    assert not silent, silent
    # the pooling and every stage's blocks are in the graph
    assert any(n.startswith("backbone_3d.stage_1_reduction") for n, _ in model.named_parameters())


def pillar_form(cells: int = 32, use_checkpoint: bool = False):
    """DSVT-P's form of the synthetic model: 6 m pillars, one stage of 4 blocks, no pooling."""
    cfg = cfg_from_yaml_file(SYN)
    m = copy.deepcopy(cfg.MODEL)
    m.VFE.VOXEL_SIZE = [0.64, 0.64, 6.0]
    layer, b3 = m.BACKBONE_3D.INPUT_LAYER, m.BACKBONE_3D
    layer.sparse_shape, layer.downsample_stride = [cells, cells, 1], []
    layer.d_model, layer.set_info, layer.window_shape = [64], [[36, 4]], [[12, 12, 1]]
    layer.shifts_list = [[[0, 0, 0], [6, 6, 0]]]
    b3.block_name, b3.set_info, b3.d_model = ["DSVTBlock"], [[36, 4]], [64]
    b3.nhead, b3.dim_feedforward, b3.output_shape = [4], [128], [cells, cells]
    b3.USE_CHECKPOINT = use_checkpoint
    m.MAP_TO_BEV.INPUT_SHAPE = [cells, cells, 1]
    half = cells * 0.64 / 2
    torch.manual_seed(0)
    model = build_network(
        m, class_names=cfg.CLASS_NAMES, point_cloud_range=[-half, -half, -2.0, half, half, 4.0],
        num_point_features=5,
    )  # fmt: skip
    return model, half


def test_pillar_form_trains_and_checkpointing_keeps_the_gradients():
    """One stage of 4 blocks without pooling (DSVT-P's form) trains; USE_CHECKPOINT recomputes
    the blocks in backward and gives the same gradients."""
    grads = []
    for use_checkpoint in (False, True):
        model, half = pillar_form(use_checkpoint=use_checkpoint)
        assert not any("reduction" in n for n, _ in model.named_parameters())
        batch = make_batch(num_point_features=5, extent=half, scale=half / 20)
        model.train()
        model.loss(batch)["loss"].backward()
        grads.append({n: p.grad for n, p in model.named_parameters()})
    assert grads[0].keys() == grads[1].keys()
    for name, grad in grads[0].items():
        torch.testing.assert_close(grads[1][name], grad, msg=name)
    model.eval()
    assert model.predict(batch)[0]["pred_boxes"].shape[1] == 7


def test_iou_branch_and_rectification_change_the_scores():
    """With IOU_RECTIFIER the scores are ``hm ** (1 - r) * iou ** r`` of the same boxes."""
    torch.manual_seed(0)
    model, _, half = cropped(SYN)
    batch = make_batch(num_point_features=5, extent=half, scale=half / 20)
    model.eval()
    rectified = model.predict(batch)
    head = model.dense_head
    rectifier = head.iou_rectifier
    head.iou_rectifier = None
    plain = model.predict(batch)
    head.iou_rectifier = rectifier
    assert rectifier == (0.68, 0.71, 0.65)
    assert not torch.equal(rectified[0]["pred_scores"], plain[0]["pred_scores"])
    for r in rectified:
        assert (r["pred_scores"][:-1] >= r["pred_scores"][1:]).all()


def test_class_specific_nms_uses_each_class_threshold():
    model, _, _ = cropped(SYN)
    head = model.dense_head
    box = torch.tensor([0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0])
    shifted = box + torch.tensor([0.6, 0, 0, 0, 0, 0, 0])  # BEV IoU 0.74 with box
    iou = float(boxes_iou_bev(box[None], shifted[None]))
    assert 0.6 < iou < 0.75
    boxes = torch.stack([box, shifted] * 3)
    scores = torch.tensor([0.9, 0.8, 0.7, 0.6, 0.5, 0.4])
    labels = torch.tensor([0, 0, 1, 1, 2, 2])
    kept = head._nms(boxes, scores, labels)  # thresholds 0.75, 0.6, 0.55
    assert kept.tolist() == [0, 1, 2, 4]


def openpcdet_dsvt_names(cfg) -> dict[str, tuple]:
    """Name -> shape of what OpenPCDet's CenterPoint with DSVT saves, from its module names
    (``backbones_3d/dsvt.py``, ``dynamic_voxel_vfe.py``, ``BaseBEVResBackbone``, CenterHead)."""
    m = cfg.MODEL
    names: dict[str, tuple] = {"global_step": (1,)}

    def bn(prefix, c, dims=1):
        return {f"{prefix}.weight": (c,), f"{prefix}.bias": (c,), f"{prefix}.running_mean": (c,),
                f"{prefix}.running_var": (c,), f"{prefix}.num_batches_tracked": ()}  # fmt: skip

    def ln(prefix, c):
        return {f"{prefix}.weight": (c,), f"{prefix}.bias": (c,)}

    def linear(prefix, cin, cout, bias=True):
        return {f"{prefix}.weight": (cout, cin), **({f"{prefix}.bias": (cout,)} if bias else {})}

    def mha(prefix, c):
        return {f"{prefix}.in_proj_weight": (3 * c, c), f"{prefix}.in_proj_bias": (3 * c,),
                **linear(f"{prefix}.out_proj", c, c)}  # fmt: skip

    widths = [num_point_features_of(cfg.DATA_CONFIG) + 6, *m.VFE.NUM_FILTERS]
    for i in range(len(widths) - 1):
        out = widths[i + 1] if i == len(widths) - 2 else widths[i + 1] // 2
        names |= linear(f"vfe.pfn_layers.{i}.linear", widths[i], out, bias=False)
        names |= bn(f"vfe.pfn_layers.{i}.norm", out)
    b3 = m.BACKBONE_3D
    shape = list(b3.INPUT_LAYER.sparse_shape)
    for s, ((_, blocks), d, ff) in enumerate(zip(b3.set_info, b3.d_model, b3.dim_feedforward)):
        dim = 3 if shape[2] > 1 else 2
        for b in range(blocks):
            for sh in range(2):
                p = f"backbone_3d.input_layer.posembed_layers.{s}.{b}.{sh}.position_embedding_head"
                names |= linear(f"{p}.0", dim, d) | bn(f"{p}.1", d) | linear(f"{p}.3", d, d)
            for e in range(2):
                p = f"backbone_3d.stage_{s}.{b}.encoder_list.{e}"
                names |= mha(f"{p}.win_attn.self_attn", d)
                names |= linear(f"{p}.win_attn.linear1", d, ff)
                names |= linear(f"{p}.win_attn.linear2", ff, d)
                names |= ln(f"{p}.win_attn.norm1", d) | ln(f"{p}.win_attn.norm2", d)
                names |= ln(f"{p}.norm", d)
            names |= ln(f"backbone_3d.residual_norm_stage_{s}.{b}", d)
        if s < len(b3.d_model) - 1:
            stride = b3.INPUT_LAYER.downsample_stride[s]
            p = f"backbone_3d.stage_{s}_reduction"
            names |= ln(f"{p}.norm", d) | mha(f"{p}.self_attn", d)
            names[f"{p}.pos_embedding"] = (math.prod(stride), d)
            shape = [-(-n // k) for n, k in zip(shape, stride)]
    b2 = m.BACKBONE_2D
    cin = [m.MAP_TO_BEV.NUM_BEV_FEATURES, *b2.NUM_FILTERS[:-1]]
    for lv, (n, f, up, uf) in enumerate(
        zip(b2.LAYER_NUMS, b2.NUM_FILTERS, b2.UPSAMPLE_STRIDES, b2.NUM_UPSAMPLE_FILTERS)
    ):
        for j in range(n + 1):
            p = f"backbone_2d.blocks.{lv}.{j}"
            c0 = cin[lv] if j == 0 else f
            names |= {f"{p}.conv1.weight": (f, c0, 3, 3), f"{p}.conv2.weight": (f, f, 3, 3)}
            names |= bn(f"{p}.bn1", f) | bn(f"{p}.bn2", f)
            if j == 0:
                names |= {f"{p}.downsample_layer.0.weight": (f, c0, 1, 1)}
                names |= bn(f"{p}.downsample_layer.1", f)
        names |= {f"backbone_2d.deblocks.{lv}.0.weight": (f, uf, up, up)}
        names |= bn(f"backbone_2d.deblocks.{lv}.1", uf)
    head = m.DENSE_HEAD
    c, bias = head.SHARED_CONV_CHANNEL, head.USE_BIAS_BEFORE_NORM
    names |= {"dense_head.shared_conv.0.weight": (c, sum(b2.NUM_UPSAMPLE_FILTERS), 3, 3)}
    names |= bn("dense_head.shared_conv.1", c)
    heads = {k: (v.out_channels, v.num_conv) for k, v in head.SEPARATE_HEAD_CFG.HEAD_DICT.items()}
    heads["hm"] = (len(cfg.CLASS_NAMES), head.NUM_HM_CONV)
    for name, (out_ch, num_conv) in heads.items():
        p = f"dense_head.heads_list.0.{name}"
        for k in range(num_conv - 1):
            names |= {f"{p}.{k}.0.weight": (c, c, 3, 3)} | bn(f"{p}.{k}.1", c)
            names |= {f"{p}.{k}.0.bias": (c,)} if bias else {}
        names |= {f"{p}.{num_conv - 1}.weight": (out_ch, c, 3, 3),
                  f"{p}.{num_conv - 1}.bias": (out_ch,)}  # fmt: skip
    return names


def openpcdet_dsvt_state(cfg) -> dict[str, torch.Tensor]:
    """Random values under OpenPCDet's DSVT names and shapes (BN variances positive)."""
    g = torch.Generator().manual_seed(0)
    return {
        k: (torch.rand(s, generator=g) + 0.5 if k.endswith("running_var") else
            torch.randn(s, generator=g) if k != "global_step" and not k.endswith("tracked")
            else torch.tensor(7 if k == "global_step" else 3))
        for k, s in openpcdet_dsvt_names(cfg).items()
    }  # fmt: skip


@pytest.mark.parametrize("path", [REAL, SYN], ids=["dsvt", "synthetic/dsvt"])
def test_openpcdet_named_state_round_trip(path):
    cfg = cfg_from_yaml_file(path)
    model = build_network_from_config(cfg)
    theirs = openpcdet_dsvt_state(cfg)
    ours, layout = openpcdet_to_atlas_state(theirs, model)
    assert layout is None  # no sparse conv weights
    model.load_state_dict(ours, strict=True)
    # DSVT, its VFE, scatter and BEV backbone carry OpenPCDet's names: every tensor lands under
    # its own name (the head's are mapped by CenterHead.openpcdet_names)
    state = model.state_dict()
    for k, v in theirs.items():
        if k != "global_step" and not k.startswith("dense_head."):
            assert torch.equal(state[k], v), k
    back = atlas_to_openpcdet_state(ours, model)
    assert back.keys() == theirs.keys()
    assert all(torch.equal(back[k], theirs[k]) for k in theirs if k != "global_step")


def test_convert_tool_takes_an_openpcdet_dsvt_checkpoint(tmp_path, capsys):
    src = tmp_path / "checkpoint_epoch_24.pth"
    theirs = openpcdet_dsvt_state(cfg_from_yaml_file(SYN))
    torch.save({"epoch": 24, "model_state": theirs, "version": "pcdet+0.6.0"}, src)
    out = tmp_path / "converted.pth"
    load_tool("data/convert_openpcdet_ckpt").main(
        ["--cfg", str(SYN), "--ckpt", str(src), "--out", str(out)]
    )
    assert "loads strictly" in capsys.readouterr().out
    model = build_network_from_config(cfg_from_yaml_file(SYN))
    assert model.load_params_from_file(out, strict=True)["epoch"] == 24
    key = "backbone_3d.stage_1_reduction.pos_embedding"
    assert torch.equal(model.state_dict()[key], theirs[key])
    iou = "dense_head.head.branches.iou.3.weight"
    assert torch.equal(model.state_dict()[iou], theirs["dense_head.heads_list.0.iou.1.weight"])


@pytest.mark.slow
def test_real_config_forward_on_a_crop():
    torch.manual_seed(0)
    model, _, half = cropped(REAL, cells=48)
    batch = make_batch(num_point_features=5, extent=half, scale=half / 20)
    model.train()
    model.loss(batch)["loss"].backward()
    model.eval()
    assert len(model.predict(batch)) == 2


def test_synthetic_config_trains_two_steps_on_the_fixture_data_and_predicts(
    synthetic_root, tmp_path
):
    """tools/train.py, 2 steps of batch 1 on a 64 x 64 crop of the fixture's frames, then the
    trained checkpoint predicts on them."""
    train = load_tool("train")
    out = train.main([
        "--cfg", str(SYN), "--out_dir", str(tmp_path), "--extra_tag", "smoke",
        "--epochs", "1", "--batch_size", "1", "--workers", "0", "--no_progress",
        "--fix_random_seed", "--device", "cpu",
        "--set", "DATA_CONFIG.DATA_PATH", str(synthetic_root),
        "DATA_CONFIG.DATA_AUGMENTOR.DISABLE_AUG_LIST", "gt_sampling",
        "DATA_CONFIG.SAMPLED_INTERVAL", "train:10,test:10",
        "DATA_CONFIG.POINT_CLOUD_RANGE", "-20.48,-20.48,-2,20.48,20.48,4",
        "MODEL.BACKBONE_3D.INPUT_LAYER.sparse_shape", "64,64,16",
        "MODEL.BACKBONE_3D.output_shape", "64,64",
        "MODEL.MAP_TO_BEV.INPUT_SHAPE", "64,64,1",
    ])  # fmt: skip
    assert out["state"].it == 2
    assert all(math.isfinite(h["loss"]) for h in out["state"].history)
    ckpt = out["output_dir"] / "ckpt" / "checkpoint_epoch_1.pth"
    cfg = cfg_from_yaml_file(out["output_dir"] / "dsvt.yaml")
    model = build_network_from_config(cfg)
    model.load_params_from_file(ckpt, strict=True)
    model.eval()
    _, loader, _ = build_dataloader(
        cfg.DATA_CONFIG, cfg.CLASS_NAMES, batch_size=1, dist=False, training=False, workers=0
    )
    batch = load_data_to_device(next(iter(loader)), "cpu")
    preds = model.predict(batch)
    assert len(preds) == 1 and preds[0]["pred_boxes"].shape[1] == 7
    assert torch.isfinite(preds[0]["pred_boxes"]).all()
