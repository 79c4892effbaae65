"""retain_freed_cpu_memory: freed large blocks stay in the process for reuse."""

import subprocess
import sys
import textwrap

import pytest

from pcdet_atlas.config import REPO_ROOT

CHILD = textwrap.dedent(
    """
    import sys
    import torch
    from pcdet_atlas.train_utils.cpu_memory import retain_freed_cpu_memory, trim_cpu_memory

    def rss_mib():
        for line in open("/proc/self/status"):
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024

    retained = retain_freed_cpu_memory() if sys.argv[1] == "retain" else False
    x = torch.empty(64 * 2**20)  # 256 MiB of float32
    x.fill_(1.0)  # fault every page in
    before = rss_mib()
    del x
    kept = before - rss_mib()
    trim_cpu_memory()
    print(retained, kept, before - rss_mib())
    """
)


def released_mib(mode: str) -> tuple[bool, float, float]:
    """MiB of resident memory a process gives back when it frees a 256 MiB tensor, and after
    a ``trim_cpu_memory()`` that follows."""
    out = subprocess.run(
        [sys.executable, "-c", CHILD, mode],
        cwd=REPO_ROOT, check=True, capture_output=True, text=True,
    )  # fmt: skip
    retained, released, after_trim = out.stdout.split()
    return retained == "True", float(released), float(after_trim)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt: Linux only")
def test_freed_memory_stays_resident_for_reuse():
    retained, released, after_trim = released_mib("retain")
    if not retained:
        pytest.skip("no glibc mallopt in this C library")
    _, released_default, _ = released_mib("default")
    assert released < 16  # kept: the next step reuses these pages without faulting them in
    assert after_trim > 240  # trim_cpu_memory (once per epoch in the trainer) gives it back
    assert released_default > 240  # glibc's default unmaps the block at once
