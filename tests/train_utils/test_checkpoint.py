"""Training checkpoints: durable writes, the CUDA generators' states, which recorded settings a
resume compares, and reading them with ``weights_only=True``."""

import copy
import os
import stat
from pathlib import Path

import pytest
import torch
from device_params import DEVICES
from malicious_files import malicious_checkpoint

from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.models.optimization import build_optimizer, build_scheduler
from pcdet_atlas.train_utils import (
    check_resume_settings,
    checkpoint_state,
    export_model_checkpoint,
    find_resume_checkpoint,
    load_checkpoint,
    save_checkpoint,
)
from pcdet_atlas.train_utils.checkpoint import model_config_sha256, training_seed
from pcdet_atlas.train_utils.stages import TrainingStage, load_stage_init
from pcdet_atlas.utils.safe_pickle import RefusedGlobalError


def test_save_checkpoint_syncs_the_file_before_the_rename_and_the_folder_after(
    tmp_path, monkeypatch
):
    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        info = os.fstat(fd)
        events.append(("fsync", stat.S_ISDIR(info.st_mode), info.st_ino, info.st_size))
        real_fsync(fd)

    def replace(src, dst, *args, **kwargs):
        events.append(("replace", str(src), str(dst)))
        real_replace(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)  # what Path.replace calls
    path = tmp_path / "ckpt" / "checkpoint_epoch_1.pth"
    save_checkpoint(checkpoint_state(torch.nn.Linear(2, 1), epoch=1, it=1), path)
    assert [e[0] for e in events] == ["fsync", "replace", "fsync"]
    _, is_dir, ino, size = events[0]  # the whole temporary file, under the name it then gets
    assert not is_dir and ino == path.stat().st_ino and size == path.stat().st_size > 0
    tmp, dst = events[1][1:]  # a temporary file of its own in the same folder
    assert Path(tmp).parent == path.parent and Path(tmp).name.startswith(".") and dst == str(path)
    assert events[2][1:3] == (True, path.parent.stat().st_ino)
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]
    assert torch.load(path, weights_only=False)["epoch"] == 1


@pytest.mark.parametrize("planted", ["checkpoint_epoch_1.pth.tmp", "checkpoint_epoch_1.pth"])
def test_save_checkpoint_writes_through_no_planted_symlink(tmp_path, planted):
    """A resumed run's ``ckpt/`` received with a symlink at the checkpoint's name or at the
    fixed temporary name of earlier versions: no write goes through it."""
    victim = tmp_path / "victim"
    victim.write_text("IMPORTANT USER DATA\n")
    ckpt_dir = tmp_path / "ckpt"
    ckpt_dir.mkdir()
    (ckpt_dir / planted).symlink_to(victim)
    path = save_checkpoint(
        checkpoint_state(torch.nn.Linear(2, 1), epoch=1, it=1),
        ckpt_dir / "checkpoint_epoch_1.pth",
    )
    assert victim.read_text() == "IMPORTANT USER DATA\n"
    assert not path.is_symlink() and torch.load(path, weights_only=False)["epoch"] == 1


def test_cuda_generator_states_are_saved_and_restored_when_cuda_is_in_use(tmp_path, monkeypatch):
    """On CPU, with torch.cuda stood in for: the field holds every device's state and each
    device present on resume gets its own back."""
    states = [torch.arange(4, dtype=torch.uint8), torch.arange(4, 8, dtype=torch.uint8)]
    restored = []
    monkeypatch.setattr(torch.cuda, "is_initialized", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_rng_state_all", lambda: [s.clone() for s in states])
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setattr(torch.cuda, "set_rng_state_all", restored.extend)
    model = torch.nn.Linear(2, 1)
    path = save_checkpoint(checkpoint_state(model, epoch=1, it=1), tmp_path / "a.pth")
    ckpt = load_checkpoint(path, model)
    assert [torch.equal(a, b) for a, b in zip(ckpt["cuda_rng_state"], states)] == [True, True]
    assert len(restored) == 1 and torch.equal(restored[0], states[0])  # the one GPU there

    restored.clear()  # a checkpoint of the code before the field: nothing to restore
    old = torch.load(path, weights_only=False)
    del old["cuda_rng_state"]
    torch.save(old, tmp_path / "old.pth")
    load_checkpoint(tmp_path / "old.pth", model)
    assert restored == []


def test_a_process_that_never_used_cuda_records_no_cuda_state(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_initialized", lambda: False)
    ckpt = checkpoint_state(torch.nn.Linear(2, 1), epoch=0, it=0)
    assert ckpt["cuda_rng_state"] is None


@pytest.mark.parametrize("device", DEVICES)
def test_resumed_dropout_draws_go_on_where_the_checkpoint_left_them(tmp_path, device):
    """The generator of the device the model trains on continues after a resume: the next
    dropout masks are those the uninterrupted process would have drawn."""
    model = torch.nn.Linear(2, 1).to(device)
    x = torch.ones(4096, device=device)
    torch.nn.functional.dropout(x, 0.5)  # the generator has moved on from its seed
    path = save_checkpoint(checkpoint_state(model, epoch=1, it=1), tmp_path / "a.pth")
    expected = torch.nn.functional.dropout(x, 0.5)
    torch.manual_seed(123)  # a new process: seeded afresh
    load_checkpoint(path, model)
    assert torch.equal(torch.nn.functional.dropout(x, 0.5), expected)


SETTINGS = {
    "OPTIMIZATION": {"LR": 0.003, "NUM_EPOCHS": 36},
    "batch_size": 4,
    "processes": 1,
    "seed": 666,
    "config_sha256": {"MODEL": "a" * 64},
}


def test_only_the_settings_a_checkpoint_records_are_compared(tmp_path):
    older = {"train_settings": {"OPTIMIZATION": {"LR": 0.003, "NUM_EPOCHS": 36}, "batch_size": 4}}
    check_resume_settings(older, SETTINGS, tmp_path / "old.pth")  # no seed etc. recorded
    check_resume_settings({}, SETTINGS, tmp_path / "older.pth")  # no settings at all
    with pytest.raises(ValueError, match=r"OPTIMIZATION\.LR: 0\.003 -> 0\.001"):
        check_resume_settings(older, {**SETTINGS, "OPTIMIZATION": {"LR": 0.001, "NUM_EPOCHS": 36}},
                              tmp_path / "old.pth")  # fmt: skip
    with pytest.raises(ValueError, match=r"OPTIMIZATION\.WARMUP_EPOCH: None -> 1"):
        check_resume_settings(older, {**SETTINGS, "OPTIMIZATION": {
            "LR": 0.003, "NUM_EPOCHS": 36, "WARMUP_EPOCH": 1}}, tmp_path / "old.pth")  # fmt: skip


@pytest.mark.parametrize(
    "field, value, shown",
    [("processes", 2, "processes: 1 -> 2"), ("seed", 7, "seed: 666 -> 7"),
     ("config_sha256", {"MODEL": "b" * 64}, f"config_sha256.MODEL: '{'a' * 64}' -> '{'b' * 64}'")],
)  # fmt: skip
def test_a_recorded_setting_that_differs_is_refused_naming_it(tmp_path, field, value, shown):
    path = tmp_path / "checkpoint_epoch_3.pth"
    with pytest.raises(ValueError, match=rf"cannot resume {path}: .*\(") as exc:
        check_resume_settings({"train_settings": SETTINGS}, {**SETTINGS, field: value}, path)
    assert shown in str(exc.value)


def test_settings_are_compared_before_the_optimizer_state_is_loaded(tmp_path):
    """A stage that trains other modules has other parameter groups: the run is refused naming
    the changed STAGE, not with torch's bare "parameter group" error."""
    from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
    from pcdet_atlas.train_utils import resume_settings

    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs/atlas/synthetic/phim_lot/stage2_ssm.yaml")
    flags = {"batch_size": 2, "processes": 1, "seed": 666, "use_amp": False, "sync_bn": False,
             "merge_all_iters_to_one_epoch": False}  # fmt: skip
    saved = resume_settings(cfg, **flags)
    cfg.STAGE.TRAIN = [*cfg.STAGE.TRAIN, "lot.score_mlp"]
    cfg.STAGE.FREEZE = [m for m in cfg.STAGE.FREEZE if m != "lot.score_mlp"]
    now = resume_settings(cfg, **flags)
    assert now["OPTIMIZATION"] == saved["OPTIMIZATION"]

    model = torch.nn.Sequential(torch.nn.Linear(2, 2), torch.nn.Linear(2, 1))
    one_group = torch.optim.AdamW(model[1].parameters())
    path = save_checkpoint(
        checkpoint_state(model, one_group, epoch=1, it=1, train_settings=saved), tmp_path / "a.pth"
    )
    two_groups = torch.optim.AdamW(model.parameters())
    with pytest.raises(ValueError, match=r"parameter group"):  # what the settings now preempt
        load_checkpoint(path, model, two_groups)
    with pytest.raises(ValueError, match=rf"cannot resume {path}: .*config_sha256\.STAGE: '"):
        load_checkpoint(path, model, two_groups, train_settings=now)


@pytest.mark.parametrize("optimizer", ["adam_onecycle", "adam", "sgd"])
def test_everything_a_training_checkpoint_saves_loads_under_weights_only(tmp_path, optimizer):
    """Optimizer, scheduler (OneCycleLR; LambdaLR with warm-up and decay), AMP scaler, RNG
    states and settings are plain: a resume reads them with ``weights_only=True``."""
    optim_cfg = {"OPTIMIZER": optimizer, "LR": 0.003, "WEIGHT_DECAY": 0.01,
                 "DECAY_STEP_LIST": [1], "LR_WARMUP": True, "WARMUP_EPOCH": 1,
                 "BATCH_SIZE_PER_GPU": 2, "NUM_EPOCHS": 2, "GRAD_NORM_CLIP": 10}  # fmt: skip

    def build():
        torch.manual_seed(0)
        model = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.BatchNorm1d(4))
        opt = build_optimizer(model, optim_cfg)
        return model, opt, build_scheduler(opt, optim_cfg, iters_per_epoch=4, total_epochs=2)

    model, opt, sched = build()
    scaler = torch.amp.GradScaler("cpu")
    for _ in range(3):
        opt.zero_grad()
        model(torch.randn(8, 3)).square().sum().backward()
        opt.step()
        sched.step()
    state = checkpoint_state(model, opt, sched, scaler, epoch=0, it=3, epoch_it=3,
                             epoch_loss_sums={"loss": 1.5}, train_settings=SETTINGS)  # fmt: skip
    path = save_checkpoint(state, tmp_path / "latest_model.pth")
    torch.load(path, weights_only=True)  # nothing in it needs more
    model2, opt2, sched2 = build()
    scaler2 = torch.amp.GradScaler("cpu")
    ckpt = load_checkpoint(path, model2, opt2, sched2, scaler2, train_settings=SETTINGS)
    assert ckpt["epoch_loss_sums"] == {"loss": 1.5} and ckpt["epoch_it"] == 3
    assert sched2.state_dict() == sched.state_dict() and sched2.get_last_lr() == sched.get_last_lr()
    assert scaler2.state_dict() == scaler.state_dict()
    for a, b in zip(opt.state_dict()["state"].values(), opt2.state_dict()["state"].values()):
        assert all(torch.equal(a[k], b[k]) for k in a)


def test_a_training_checkpoint_that_would_run_code_is_refused(tmp_path):
    """``--ckpt``, auto-resume (``latest_model.pth``), the export of a model-zoo file and a
    stage's initialisation all read with ``weights_only=True``."""
    model = torch.nn.Linear(2, 1)
    marker = tmp_path / "marker"
    good = save_checkpoint(checkpoint_state(model, epoch=1, it=1), tmp_path / "ckpt" / "a.pth")
    evil = malicious_checkpoint(
        tmp_path / "ckpt" / "latest_model.pth", marker, **torch.load(good, weights_only=True)
    )
    refused = rf"checkpoint {evil} refused: it needs \S+ to load"
    with pytest.raises(RefusedGlobalError, match=refused):
        find_resume_checkpoint(evil.parent)
    with pytest.raises(RefusedGlobalError, match=refused):
        load_checkpoint(evil, model)
    with pytest.raises(RefusedGlobalError, match=refused):
        export_model_checkpoint(evil, tmp_path / "small.pth")
    stage = TrainingStage(name="s", init_from=None, train=("weight",), freeze=(), source="s.yaml")
    with pytest.raises(RefusedGlobalError, match=refused):
        load_stage_init(model, stage, evil)
    assert not marker.exists()


def test_the_training_seed_and_model_digest_that_results_record(tmp_path):
    """results.json's training_seed: the checkpoint's train_settings, else the config's
    ATLAS.TRAINING_SEED (a contradiction or a non-integer is refused, naming the file); its
    model_sha256: the same for one model config under another checkpoint, display name or data
    path, another for another model; export keeps the record."""
    assert training_seed({"train_settings": {"seed": 3}}, None, "a.pth") == 3
    assert training_seed({"train_settings": {"seed": 3}}, 3, "a.pth") == 3
    assert training_seed({"model_state": {}}, 666, "a.pth") == 666
    assert training_seed({"train_settings": None}, None, "a.pth") is None
    with pytest.raises(ValueError, match=r"a\.pth: trained with seed 3 .* says 4"):
        training_seed({"train_settings": {"seed": 3}}, 4, "a.pth")
    with pytest.raises(ValueError, match="TRAINING_SEED '1': expected an integer"):
        training_seed({}, "1", "a.pth")
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "centerpoint.yaml")
    digest = model_config_sha256(cfg)
    other = copy.deepcopy(cfg)
    other.ATLAS.CHECKPOINT, other.ATLAS.MODEL_NAME = "ckpt/seed2.pth", "CenterPoint seed 2"
    other.DATA_CONFIG.DATA_PATH = "/elsewhere"
    assert model_config_sha256(other) == digest
    other.MODEL.DENSE_HEAD.SHARED_CONV_CHANNEL = 64
    assert model_config_sha256(other) != digest
    cp4f = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "cp4f.yaml")
    assert model_config_sha256(cp4f) != digest
    path = tmp_path / "full.pth"
    torch.save({"model_state": {}, "optimizer_state": {}, "train_settings": {"seed": 5}}, path)
    small = torch.load(export_model_checkpoint(path, tmp_path / "small.pth"), weights_only=True)
    assert training_seed(small, None, "small.pth") == 5 and "optimizer_state" not in small
