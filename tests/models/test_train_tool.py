"""tools/train.py end to end on the tiny synthetic dataset: the loss falls, resume is exact, a
resume with other settings is refused; bad counts, devices and checkpoints are clear errors."""

import shutil

import pytest
import torch
from model_batches import load_tool

import pcdet_atlas
from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.models import build_network_from_config
from pcdet_atlas.train_utils import checkpoint_state, export_model_checkpoint, save_checkpoint
from pcdet_atlas.utils.provenance import source_revision

CFG = REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "centerpoint.yaml"


def train_args(root, out, epochs, extra_tag):
    return [
        "--cfg", str(CFG), "--out_dir", str(out), "--extra_tag", extra_tag,
        "--epochs", str(epochs), "--batch_size", "2", "--workers", "0", "--no_progress",
        "--fix_random_seed", "--device", "cpu",
        "--set", "DATA_CONFIG.DATA_PATH", str(root),
        "DATA_CONFIG.DATA_AUGMENTOR.DISABLE_AUG_LIST", "gt_sampling",
        "DATA_CONFIG.SAMPLED_INTERVAL", "train:5,test:5",
        # a 64 x 64 pillar crop keeps the test fast; the model widths are the config's
        "DATA_CONFIG.POINT_CLOUD_RANGE", "-20.48,-20.48,-2,20.48,20.48,4",
        "OPTIMIZATION.LR", "0.01",
    ]  # fmt: skip


@pytest.mark.slow
def test_train_lowers_loss_and_resumes_bit_exactly(synthetic_root, tmp_path):
    train = load_tool("train")
    out = tmp_path / "output"
    full = train.main(train_args(synthetic_root, out, 3, "full"))
    run_dir = full["output_dir"]
    assert run_dir == out / "atlas" / "synthetic" / "centerpoint" / "full"
    history = full["state"].history
    assert len(history) == 3 and full["state"].it == 6  # 4 frames / batch 2 = 2 steps per epoch
    assert history[-1]["loss"] < history[0]["loss"]
    assert (run_dir / "centerpoint.yaml").is_file()
    assert list(run_dir.glob("train_*.log")) and list((run_dir / "tensorboard").iterdir())
    ckpts = sorted(p.name for p in (run_dir / "ckpt").iterdir())
    assert ckpts == [f"checkpoint_epoch_{e}.pth" for e in (1, 2, 3)]

    # an interrupted run (only epoch 2's checkpoint left) resumes to the same weights, bit for bit
    resumed_dir = out / "atlas" / "synthetic" / "centerpoint" / "resumed" / "ckpt"
    resumed_dir.mkdir(parents=True)
    shutil.copy(run_dir / "ckpt" / "checkpoint_epoch_2.pth", resumed_dir)
    resumed = train.main(train_args(synthetic_root, out, 3, "resumed"))
    assert resumed["state"].epoch == 3 and resumed["state"].it == 6
    assert len(resumed["state"].history) == 1  # only epoch 3 was trained here
    a = torch.load(run_dir / "ckpt" / "checkpoint_epoch_3.pth", weights_only=False)
    b = torch.load(resumed_dir / "checkpoint_epoch_3.pth", weights_only=False)
    assert a["model_state"].keys() == b["model_state"].keys()
    for k in a["model_state"]:
        assert torch.equal(a["model_state"][k], b["model_state"][k]), k
    assert a["scheduler_state"]["last_epoch"] == b["scheduler_state"]["last_epoch"] == 6
    assert history[-1] == resumed["state"].history[0]
    # each checkpoint names the training calls behind it: where each started, on what, from
    # which code; the resumed run's adds its own to those of the checkpoint it resumed
    (run,) = a["train_runs"]
    assert run["from_epoch"] == 0 and run["from_it"] == 0 and run["device"] == "cpu"
    assert run["threads"] == torch.get_num_threads() and run["processes"] == 1
    assert run["torch"] == str(torch.__version__) and run["package"] == pcdet_atlas.__version__
    revision = source_revision()
    assert run["source_commit"] == (revision and revision.commit)
    first, second = b["train_runs"]
    assert first == run and (second["from_epoch"], second["from_it"]) == (2, 4)
    small = export_model_checkpoint(resumed_dir / "checkpoint_epoch_3.pth", tmp_path / "s.pth")
    assert torch.load(small, weights_only=True)["train_runs"] == b["train_runs"]


@pytest.mark.parametrize(
    "flag, value",
    [("--epochs", "0"), ("--epochs", "-3"), ("--batch_size", "0"), ("--batch_size", "-2"),
     ("--workers", "-1"), ("--max_ckpt_save_num", "0"), ("--ckpt_save_interval", "0"),
     ("--num_epochs_to_eval", "-1"), ("--logger_iter_interval", "0"), ("--threads", "0"),
     ("--epochs", "two")],
)  # fmt: skip
def test_counts_below_their_minimum_are_usage_errors(flag, value, capsys):
    train = load_tool("train")
    with pytest.raises(SystemExit) as exc:
        train.parse_args(["--cfg", str(CFG), flag, value])
    assert exc.value.code == 2
    assert f"argument {flag}: must be an integer >=" in capsys.readouterr().err


@pytest.mark.skipif(torch.cuda.is_available(), reason="the case of a machine without a GPU")
@pytest.mark.parametrize(
    "tool, args",
    [
        ("train", ["--cfg", str(CFG)]),
        ("test", ["--cfg", str(CFG)]),
        ("data/create_synthetic_waymo", []),
    ],
)
def test_device_cuda_without_gpu_is_one_clear_error(tool, args, capsys):
    with pytest.raises(SystemExit):
        load_tool(tool).parse_args([*args, "--device", "cuda"])
    err = capsys.readouterr().err.splitlines()[-1]
    assert err.endswith("error: argument --device: 'cuda': no CUDA GPU is visible to torch "
                        "(torch.cuda.is_available() is False); use --device cpu")  # fmt: skip


def one_step_args(root, out, extra_tag, *overrides):
    """One epoch of one step (2 frames, batch 2)."""
    args = train_args(root, out, 1, extra_tag)
    args[args.index("train:5,test:5")] = "train:10,test:10"
    return args + list(overrides)


def test_resume_with_other_settings_is_refused_and_the_config_states_them(synthetic_root, tmp_path):
    train = load_tool("train")
    ret = train.main(one_step_args(synthetic_root, tmp_path, "run"))
    run_dir = ret["output_dir"]
    assert ret["state"].it == 1
    saved = cfg_from_yaml_file(run_dir / "centerpoint.yaml")
    # what --epochs 1 / --batch_size 2 put in effect, not the YAML's 20 epochs of 4
    assert saved.OPTIMIZATION.NUM_EPOCHS == 1 and saved.OPTIMIZATION.BATCH_SIZE_PER_GPU == 2
    ckpt = torch.load(run_dir / "ckpt" / "checkpoint_epoch_1.pth", weights_only=False)
    assert ckpt["train_settings"]["OPTIMIZATION"]["LR"] == 0.01
    assert ckpt["train_settings"]["batch_size"] == 2

    with pytest.raises(ValueError, match=r"OPTIMIZATION\.LR: 0\.01 -> 0\.02") as exc:
        train.main(one_step_args(synthetic_root, tmp_path, "run", "OPTIMIZATION.WEIGHT_DECAY",
                                 "0.02", "OPTIMIZATION.LR", "0.02"))  # fmt: skip
    assert "OPTIMIZATION.WEIGHT_DECAY" in str(exc.value) and "checkpoint_epoch_1.pth" in str(
        exc.value
    )
    args = one_step_args(synthetic_root, tmp_path, "run")
    args[args.index("--epochs") + 1] = "2"
    with pytest.raises(ValueError, match=r"OPTIMIZATION\.NUM_EPOCHS: 1 -> 2"):
        train.main(args)
    args[args.index("--batch_size") + 1] = "1"
    args[args.index("--epochs") + 1] = "1"
    with pytest.raises(ValueError, match=r"batch_size: 2 -> 1"):
        train.main(args)
    # a refused resume leaves the saved config as it was
    assert cfg_from_yaml_file(run_dir / "centerpoint.yaml") == saved


def test_truncated_checkpoint_names_its_path(synthetic_root, tmp_path):
    train = load_tool("train")
    ckpt_dir = tmp_path / "atlas" / "synthetic" / "centerpoint" / "cut" / "ckpt"
    ckpt_dir.mkdir(parents=True)
    model = build_network_from_config(cfg_from_yaml_file(CFG))
    whole = tmp_path / "whole.pth"
    torch.save({"model_state": model.state_dict(), "epoch": 1}, whole)
    cut = ckpt_dir / "checkpoint_epoch_1.pth"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    with pytest.raises(ValueError, match=f"checkpoint {cut} cannot be read .*truncated"):
        train.main(one_step_args(synthetic_root, tmp_path, "cut"))
    with pytest.raises(ValueError, match=f"checkpoint {cut} cannot be read"):
        model.load_params_from_file(cut)


@pytest.mark.slow
def test_staged_training_chains_through_train_py(synthetic_root, tmp_path):
    """PHiM+LOT's stages: stage 1 from a PHiM checkpoint, stage 2 from stage 1's run under the
    same --extra_tag (its frozen score MLP kept bit for bit), a missing predecessor an error."""
    train = load_tool("train")
    stages = REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "phim_lot"
    out = tmp_path / "output"

    def args(name, tag, *extra):
        return [
            "--cfg", str(stages / name), "--out_dir", str(out), "--extra_tag", tag,
            "--epochs", "1", "--batch_size", "2", "--workers", "0", "--no_progress",
            "--fix_random_seed", "--device", "cpu", *extra,
            "--set", "DATA_CONFIG.DATA_PATH", str(synthetic_root),
            "DATA_CONFIG.DATA_AUGMENTOR.DISABLE_AUG_LIST", "gt_sampling",
            "DATA_CONFIG.SAMPLED_INTERVAL", "train:5,test:5",
            "DATA_CONFIG.POINT_CLOUD_RANGE", "-20.48,-20.48,-2,20.48,20.48,4",
        ]  # fmt: skip

    phim_cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "phim.yaml")
    torch.manual_seed(3)
    phim = build_network_from_config(phim_cfg)
    torch.save({"model_state": phim.state_dict()}, tmp_path / "phim.pth")
    s1 = train.main(
        args("stage1_score.yaml", "chain", "--pretrained_model", str(tmp_path / "phim.pth"))
    )
    s2 = train.main(args("stage2_ssm.yaml", "chain"))
    w1 = torch.load(s1["output_dir"] / "ckpt" / "checkpoint_epoch_1.pth", weights_only=False)
    w2 = torch.load(s2["output_dir"] / "ckpt" / "checkpoint_epoch_1.pth", weights_only=False)
    m0, m1, m2 = phim.state_dict(), w1["model_state"], w2["model_state"]
    for k in m1:
        if k.startswith("vfe."):
            assert torch.equal(m0[k], m1[k]) and torch.equal(m1[k], m2[k]), k
        if k.startswith("lot.score_mlp."):
            assert torch.equal(m1[k], m2[k]), k  # frozen in stage 2
    assert any(not torch.equal(m1[k], m2[k]) for k in m1 if k.startswith("lot.convssm."))
    # stage 1 leaves the detector as PHiM left it
    assert all(torch.equal(m0[k], m1[k]) for k in m0 if k.startswith("backbone_3d."))
    with pytest.raises(SystemExit, match=r"stage2_ssm.*stage1_score"):
        train.main(args("stage2_ssm.yaml", "other"))


class Killed(Exception):
    """Stands for the job being killed."""


def kill_and_resume(monkeypatch, root, out, tag, kill_at_load, *flags):
    """Train 2 epochs with ``latest_model.pth`` rewritten after every step, kill the run while it
    loads batch ``kill_at_load``, and run the same command again. Returns the ckpt folder, the
    ``latest_model.pth`` the killed run left, and the resumed run's result."""
    from pcdet_atlas.train_utils import trainer

    to_device = trainer.load_data_to_device
    loads = []

    def load_or_die(batch, device):
        loads.append(batch["frame_id"])
        if len(loads) == kill_at_load:
            raise Killed
        return to_device(batch, device)

    monkeypatch.setattr(trainer, "load_data_to_device", load_or_die)
    args = ["--ckpt_save_time_interval", "0", *flags, *train_args(root, out, 2, tag)]
    train = load_tool("train")
    with pytest.raises(Killed):
        train.main(args)
    ckpt_dir = out / "atlas" / "synthetic" / "centerpoint" / tag / "ckpt"
    latest = torch.load(ckpt_dir / "latest_model.pth", weights_only=False)
    monkeypatch.undo()
    return ckpt_dir, latest, train.main(args)


def assert_same_training(a_path, b_path):
    a, b = (torch.load(p, weights_only=False) for p in (a_path, b_path))
    for k in a["model_state"]:
        assert torch.equal(a["model_state"][k], b["model_state"][k]), k
    assert a["optimizer_state"]["state"].keys() == b["optimizer_state"]["state"].keys()
    for k, v in a["optimizer_state"]["state"].items():
        assert all(torch.equal(v[s], b["optimizer_state"]["state"][k][s]) for s in v), k


@pytest.mark.slow
def test_training_killed_mid_epoch_resumes_from_latest_model_bit_exactly(
    synthetic_root, tmp_path, monkeypatch
):
    out = tmp_path / "output"
    full = load_tool("train").main(train_args(synthetic_root, out, 2, "full"))  # 2 steps/epoch

    # killed while loading its 4th batch: epoch 1 and the first batch of epoch 2 trained
    ckpt_dir, latest, resumed = kill_and_resume(monkeypatch, synthetic_root, out, "killed", 4)
    assert (latest["epoch"], latest["it"], latest["epoch_it"]) == (1, 3, 1)
    assert set(latest["epoch_loss_sums"]) == set(full["state"].history[-1])
    state = resumed["state"]  # went on with epoch 2's second batch
    assert (state.epoch, state.it, state.epoch_it) == (2, 4, 0)
    assert state.history == [full["state"].history[-1]]  # epoch 2's mean over both its batches
    assert sorted(p.name for p in ckpt_dir.iterdir()) == [
        "checkpoint_epoch_1.pth", "checkpoint_epoch_2.pth"
    ]  # fmt: skip
    assert_same_training(
        full["output_dir"] / "ckpt" / "checkpoint_epoch_2.pth", ckpt_dir / "checkpoint_epoch_2.pth"
    )


@pytest.mark.slow
def test_epoch_end_without_epoch_checkpoint_is_a_resume_point(
    synthetic_root, tmp_path, monkeypatch
):
    """With --ckpt_save_interval 2, epoch 1 writes no epoch checkpoint: latest_model.pth then
    records the epoch's end, not its last batch as pending (the last batch holds 1 of 3 frames:
    a position of 2 x 3 samples would lie past the epoch's 4)."""
    out = tmp_path / "output"
    batch3 = ("--batch_size", "3", "--ckpt_save_interval", "2")
    args = [*batch3, *train_args(synthetic_root, out, 2, "full")]
    full = load_tool("train").main(args)
    assert full["state"].it == 4  # 2 batches per epoch: 3 frames and 1

    # killed while loading its 3rd batch, the first of epoch 2
    ckpt_dir, latest, resumed = kill_and_resume(
        monkeypatch, synthetic_root, out, "killed", 3, *batch3
    )  # fmt: skip
    assert (latest["epoch"], latest["it"], latest["epoch_it"]) == (1, 2, 0)
    assert latest["epoch_loss_sums"] == {}
    assert (resumed["state"].epoch, resumed["state"].it) == (2, 4)
    assert resumed["state"].history == [full["state"].history[-1]]
    assert sorted(p.name for p in ckpt_dir.iterdir()) == ["checkpoint_epoch_2.pth"]
    assert_same_training(
        full["output_dir"] / "ckpt" / "checkpoint_epoch_2.pth", ckpt_dir / "checkpoint_epoch_2.pth"
    )


def test_resume_point_is_the_most_advanced_checkpoint(tmp_path):
    from pcdet_atlas.train_utils import find_resume_checkpoint

    model = torch.nn.Linear(2, 1)
    assert find_resume_checkpoint(tmp_path) is None
    for epoch in (1, 2):
        save_checkpoint(checkpoint_state(model, epoch=epoch, it=2 * epoch),
                        tmp_path / f"checkpoint_epoch_{epoch}.pth")  # fmt: skip
    latest = tmp_path / "latest_model.pth"
    save_checkpoint(checkpoint_state(model, epoch=2, it=5, epoch_it=1), latest)
    assert find_resume_checkpoint(tmp_path) == latest  # one batch into epoch 3
    # a run killed between writing epoch 3's checkpoint and removing latest_model.pth
    save_checkpoint(checkpoint_state(model, epoch=3, it=6), tmp_path / "checkpoint_epoch_3.pth")
    assert find_resume_checkpoint(tmp_path) == tmp_path / "checkpoint_epoch_3.pth"
    (tmp_path / "checkpoint_epoch_3.pth").unlink()
    (tmp_path / "checkpoint_epoch_2.pth").unlink()
    (tmp_path / "checkpoint_epoch_1.pth").unlink()
    assert find_resume_checkpoint(tmp_path) == latest
    torch.save({"model_state": model.state_dict()}, latest)  # weights only: no training state
    with pytest.raises(ValueError, match=r"latest_model\.pth has no 'epoch'"):
        find_resume_checkpoint(tmp_path)


class _ToyModel(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.linear = torch.nn.Linear(2, 1)

    def forward(self, batch):
        loss = self.linear(batch["x"]).square().mean()
        return {"loss": loss}, {"loss": float(loss.detach())}, {}


def test_checkpoint_rotation_removes_the_oldest_only_after_the_new_one_is_written(
    tmp_path, monkeypatch
):
    """With ``max_ckpt_save_num`` 1, a kill while epoch 2's checkpoint is written leaves epoch
    1's to resume from (the rotation used to delete it first)."""
    from pcdet_atlas.train_utils import find_resume_checkpoint, trainer

    model = _ToyModel()
    loader = torch.utils.data.DataLoader([{"x": torch.ones(2)}] * 2, batch_size=1)
    optimizer = torch.optim.SGD(model.parameters(), lr=0.1)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda _: 1.0)
    common = dict(
        total_epochs=1, device=torch.device("cpu"), seed=0, grad_norm_clip=10.0,
        ckpt_dir=tmp_path, max_ckpt_save_num=1, show_progress=False,
    )  # fmt: skip
    state = trainer.TrainState()
    trainer.train_model(model, optimizer, scheduler, loader, None, state=state, **common)
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint_epoch_1.pth"]

    def killed(state_dict, path):
        raise KeyboardInterrupt(f"killed while writing {path}")

    monkeypatch.setattr(trainer, "save_checkpoint", killed)
    with pytest.raises(KeyboardInterrupt, match="checkpoint_epoch_2"):
        trainer.train_model(
            model, optimizer, scheduler, loader, None, state=state, **dict(common, total_epochs=2)
        )
    assert find_resume_checkpoint(tmp_path) == tmp_path / "checkpoint_epoch_1.pth"
    monkeypatch.undo()
    resumed = trainer.TrainState(epoch=1, it=2)  # what a resume from epoch 1's checkpoint reads
    trainer.train_model(
        model, optimizer, scheduler, loader, None, state=resumed, **dict(common, total_epochs=2)
    )
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint_epoch_2.pth"]


@pytest.mark.parametrize("every,want", [(2, [2, 4, 5, 6, 8, 10]), (None, [5, 10])])
def test_cpu_training_trims_the_heap_every_n_steps_and_each_epoch(
    tmp_path, monkeypatch, every, want
):
    """On CPU the trainer gives free heap memory back every ``cpu_trim_every`` steps (the
    counts after which it trims; an epoch's last step trims at the epoch's end) and after every
    epoch: the heap that retain_freed_cpu_memory keeps is bounded by a few steps' peak
    (docs/benchmarks.md, "Training step")."""
    from pcdet_atlas.train_utils import trainer

    model = _ToyModel()
    loader = torch.utils.data.DataLoader([{"x": torch.ones(2)}] * 5, batch_size=1)
    optimizer = torch.optim.SGD(model.parameters(), lr=0.1)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda _: 1.0)
    state = trainer.TrainState()
    trims = []
    monkeypatch.setattr(trainer, "trim_cpu_memory", lambda: trims.append(state.it))
    trainer.train_model(
        model, optimizer, scheduler, loader, None, state=state, total_epochs=2,
        device=torch.device("cpu"), seed=0, grad_norm_clip=10.0, ckpt_dir=tmp_path,
        show_progress=False, cpu_trim_every=every,
    )  # fmt: skip
    assert trims == want


@pytest.mark.slow
def test_merged_epochs_train_as_many_steps_as_plain_epochs_and_resume_exactly(
    synthetic_root, tmp_path, monkeypatch
):
    """--merge_all_iters_to_one_epoch (OpenPCDet's semantics): the dataset is 2 passes long and
    each of the 2 epochs takes half of one shuffled pass over it, so the run trains the 4 steps
    of 2 plain epochs (4 frames, batch 2), each frame once per pass; a run killed mid-epoch 2
    goes on in the same pass to the same weights."""
    from pcdet_atlas.train_utils import trainer

    merge = "--merge_all_iters_to_one_epoch"
    out = tmp_path / "output"
    to_device = trainer.load_data_to_device
    frames = []

    def record(batch, device):
        frames.extend(batch["frame_id"])
        return to_device(batch, device)

    monkeypatch.setattr(trainer, "load_data_to_device", record)
    full = load_tool("train").main([merge, *train_args(synthetic_root, out, 2, "full")])
    monkeypatch.undo()
    assert (full["state"].epoch, full["state"].it) == (2, 4)  # as 2 plain epochs
    assert len(full["state"].history) == 2
    assert len(frames) == 8 and all(frames.count(f) == 2 for f in frames)
    last = torch.load(full["output_dir"] / "ckpt" / "checkpoint_epoch_2.pth", weights_only=False)
    assert last["scheduler_state"]["total_steps"] == last["scheduler_state"]["last_epoch"] == 4
    assert last["train_settings"]["merge_all_iters_to_one_epoch"] is True

    # killed while loading its 4th batch: epoch 1 and the first batch of epoch 2 trained
    ckpt_dir, latest, resumed = kill_and_resume(
        monkeypatch, synthetic_root, out, "killed", 4, merge
    )  # fmt: skip
    assert (latest["epoch"], latest["it"], latest["epoch_it"]) == (1, 3, 1)
    state = resumed["state"]
    assert (state.epoch, state.it, state.epoch_it) == (2, 4, 0)
    assert state.history == [full["state"].history[-1]]
    assert_same_training(
        full["output_dir"] / "ckpt" / "checkpoint_epoch_2.pth", ckpt_dir / "checkpoint_epoch_2.pth"
    )
    # a merged checkpoint does not resume as a plain run (same step count, another data order)
    with pytest.raises(ValueError, match=r"merge_all_iters_to_one_epoch: True -> False"):
        load_tool("train").main(train_args(synthetic_root, out, 2, "killed"))


def test_resume_with_another_seed_process_setup_or_config_is_refused_before_loading(
    synthetic_root, tmp_path
):
    """The seed, --use_amp and the merged DATA_CONFIG / MODEL are part of what a checkpoint
    records: another value is refused naming the setting, both values and the checkpoint, before
    any state is loaded (a MODEL with other shapes does not get as far as the weights)."""
    train = load_tool("train")
    run_dir = train.main(one_step_args(synthetic_root, tmp_path, "run"))["output_dir"]
    ckpt = run_dir / "ckpt" / "checkpoint_epoch_1.pth"
    settings = torch.load(ckpt, weights_only=False)["train_settings"]
    assert settings["seed"] == 666 and settings["processes"] == 1
    assert settings["use_amp"] is False and settings["sync_bn"] is False
    assert set(settings["config_sha256"]) == {"CLASS_NAMES", "DATA_CONFIG", "MODEL"}

    with pytest.raises(ValueError, match=r"seed: 666 -> 7") as exc:
        train.main(["--seed", "7", *one_step_args(synthetic_root, tmp_path, "run")])
    assert str(ckpt) in str(exc.value)
    with pytest.raises(ValueError, match=r"use_amp: False -> True"):
        train.main(["--use_amp", *one_step_args(synthetic_root, tmp_path, "run")])
    with pytest.raises(ValueError, match=r"config_sha256\.DATA_CONFIG: '[0-9a-f]{64}' -> '"):
        train.main(one_step_args(synthetic_root, tmp_path, "run",
                                 "DATA_CONFIG.FILTER_EMPTY_BOXES_FOR_TRAIN", "False"))  # fmt: skip
    with pytest.raises(ValueError, match=r"config_sha256\.MODEL: ") as exc:
        train.main(one_step_args(synthetic_root, tmp_path, "run",
                                 "MODEL.BACKBONE_2D.NUM_FILTERS", "32,64,96"))  # fmt: skip
    assert "DATA_CONFIG" not in str(exc.value)
    # the dataset's folder is not part of it: a moved dataset resumes (here: a finished run)
    moved = tmp_path / "moved_data"
    shutil.copytree(synthetic_root, moved)
    again = train.main(one_step_args(moved, tmp_path, "run"))
    assert (again["state"].epoch, again["state"].it) == (1, 1)


def strip_to_old_format(path):
    """Rewrite ``path`` as a checkpoint of the code before the seed, process count, AMP, SyncBN,
    merge flag, config digests and CUDA generator states were recorded."""
    ckpt = torch.load(path, weights_only=False)
    settings = ckpt["train_settings"]
    ckpt["train_settings"] = {k: settings[k] for k in ("OPTIMIZATION", "batch_size")}
    del ckpt["cuda_rng_state"]
    torch.save(ckpt, path)


@pytest.mark.slow
def test_checkpoint_without_the_newer_settings_resumes_bit_exactly(synthetic_root, tmp_path):
    """What an older checkpoint does not record is not compared: it resumes (even with another
    --seed, which it cannot know) and, with the same arguments, ends as the uninterrupted run."""
    train = load_tool("train")
    out = tmp_path / "output"
    args = one_step_args(synthetic_root, out, "full")
    args[args.index("--epochs") + 1] = "2"
    full = train.main(args)
    old_dir = out / "atlas" / "synthetic" / "centerpoint" / "old" / "ckpt"
    old_dir.mkdir(parents=True)
    shutil.copy(full["output_dir"] / "ckpt" / "checkpoint_epoch_1.pth", old_dir)
    strip_to_old_format(old_dir / "checkpoint_epoch_1.pth")
    args[args.index("--extra_tag") + 1] = "old"
    resumed = train.main(args)
    assert (resumed["state"].epoch, resumed["state"].it) == (2, 2)
    assert len(resumed["state"].history) == 1
    assert_same_training(
        full["output_dir"] / "ckpt" / "checkpoint_epoch_2.pth", old_dir / "checkpoint_epoch_2.pth"
    )
    written = torch.load(old_dir / "checkpoint_epoch_2.pth", weights_only=False)
    assert written["train_settings"]["seed"] == 666  # what it writes from now on records them


@pytest.mark.parametrize(
    "key, value, expected",
    [("GRAD_NORM_CLIP", "-1", "a number > 0"), ("PCT_START", "1.0", "between 0 and 1"),
     ("PCT_START", "0.0", "between 0 and 1"), ("MOMS", "0.95", "two numbers in \\[0, 1\\)"),
     ("MOMS", "0.95,1.5", "two numbers in \\[0, 1\\)"), ("DIV_FACTOR", "0", "a number > 0"),
     ("OPTIMIZER", "adamw", "one of adam_onecycle")],
)  # fmt: skip
def test_bad_optimization_values_are_config_errors_before_anything_is_written(
    synthetic_root, tmp_path, key, value, expected
):
    from pcdet_atlas.config import ConfigError

    train = load_tool("train")
    args = one_step_args(synthetic_root, tmp_path, "bad", f"OPTIMIZATION.{key}", value)
    with pytest.raises(ConfigError, match=rf"OPTIMIZATION\.{key} = .* \(from --set\)") as exc:
        train.main(args)
    assert expected.replace("\\", "") in str(exc.value)
    assert not (tmp_path / "atlas").exists()


def test_missing_grad_norm_clip_names_the_key_and_the_file(synthetic_root, tmp_path):
    from pcdet_atlas.config import ConfigError, save_config

    cfg = cfg_from_yaml_file(CFG)
    del cfg.OPTIMIZATION["GRAD_NORM_CLIP"]
    cfg_file = save_config(cfg, tmp_path / "no_clip.yaml")
    args = one_step_args(synthetic_root, tmp_path / "out", "bad")
    args[args.index("--cfg") + 1] = str(cfg_file)
    with pytest.raises(
        ConfigError, match=r"missing required key OPTIMIZATION\.GRAD_NORM_CLIP"
    ) as e:
        load_tool("train").main(args)
    assert str(cfg_file) in str(e.value)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("flag", ["--ckpt", "--pretrained_model"])
def test_missing_checkpoint_file_is_an_error_before_the_model_is_built(
    synthetic_root, tmp_path, monkeypatch, flag
):
    train = load_tool("train")

    def never(*args, **kwargs):
        raise AssertionError("built before the checkpoint was checked")

    monkeypatch.setattr(train, "build_dataloader", never)
    monkeypatch.setattr(train, "build_network_from_config", never)
    missing = tmp_path / "nope.pth"
    with pytest.raises(FileNotFoundError, match=f"{flag} {missing}: no such checkpoint file"):
        train.main([flag, str(missing), *one_step_args(synthetic_root, tmp_path, "x")])
    assert not (tmp_path / "atlas").exists()


def test_every_shipped_training_config_passes_the_optimization_checks():
    from pcdet_atlas.models.optimization import check_optimization_config

    configs = sorted((REPO_ROOT / "cfgs" / "atlas").rglob("*.yaml"))
    assert len(configs) > 10
    for path in configs:
        check_optimization_config(cfg_from_yaml_file(path).OPTIMIZATION)


def test_cpu_evaluation_trims_the_heap_every_20_batches(monkeypatch):
    """predict_dataset gives free heap memory back every TRIM_EVERY_BATCHES batches on CPU
    (tools/test.py keeps freed memory for reuse, which fragmentation would otherwise grow)."""
    from pcdet_atlas.train_utils import eval_utils

    class Frames(torch.utils.data.Dataset):
        class_names = ["Vehicle"]
        infos = [{"frame_id": f"f{i}"} for i in range(45)]

        def __len__(self):
            return len(self.infos)

        def __getitem__(self, i):
            return {"frame_id": self.infos[i]["frame_id"], "x": torch.ones(1)}

        def generate_prediction_dicts(self, batch, pred_dicts, class_names):
            return [{"frame_id": f} for f in batch["frame_id"]]

    class Model(torch.nn.Module):
        def stored_predict(self, batch):
            return [{} for _ in batch["frame_id"]]

    def collate(samples):
        return {
            "frame_id": [s["frame_id"] for s in samples],
            "x": torch.stack([s["x"] for s in samples]),
        }

    trims = []
    loader = torch.utils.data.DataLoader(Frames(), batch_size=1, collate_fn=collate)
    monkeypatch.setattr(eval_utils, "trim_cpu_memory", lambda: trims.append(len(trims)))
    annos, _ = eval_utils.predict_dataset(Model(), loader, device=torch.device("cpu"),
                                          show_progress=False)  # fmt: skip
    assert [a["frame_id"] for a in annos] == [f"f{i}" for i in range(45)]
    assert eval_utils.TRIM_EVERY_BATCHES == 20 and len(trims) == 2  # after batches 20 and 40
