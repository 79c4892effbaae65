"""Training checkpoints: durable writes, the CUDA generators' states, and which recorded
settings a resume compares."""

import os
import stat

import pytest
import torch
from device_params import DEVICES

from pcdet_atlas.train_utils import (
    check_resume_settings,
    checkpoint_state,
    load_checkpoint,
    save_checkpoint,
)


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
    assert events[1][1:] == (str(path) + ".tmp", str(path))
    assert events[2][1:3] == (True, path.parent.stat().st_ino)
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]
    assert torch.load(path, weights_only=False)["epoch"] == 1


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
