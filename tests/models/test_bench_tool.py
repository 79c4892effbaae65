"""tools/bench/bench_models.py end to end on the tiny synthetic dataset, at the smallest sizes: the
latency table (a shipped model and a real-Waymo two-stage config whose RPN is not trained here),
the test-step shares of the three attack families, PTT with and without its proposal bank,
selective_scan against its loop, and the sparse conv layers of a voxel backbone. The figures
are not checked, only that every table is complete and its numbers are sane."""

import re
import subprocess
import sys

import pytest

from pcdet_atlas.config import REPO_ROOT

pytestmark = pytest.mark.slow


def table(out: str, header_start: str) -> list[list[str]]:
    """The rows (cells stripped) of the Markdown table whose header begins ``header_start``."""
    lines = out.splitlines()
    starts = [i for i, line in enumerate(lines) if line.startswith(header_start)]
    assert len(starts) == 1, f"no single table headed {header_start!r} in:\n{out}"
    rows = []
    for line in lines[starts[0] + 2 :]:
        if not line.startswith("|"):
            break
        rows.append([cell.strip() for cell in line.strip().strip("|").split("|")])
    return rows


def number(cell: str) -> float:
    return float(re.match(r"[\d,.e+-]+", cell).group().replace(",", ""))


def test_every_table_is_complete(synthetic_root):
    cmd = [
        sys.executable, str(REPO_ROOT / "tools" / "bench" / "bench_models.py"),
        "--cfgs", "cfgs/atlas/synthetic/centerpoint.yaml", "cfgs/atlas/msf_4f.yaml",
        "--data_path", str(synthetic_root), "--frames", "1", "--threads", "1",
        "--share_cfg", "cfgs/atlas/synthetic/centerpoint.yaml", "--share_frames", "1",
        "--bank_cfg", "cfgs/atlas/synthetic/ptt_32f.yaml", "--bank_frames", "3",
        "--ssm", "--ssm_lengths", "32",
        "--spconv", "cfgs/atlas/synthetic/cp4f_voxel.yaml", "--spconv_crop", "8",
        "--spconv_frame", "3",
    ]  # fmt: skip
    proc = subprocess.run(cmd, cwd=REPO_ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout

    latency = table(out, "| config | params (M)")
    assert [r[0] for r in latency] == ["atlas/synthetic/centerpoint.yaml", "atlas/msf_4f.yaml"]
    cp = latency[0]
    assert number(cp[1]) == pytest.approx(0.86, abs=0.01)  # the synthetic CenterPoint's size
    assert number(cp[2]) > 1000 and number(cp[3]) > 0 and number(cp[6]) > 0
    assert cp[7] == "trained (pass --eval)"  # its checkpoint ships
    assert latency[1][1].startswith("not built: MODEL.RPN.CHECKPOINT")

    shares = table(out, "| variant | data loading")
    assert [r[0] for r in shares] == ["clean", "inj_global_hard", "rem_40"]
    for row in shares:
        assert sum(number(c) for c in row[1:5]) == pytest.approx(100, abs=3), row
        assert number(row[5]) > 0

    bank = table(out, "| proposals | RPN passes")
    # frame t's window holds t previous frames: one RPN pass per frame with the bank, t + 1
    # without it (1 + 2 + 3)
    assert [(r[0], r[1]) for r in bank] == [("bank", "3"), ("no bank", "6")]
    assert all(number(r[3]) > 0 for r in bank)

    scan = table(out, "| l | pass | chunked ms")
    assert [(r[0], r[1]) for r in scan] == [("32", "forward"), ("32", "forward + backward")]
    assert all(number(r[5]) < 1e-4 for r in scan), scan  # chunked scan == the loop

    layers = table(out, "| layer | kind")
    assert len(layers) == 21  # VoxelResBackBone8x's sparse convs
    assert layers[0][:2] == ["conv_input.0", "subm 3x3x3"]
    assert [r[0] for r in layers if r[1].startswith("spconv")] == [
        "conv2.0.0", "conv3.0.0", "conv4.0.0", "conv_out.0",
    ]  # fmt: skip
    assert all(number(r[6]) > 0 and number(r[8]) > 0 for r in layers)
    assert "whole backbone forward" in out
