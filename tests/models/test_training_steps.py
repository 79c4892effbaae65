import pytest
import torch
from easydict import EasyDict
from model_batches import make_batch

from pcdet_atlas.config import REPO_ROOT, ConfigError, cfg_from_yaml_file
from pcdet_atlas.models import build_network
from pcdet_atlas.models.optimization import build_optimizer, build_scheduler


def tiny_cp4f():
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "cp4f.yaml")
    return build_network(
        cfg.MODEL,
        class_names=cfg.CLASS_NAMES,
        point_cloud_range=[-20.48, -20.48, -2.0, 20.48, 20.48, 4.0],
        num_point_features=6,
    )


def test_a_few_steps_lower_the_loss():
    torch.manual_seed(0)
    model = tiny_cp4f().train()
    batch = make_batch(num_point_features=6, with_velocity=True)
    optim = torch.optim.AdamW(model.parameters(), lr=3e-3, betas=(0.9, 0.99))
    history = []
    for _ in range(8):
        optim.zero_grad()
        losses = model.loss(batch)
        losses["loss"].backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10)
        optim.step()
        history.append({k: float(v.detach()) for k, v in losses.items()})
    assert history[-1]["loss"] < 0.7 * history[0]["loss"]
    assert history[-1]["hm_loss"] < history[0]["hm_loss"]
    assert history[-1]["loc_loss"] < history[0]["loc_loss"]


def test_onecycle_schedule_shape_and_resume():
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "atlas" / "centerpoint.yaml").OPTIMIZATION
    model = torch.nn.Linear(2, 2)

    def make():
        opt = build_optimizer(model, cfg)
        return opt, build_scheduler(opt, cfg, iters_per_epoch=10, total_epochs=10)

    opt, sched = make()
    lrs, betas = [], []
    for _ in range(100):
        lrs.append(opt.param_groups[0]["lr"])
        betas.append(opt.param_groups[0]["betas"][0])
        opt.step()
        sched.step()
    assert isinstance(opt, torch.optim.AdamW) and opt.param_groups[0]["weight_decay"] == 0.01
    assert lrs[0] == pytest.approx(0.003 / 10)
    assert max(lrs) == pytest.approx(0.003, rel=1e-3) and lrs.index(max(lrs)) in (39, 40)
    assert (
        lrs[-1] < 1e-5
        and betas[0] == pytest.approx(0.95)
        and min(betas) == pytest.approx(0.85, abs=1e-3)
    )
    # a scheduler restored from its state dict continues identically
    opt2, sched2 = make()
    opt, sched = make()
    for _ in range(37):
        opt.step()
        sched.step()
    opt2.load_state_dict(opt.state_dict())
    sched2.load_state_dict(sched.state_dict())
    for _ in range(20):
        for o, s in ((opt, sched), (opt2, sched2)):
            o.step()
            s.step()
        assert opt.param_groups[0]["lr"] == opt2.param_groups[0]["lr"]


def test_step_decay_and_bad_optimizer():
    run = {"BATCH_SIZE_PER_GPU": 1, "NUM_EPOCHS": 6, "GRAD_NORM_CLIP": 10}
    cfg = EasyDict(
        OPTIMIZER="adam", LR=0.01, DECAY_STEP_LIST=[2, 4], LR_DECAY=0.1, LR_CLIP=1e-4,
        LR_WARMUP=False, **run,
    )  # fmt: skip
    opt = build_optimizer(torch.nn.Linear(2, 2), cfg)
    sched = build_scheduler(opt, cfg, iters_per_epoch=5, total_epochs=6)
    lrs = []
    for _ in range(30):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert lrs[0] == pytest.approx(0.01) and lrs[10] == pytest.approx(0.001)
    assert lrs[25] == pytest.approx(1e-4)  # 1e-4 by decay and by clip
    with pytest.raises(ConfigError, match="'rmsprop'"):
        build_optimizer(torch.nn.Linear(2, 2), EasyDict(OPTIMIZER="rmsprop", LR=0.1, **run))
    with pytest.raises(ConfigError, match="unknown key 'LR_MAX'"):
        build_optimizer(torch.nn.Linear(2, 2), EasyDict(OPTIMIZER="adam", LR=0.1, LR_MAX=1, **run))
