"""The MSF detector: every MSF config builds and trains (smoke), the frozen RPN, the RPN's
record in checkpoints, proposals from the attacked input (a phantom reaches the RPN), and the
training proposal cache."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import torch
from device_params import DEVICES
from malicious_files import malicious_checkpoint
from model_batches import two_stage_batch as training_batch

from pcdet_atlas.attacks import AtlasWaymoDataset
from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.datasets.dataset import collate_batch
from pcdet_atlas.models import build_network_from_config, load_data_to_device
from pcdet_atlas.models.detectors import MSF, TwoStageDetector
from pcdet_atlas.models.detectors.detector3d_template import CheckpointMismatchError
from pcdet_atlas.models.detectors.two_stage import roi_boxes_to_padded
from pcdet_atlas.models.model_utils.motion_sampler import propagate_boxes
from pcdet_atlas.ops.iou3d_nms import boxes_iou_bev
from pcdet_atlas.train_utils import checkpoint_state, export_model_checkpoint, load_checkpoint
from pcdet_atlas.train_utils.proposals import proposal_cache_file, training_proposals
from pcdet_atlas.utils.safe_pickle import RefusedGlobalError

CFGS = REPO_ROOT / "cfgs" / "atlas"
MSF_CONFIGS = sorted(
    p for p in CFGS.rglob("*.yaml") if cfg_from_yaml_file(p).MODEL.NAME in ("MSF",)
)


def test_msf_configs_exist():
    names = {str(p.relative_to(CFGS)) for p in MSF_CONFIGS}
    assert names == {"msf_4f.yaml", "msf_8f.yaml", "synthetic/msf_4f.yaml", "synthetic/msf_8f.yaml"}


def load_msf_cfg(path: Path, rpn_ckpt: Path | None = None):
    """The config; a real-Waymo one with a random RPN and fewer ROIs and points per frame (the
    parameters do not depend on those; the full sizes need GPU memory)."""
    cfg = cfg_from_yaml_file(path)
    if rpn_ckpt is not None and "synthetic" not in path.parts:
        cfg.MODEL.RPN.CHECKPOINT = str(rpn_ckpt)
        cfg.MODEL.ROI_HEAD.TARGET_CONFIG.ROI_PER_IMAGE = 8
        cfg.MODEL.ROI_HEAD.SAMPLER.NUM_POINTS = 16
    return cfg


@pytest.mark.parametrize("path", MSF_CONFIGS, ids=lambda p: str(p.relative_to(CFGS)))
def test_build_train_predict(path, real_rpn_checkpoint):
    cfg = load_msf_cfg(path, real_rpn_checkpoint)
    model = build_network_from_config(cfg)
    assert isinstance(model, MSF)
    head = model.roi_head
    assert head.num_frames == cfg.ATLAS.TEMPORAL_WINDOW  # the lifecycle W is the input window
    seq = cfg.DATA_CONFIG.SEQUENCE_CONFIG.SAMPLE_OFFSET
    assert seq[1] - seq[0] + 1 == head.num_frames
    assert model.rpn_info["window"] == 4  # the same 4-frame RPN for both
    batch = training_batch(head.num_frames)
    model.train()
    ret, tb, _ = model(batch)
    assert {"loss", "rcnn_loss_cls", "rcnn_loss_reg", "rcnn_loss_corner"} <= set(tb)
    ret["loss"].backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    if "synthetic" in path.parts:  # the shipped RPN proposes on the batch's points
        model.eval()
        preds, _ = model(batch)
        assert len(preds) == 2
        for p in preds:
            assert p["pred_boxes"].shape[1] == 7 and torch.isfinite(p["pred_boxes"]).all()
            assert (p["pred_scores"] > 0.1).all()


def synthetic_msf(name: str = "msf_4f.yaml"):
    torch.manual_seed(0)
    return build_network_from_config(cfg_from_yaml_file(CFGS / "synthetic" / name))


@pytest.mark.parametrize("device", DEVICES[1:])
def test_the_head_computes_on_cuda_what_it_computes_on_the_cpu(device):
    """MSF-8f's second stage on the same proposals: the sampler's keys are drawn on the CPU, so
    both devices sample the same points, and the refined boxes and logits agree to float32
    rounding."""
    model = synthetic_msf("msf_8f.yaml").eval()
    batch = training_batch(8)

    def outputs(dev):
        model.to(dev)
        b = load_data_to_device(batch, dev)
        rois, _, _, valid = roi_boxes_to_padded(b["roi_boxes"])
        head = model.roi_head
        traj = torch.stack([propagate_boxes(r, head.num_frames) for r in rois])
        with torch.no_grad():
            out = head({
                **b, "rois": rois, "roi_valid": valid, "trajectories": traj,
                "generators": model.sample_generators(b, "msf_points"),
            })  # fmt: skip
            boxes, logits = head.decode(out, rois)
        return boxes.cpu(), logits.cpu(), valid.cpu()

    cpu_boxes, cpu_logits, valid = outputs("cpu")
    gpu_boxes, gpu_logits, _ = outputs(device)
    assert valid.sum() >= 4
    torch.testing.assert_close(gpu_boxes[valid], cpu_boxes[valid], atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(gpu_logits[valid], cpu_logits[valid], atol=1e-4, rtol=1e-4)


def test_the_rpn_is_frozen_and_outside_the_trained_state():
    model = synthetic_msf()
    rpn_state = {k: v.clone() for k, v in model.rpn.state_dict().items()}
    own = {id(p) for p in model.parameters()}
    assert not own & {id(p) for p in model.rpn.parameters()}
    assert not any(k.startswith("rpn") for k in model.state_dict())
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    batch = training_batch(4)
    for _ in range(2):
        model.train()
        assert not model.rpn.training  # batch-norm statistics of the RPN never move
        loss = model(batch)[0]["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        model.eval()
        model.predict(batch)
    for k, v in model.rpn.state_dict().items():
        assert torch.equal(v, rpn_state[k]), k


def test_checkpoints_record_the_rpn(tmp_path):
    model = synthetic_msf()
    path = tmp_path / "msf.pth"
    torch.save(checkpoint_state(model, epoch=1, it=1), path)
    small = export_model_checkpoint(path, tmp_path / "small.pth")
    model.load_params_from_file(small)  # the RPN it was trained with: loads
    other = tmp_path / "other_rpn.pth"
    rpn = torch.load(REPO_ROOT / "checkpoints" / "cp4f_synthetic.pth", weights_only=False)
    rpn["epoch"] = -1  # other bytes, other hash
    torch.save(rpn, other)
    cfg = cfg_from_yaml_file(CFGS / "synthetic" / "msf_4f.yaml")
    cfg.MODEL.RPN.CHECKPOINT = str(other)
    other_model = build_network_from_config(cfg)
    with pytest.raises(CheckpointMismatchError, match="trained on the proposals of an RPN"):
        other_model.load_params_from_file(small)
    with pytest.raises(CheckpointMismatchError, match="trained on the proposals of an RPN"):
        load_checkpoint(path, other_model)  # resuming a training run with another RPN


def test_an_rpn_checkpoint_that_would_run_code_is_refused(tmp_path):
    """``MODEL.RPN.CHECKPOINT`` is read with ``weights_only=True``."""
    rpn = torch.load(REPO_ROOT / "checkpoints" / "cp4f_synthetic.pth", weights_only=True)
    marker = tmp_path / "marker"
    evil = malicious_checkpoint(tmp_path / "rpn.pth", marker, **rpn)
    cfg = cfg_from_yaml_file(CFGS / "synthetic" / "msf_4f.yaml")
    cfg.MODEL.RPN.CHECKPOINT = str(evil)
    with pytest.raises(RefusedGlobalError, match=rf"checkpoint {evil} refused: it needs \S+"):
        build_network_from_config(cfg)
    assert not marker.exists()


def test_missing_rpn_checkpoint_names_it():
    cfg = cfg_from_yaml_file(CFGS / "msf_8f.yaml")
    with pytest.raises(FileNotFoundError, match=r"MODEL\.RPN\.CHECKPOINT.*checkpoint_epoch_36"):
        build_network_from_config(cfg)


def test_a_phantom_reaches_the_rpn_on_spoofed_frames(synthetic_root, injection):
    cfg = cfg_from_yaml_file(CFGS / "synthetic" / "msf_4f.yaml")
    data_cfg = copy.deepcopy(cfg.DATA_CONFIG)
    data_cfg.DATA_PATH = str(synthetic_root)
    attacked = AtlasWaymoDataset(data_cfg, cfg.CLASS_NAMES, injection, training=False)
    clean = AtlasWaymoDataset(
        data_cfg, cfg.CLASS_NAMES, REPO_ROOT / "cfgs" / "attacks" / "clean.yaml", training=False
    )
    model = synthetic_msf().eval()
    seen = 0
    for index in (44, 52, 60):  # spoofed frames of the run 32..63
        sample = attacked[index]
        meta = sample["attack"]
        assert meta["spoofed"] and meta["target_box"] is not None
        phantom = torch.from_numpy(meta["target_box"])[None]
        with_phantom = model.propose(load_data_to_device(collate_batch([sample]), "cpu"))[0]
        without = model.propose(load_data_to_device(collate_batch([clean[index]]), "cpu"))[0]
        hit = boxes_iou_bev(with_phantom["pred_boxes"][:, :7], phantom).amax() if len(
            with_phantom["pred_boxes"]) else torch.tensor(0.0)  # fmt: skip
        miss = boxes_iou_bev(without["pred_boxes"][:, :7], phantom).amax() if len(
            without["pred_boxes"]) else torch.tensor(0.0)  # fmt: skip
        assert float(miss) < 0.1  # nothing was there on the clean frame
        seen += float(hit) > 0.3
    assert seen >= 2  # the RPN proposes the phantom: MSF refines what the attack put there


def test_training_proposals_are_cached_by_rpn_hash(synthetic_root, tmp_path):
    cpu = torch.device("cpu")
    cfg = cfg_from_yaml_file(CFGS / "synthetic" / "msf_4f.yaml")
    cfg.DATA_CONFIG.DATA_PATH = str(synthetic_root)
    cfg.MODEL.RPN.CACHE_DIR = str(tmp_path / "cache")
    model = build_network_from_config(cfg)
    table, path = training_proposals(
        model, cfg.DATA_CONFIG, cfg.CLASS_NAMES, device=torch.device("cpu")
    )
    assert path.is_file() and path == proposal_cache_file(model, cfg.DATA_CONFIG, "train")
    assert len(table) == 20 and all(v.shape[1] == 11 for v in table.values())
    assert all(np.isin(v[:, 10], [1, 2, 3]).all() and (v[:, 9] > 0.1).all() for v in table.values())
    again, _ = training_proposals(
        model, cfg.DATA_CONFIG, cfg.CLASS_NAMES, device=torch.device("cpu")
    )
    assert all(np.array_equal(again[k], table[k]) for k in table)  # read back from the cache
    # another RPN checkpoint never reads this file: its key differs
    model.rpn_info = {**model.rpn_info, "sha256": "0" * 64}
    assert proposal_cache_file(model, cfg.DATA_CONFIG, "train") != path
    # a file whose record disagrees with its name is refused
    data = torch.load(path, weights_only=True)
    data["rpn_checkpoint_sha256"] = "f" * 64
    torch.save(data, path)
    model.rpn_info = {**model.rpn_info, "sha256": build_network_from_config(cfg).rpn_info["sha256"]}
    with pytest.raises(ValueError, match="rpn_checkpoint_sha256"):
        training_proposals(model, cfg.DATA_CONFIG, cfg.CLASS_NAMES, device=cpu)


def test_a_proposal_cache_that_would_run_code_is_refused(synthetic_root, tmp_path):
    cfg = cfg_from_yaml_file(CFGS / "synthetic" / "msf_4f.yaml")
    cfg.DATA_CONFIG.DATA_PATH = str(synthetic_root)
    cfg.MODEL.RPN.CACHE_DIR = str(tmp_path / "cache")
    model = build_network_from_config(cfg)
    marker = tmp_path / "marker"
    path = malicious_checkpoint(proposal_cache_file(model, cfg.DATA_CONFIG, "train"), marker)
    with pytest.raises(ValueError, match=rf"{path}: not a proposal cache .*could run code"):
        training_proposals(model, cfg.DATA_CONFIG, cfg.CLASS_NAMES, device=torch.device("cpu"))
    assert not marker.exists()


def test_the_dataset_serves_and_augments_proposals_with_the_boxes(synthetic_root):
    from pcdet_atlas.datasets import build_dataloader

    cfg = cfg_from_yaml_file(CFGS / "synthetic" / "msf_4f.yaml")
    cfg.DATA_CONFIG.DATA_PATH = str(synthetic_root)
    dataset, _, _ = build_dataloader(
        cfg.DATA_CONFIG, cfg.CLASS_NAMES, 1, False, workers=0, training=True
    )
    with pytest.raises(KeyError, match="no proposals for 20 of the 20 frames"):
        dataset.set_proposals({}, "table.pkl")
    # each frame's proposals: its own ground truth (with velocity), score 0.9
    table = {}
    for info in dataset.infos:
        anno = dataset.get_annotations(info)
        boxes = anno["gt_boxes"]
        labels = [
            cfg.CLASS_NAMES.index(n) + 1 if n in cfg.CLASS_NAMES else 0 for n in anno["gt_names"]
        ]
        table[info["frame_id"]] = np.concatenate(
            [boxes[:, :9], np.full((len(boxes), 1), 0.9), np.array(labels, float)[:, None]], 1
        ).astype(np.float32)
    dataset.set_proposals(table, "table.pkl")
    for index in (3, 14):
        sample = dataset[index]
        gt, rois = sample["gt_boxes"], sample["roi_boxes"]
        assert sample["flip_x"] or sample["flip_y"] or abs(sample["noise_rot"]) > 0
        # the augmentation moved proposals exactly as the boxes they copy
        for box in gt:
            match = np.abs(rois[:, :9] - box[:9]).max(1)
            assert match.min() < 1e-4
        assert np.allclose(rois[:, 9], 0.9) and set(rois[:, 10]) <= {1.0, 2.0, 3.0, 0.0}
    batch = collate_batch([dataset[0], dataset[1]])
    assert batch["roi_boxes"].shape[0] == 2 and batch["roi_boxes"].shape[2] == 11
    assert isinstance(batch["frame_seed"], np.ndarray) and batch["frame_seed"].shape == (2,)


def test_two_stage_detector_is_exported():
    assert issubclass(MSF, TwoStageDetector)


@pytest.mark.slow
def test_test_tool_runs_msf_with_its_window_and_refuses_missing_data(
    synthetic_root, injection, tmp_path, capsys
):
    """tools/test.py on MSF-8f: same flags and results.json, lifecycle window 8; on a fresh
    machine the real config stops at once naming the data path and the synthetic config."""
    from model_batches import load_tool

    from pcdet_atlas.evaluation import load_results

    test = load_tool("test")
    with pytest.raises(SystemExit, match=r"DATA_PATH .*absent.*--cfg cfgs/atlas/synthetic/msf_8f"):
        test.main(["--cfg", str(CFGS / "msf_8f.yaml"), "--set", "DATA_CONFIG.DATA_PATH",
                   str(tmp_path / "absent")])  # fmt: skip
    model = synthetic_msf("msf_8f.yaml")
    ckpt = tmp_path / "msf_random.pth"
    torch.save(checkpoint_state(model, epoch=0, it=0), ckpt)
    variant = tmp_path / "inj_global_hard.yaml"
    variant.write_text(
        f"_BASE_CONFIG_: {REPO_ROOT / 'cfgs' / 'attacks' / 'inj_global_hard.yaml'}\n"
        f"TRACE_LIBRARY:\n  PATH: {injection.TRACE_LIBRARY.PATH}\n  MIN_POINTS: 100\n"
    )
    ret = test.main([
        "--cfg", str(CFGS / "synthetic" / "msf_8f.yaml"), "--ckpt", str(ckpt), "--attacks",
        f"clean,{variant}", "--out_dir", str(tmp_path / "out"), "--workers", "0",
        "--no_progress", "--device", "cpu", "--set", "DATA_CONFIG.DATA_PATH", str(synthetic_root),
        "DATA_CONFIG.SAMPLED_INTERVAL", "train:1,test:14",
    ])  # fmt: skip
    results = load_results(ret["output_dir"] / "results.json")
    assert results["model"] == "MSF-8f"
    inj = results["variants"]["inj_global_hard"]
    assert inj["num_frames"] == 5 and inj["num_targets"] == 2
    assert inj["lifecycle"]["window"] == 8
    assert "inj_global_hard" in capsys.readouterr().out  # the table
