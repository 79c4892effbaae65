import numpy as np
import pytest
import torch

from pcdet_atlas.attacks.counters import COUNTERS, AttackCounters
from pcdet_atlas.attacks.schedule import (
    is_spoofed,
    lifecycle_frames,
    lifecycle_of_frame,
    lifecycle_positions,
    num_runs,
    run_bounds,
    run_of_frame,
    schedule_runs,
    spoof_schedule,
)


@pytest.mark.parametrize("window", [1, 3, 8, 32])
@pytest.mark.parametrize("num_frames", [0, 1, 5, 31, 32, 33, 64, 70, 198, 200])
def test_schedule_equals_formula(num_frames, window):
    s = spoof_schedule(num_frames, window)
    assert s.dtype == bool and s.shape == (num_frames,)
    expected = [i >= 1 and (i // window) % 2 == 1 for i in range(num_frames)]
    assert s.tolist() == expected
    assert [is_spoofed(i, window) for i in range(num_frames)] == expected
    runs = schedule_runs(s)
    assert len(runs) == num_runs(num_frames, window)
    for r, (a, b) in enumerate(runs):
        assert run_bounds(r, num_frames, window) == (a, b)
        for i in range(a, b + 1):
            assert run_of_frame(i, num_frames, window) == (r, i - a)
    for i in np.flatnonzero(~s):
        assert run_of_frame(int(i), num_frames, window) == (-1, -1)


def test_waymo_sequence_runs():
    s = spoof_schedule(198)
    assert schedule_runs(s) == [(32, 63), (96, 127), (160, 191)]
    assert not s[0] and s[32] and not s[64] and s[191] and not s[192]
    assert run_of_frame(100, 198) == (1, 4)
    # a short sequence truncates its only run
    assert schedule_runs(spoof_schedule(50)) == [(32, 49)]
    assert schedule_runs(spoof_schedule(32)) == []
    assert schedule_runs(spoof_schedule(10, window=4)) == [(4, 7)]


def test_schedule_runs_of_any_schedule():
    assert schedule_runs([True, True, False, True]) == [(0, 1), (3, 3)]
    assert schedule_runs(torch.tensor([False, True, True])) == [(1, 2)]
    assert schedule_runs([]) == []


def test_lifecycle_positions():
    W, n = 32, 198
    assert lifecycle_positions(31, n) == [(0, 0)]
    assert lifecycle_positions(32, n) == [(0, 1)]
    assert lifecycle_positions(63, n) == [(0, 32)]
    assert lifecycle_positions(64, n) == [(0, 33)]
    # the frame before the next onset closes the previous run's tail
    assert lifecycle_positions(95, n) == [(0, 2 * W), (1, 0)]
    assert lifecycle_of_frame(95, n) == (1, 0)
    assert lifecycle_positions(30, n) == [] and lifecycle_of_frame(0, n) == (-1, -1)
    assert lifecycle_positions(197, n) == [(2, 38)]
    frames = lifecycle_frames(0, n)
    assert frames[0] == (31, 0) and frames[-1] == (95, 64) and len(frames) == 2 * W + 1
    assert lifecycle_frames(2, n)[-1] == (197, 38)
    # consistent with lifecycle_frames for every run, small window
    n, W = 23, 3
    members = {}
    for r in range(num_runs(n, W)):
        for i, k in lifecycle_frames(r, n, W):
            members.setdefault(i, []).append((r, k))
    for i in range(n):
        assert lifecycle_positions(i, n, W) == members.get(i, [])


def test_schedule_bad_input():
    with pytest.raises(ValueError, match="window"):
        spoof_schedule(10, window=0)
    with pytest.raises(ValueError, match="num_frames"):
        spoof_schedule(-1)
    with pytest.raises(ValueError, match="outside"):
        run_of_frame(10, 10)
    with pytest.raises(ValueError, match="run_id"):
        run_bounds(3, 198)


def test_counters():
    c = AttackCounters()
    c.add(frames_simulated=2, bins_touched=5)
    with c.measure() as work:
        c.add(frames_simulated=1)
        with c.measure() as inner:
            c.add(dual_draws=3)
    assert work["frames_simulated"] == 1 and work["dual_draws"] == 3
    assert inner["frames_simulated"] == 0 and inner["dual_draws"] == 3
    snap = c.snapshot()
    assert snap["frames_simulated"] == 3 and snap["bins_touched"] == 5
    c.reset()
    assert set(c.snapshot().values()) == {0}
    with pytest.raises(KeyError, match="unknown attack counter"):
        c.add(frame_simulated=1)
    with pytest.raises(ValueError, match="counter 'frames_simulated' increment must be >= 0"):
        c.add(frames_simulated=-1)
    assert isinstance(COUNTERS, AttackCounters)


def test_attack_schedule_state_memo_keeps_the_checks():
    """``BaseAttack.schedule_state`` is memoised per (frame, num_frames): repeated asks give the
    same state as the schedule functions, and bad arguments still fail after a valid ask."""
    from pcdet_atlas.attacks.base import BaseAttack

    class Scheduled(BaseAttack):  # the schedule of every family; no physics
        prepare_run = attack_frame = shadow_meta = None

    attack = Scheduled("scheduled", window=32)
    for frame in (0, 31, 32, 63, 64, 197):
        for _ in range(2):
            state = attack.schedule_state(frame, 198)
            assert (state.run_id, state.run_position) == (
                run_of_frame(frame, 198, 32) if state.spoofed else (state.run_id, -1)
            )
            assert state.spoofed == is_spoofed(frame, 32)
    for bad in (True, 1.5, 198, -1):
        with pytest.raises(ValueError, match=f"frame index .*{bad!r}"):
            attack.schedule_state(bad, 198)
