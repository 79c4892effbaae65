"""Children started with die_with_parent do not outlive their parent (tools/reproduce.py)."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

PARENT = """
import subprocess, sys
from pcdet_atlas.utils.processes import die_with_parent
child = subprocess.Popen(["sleep", "60"], preexec_fn=die_with_parent())
print(child.pid, flush=True)
child.wait()
"""


def running(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie no reaper collected counts as gone)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl(PR_SET_PDEATHSIG)")
def test_a_child_dies_when_its_parent_is_killed():
    assert_child_dies_with_it(PARENT, "the child outlived its killed parent")


def assert_child_dies_with_it(script: str, message: str) -> None:
    """Run ``script`` (it prints a child's pid), SIGKILL it, and check the child ends within 5 s."""
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    child = int(parent.stdout.readline())
    try:
        assert running(child)
        parent.kill()  # SIGKILL: the parent cleans up nothing
        parent.wait()
        deadline = time.monotonic() + 5
        while running(child) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert not running(child), message
    finally:
        if running(child):
            os.kill(child, signal.SIGKILL)


LOADER = """
import time
import numpy as np
from torch.utils.data import DataLoader, Dataset
from pcdet_atlas.datasets import worker_init_fn

class Slow(Dataset):
    def __len__(self):
        return 1000
    def __getitem__(self, i):
        time.sleep(0.05)
        return {"points": np.zeros(1 << 18, np.float32)}  # pickled through the pipe: 1 MiB

def collate(samples):  # numpy, as the datasets' collate_batch: sent through the pipe
    return samples

loader = DataLoader(Slow(), batch_size=4, num_workers=1, worker_init_fn=worker_init_fn,
                    collate_fn=collate)
it = iter(loader)
next(it)
print(it._workers[0].pid, flush=True)
time.sleep(60)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl(PR_SET_PDEATHSIG)")
def test_a_loader_worker_dies_when_its_process_is_killed():
    """A worker tied by worker_init_fn leaves with its killed process; without it, one blocked
    handing over a batch would stay, holding the output folder's lock it inherited."""
    assert_child_dies_with_it(LOADER, "the loader worker outlived its killed process")
