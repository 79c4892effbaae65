"""retain_freed_cpu_memory: freed large blocks are reused without faulting pages in again."""

import subprocess
import sys
import textwrap

import pytest

from pcdet_atlas.config import REPO_ROOT

CHILD = textwrap.dedent(
    """
    import resource, sys
    import torch
    from pcdet_atlas.train_utils import retain_freed_cpu_memory

    retained = retain_freed_cpu_memory() if sys.argv[1] == "retain" else False
    n = 64 * 2**20  # 256 MB of float32, 65536 pages of 4 KiB

    def faults_of_one_step():
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        x = torch.empty(n)
        x.fill_(1.0)  # touch every page
        del x
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

    faults_of_one_step()  # the first steps grow the heap (fault their memory in) either way
    faults_of_one_step()
    print(retained, faults_of_one_step())
    """
)


def run_child(mode: str) -> tuple[bool, int]:
    out = subprocess.run(
        [sys.executable, "-c", CHILD, mode],
        cwd=REPO_ROOT, check=True, capture_output=True, text=True,
    )  # fmt: skip
    retained, faults = out.stdout.split()
    return retained == "True", int(faults)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt: Linux only")
def test_retained_memory_is_reused_without_page_faults():
    retained, faults = run_child("retain")
    if not retained:
        pytest.skip("no glibc mallopt in this C library")
    _, faults_default = run_child("default")
    pages = 64 * 2**20 * 4 // 4096
    assert faults < 0.1 * pages  # the second 256 MB block reuses the first one's pages
    assert faults_default > 0.5 * pages  # glibc's default unmaps it and faults it in again
