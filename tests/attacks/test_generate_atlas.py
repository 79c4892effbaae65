"""tools/data/generate_atlas.py refuses an --out_dir that would overwrite its own source dataset and
writes per-LiDAR row counts that match the written frames."""

import hashlib
import re

import numpy as np
import pytest
from atlas_helpers import load_tool, write_tiny_waymo
from malicious_files import malicious_pickle

from pcdet_atlas.attacks.lidar_fit import top_lidar_points
from pcdet_atlas.config import REPO_ROOT
from pcdet_atlas.datasets import waymo_format as wf
from pcdet_atlas.utils.common import save_pickle
from pcdet_atlas.utils.paths import UnsafePathError
from pcdet_atlas.utils.safe_pickle import RefusedGlobalError, load_pickle

ATTACKS = REPO_ROOT / "cfgs" / "attacks"


def tree_digest(root):
    """``{relative path: sha1}`` of every file under ``root``."""
    return {
        str(p.relative_to(root)): hashlib.sha1(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture
def source(tmp_path):
    root = write_tiny_waymo(tmp_path / "data" / "tiny", frames={"train": 2, "val": 3})
    cfg_path = tmp_path / "data.yaml"
    cfg_path.write_text(
        f"_BASE_CONFIG_: {REPO_ROOT / 'cfgs/dataset_configs/synthetic_waymo.yaml'}\n"
        f"DATA_PATH: {root}\n"
    )
    return root, cfg_path


def gen_args(cfg_path, out_dir):
    return ["--data_cfg", str(cfg_path), "--attack", str(ATTACKS / "clean.yaml"), "--out_dir",
            str(out_dir)]  # fmt: skip


@pytest.mark.parametrize("where", ["same", "inside", "contains", "symlink", "symlink_inside"])
def test_out_dir_overlapping_the_source_is_refused(source, tmp_path, where):
    root, cfg_path = source
    link = tmp_path / "link"
    link.symlink_to(root, target_is_directory=True)
    out_dir = {
        "same": root,
        "inside": root / "atlas" / "clean",
        "contains": root.parent,
        "symlink": link,
        "symlink_inside": link / "waymo_processed_data_v0_5_0",
    }[where]
    before = tree_digest(root)
    relation = {"contains": "contains", "inside": "lies inside", "symlink_inside": "lies inside"}
    with pytest.raises(ValueError, match=f"--out_dir .* {relation.get(where, 'is')} the source"):
        load_tool("data/generate_atlas").main(gen_args(cfg_path, out_dir))
    assert tree_digest(root) == before
    assert not (root / "atlas").exists() and not (root / "atlas_attack.yaml").exists()


def test_out_dir_beside_the_source_is_written(source, tmp_path):
    root, cfg_path = source
    out_dir = tmp_path / "data" / "tiny_clean"  # a sibling whose name starts like the source's
    load_tool("data/generate_atlas").main(gen_args(cfg_path, out_dir))
    assert (out_dir / "atlas_attack_metadata.pkl").is_file()
    assert sorted(p.name for p in (out_dir / "ImageSets").iterdir()) == ["val.txt"]


def test_relative_out_dir_is_read_from_the_working_directory(source, tmp_path, monkeypatch):
    root, cfg_path = source
    monkeypatch.chdir(tmp_path / "data")
    load_tool("data/generate_atlas").main(gen_args(cfg_path, "tiny_clean"))
    assert (tmp_path / "data" / "tiny_clean" / "atlas_attack_metadata.pkl").is_file()
    with pytest.raises(ValueError, match="lies inside the source"):  # relative to the cwd too
        load_tool("data/generate_atlas").main(gen_args(cfg_path, "tiny/atlas"))


@pytest.mark.parametrize("variant", ["inj_rel_hard", "rem_60"])
def test_lidar_counts_sum_to_the_written_rows(tmp_path, variant):
    """``num_points_of_each_lidar`` of a written frame counts the rows kept of each LiDAR, the
    phantom rows in the TOP count: the counts sum to the frame's rows, and the TOP rows are
    found again (a source whose last 800 rows are the FRONT LiDAR's)."""
    root = write_tiny_waymo(tmp_path / "src", frames={"train": 6, "val": 40})
    seq = "segment-tinyval_with_camera_labels"
    pkl = wf.sequence_pkl_path(root, seq)
    infos = wf.load_sequence_infos(pkl)
    for info in infos:
        info["num_points_of_each_lidar"] = [info["num_points_of_each_lidar"][0] - 800, 800, 0, 0, 0]
    wf.save_sequence_infos(pkl, infos)
    cfg_path = tmp_path / "data.yaml"
    cfg_path.write_text(
        f"_BASE_CONFIG_: {REPO_ROOT / 'cfgs/dataset_configs/synthetic_waymo.yaml'}\n"
        f"DATA_PATH: {root}\n"
    )
    attack = ["--attack", str(ATTACKS / f"{variant}.yaml")]
    fewer = ["--set", "TRACE_LIBRARY.MIN_POINTS", "100"] if variant.startswith("inj") else []
    if fewer:
        load_tool("data/build_trace_library").main(
            ["--cfg", attack[1], "--data_path", str(root), *fewer]
        )
    out = tmp_path / "out"
    load_tool("data/generate_atlas").main(
        ["--data_cfg", str(cfg_path), *attack, "--out_dir", str(out), *fewer]
    )
    written = wf.load_sequence_infos(wf.sequence_pkl_path(out, seq))
    changed = 0
    for k in range(32, 40):  # the spoofed frames
        src = wf.load_frame_points(wf.frame_npy_path(root, seq, k))
        rows = wf.load_frame_points(wf.frame_npy_path(out, seq, k))
        front = {r.tobytes() for r in src[-800:]}
        is_front = np.array([r.tobytes() in front for r in rows])
        counts = written[k]["num_points_of_each_lidar"]
        assert counts == [int((~is_front).sum()), int(is_front.sum()), 0, 0, 0]
        top = top_lidar_points(rows, written[k], "f")
        assert sorted(r.tobytes() for r in top) == sorted(r.tobytes() for r in rows[~is_front])
        changed += len(rows) != len(src)
    assert changed > 0
    if variant.startswith("rem"):
        assert any(c["num_points_of_each_lidar"][1] < 800 for c in written[32:40])


def test_a_rerun_refuses_attack_metadata_that_would_run_code(source, tmp_path):
    """A rerun reads each finished sequence's ``<seq>_atlas.pkl`` (to skip it) with the
    restricted unpickler."""
    root, cfg_path = source
    out_dir = tmp_path / "out"
    load_tool("data/generate_atlas").main(gen_args(cfg_path, out_dir))
    (meta,) = wf.data_dir(out_dir).glob("*/*_atlas.pkl")
    marker = tmp_path / "marker"
    malicious_pickle(meta, marker)
    with pytest.raises(RefusedGlobalError, match=rf"{meta}: refused to unpickle the global "):
        load_tool("data/generate_atlas").main(gen_args(cfg_path, out_dir))
    assert not marker.exists()


def test_a_rerun_names_attack_metadata_that_is_not_the_tools(source, tmp_path):
    """A finished sequence's ``<seq>_atlas.pkl`` that is no dict, or whose frames are not a
    dict of dict records, is an error naming the file (``saved.get`` of a list was a bare
    AttributeError)."""
    root, cfg_path = source
    out_dir = tmp_path / "out"
    load_tool("data/generate_atlas").main(gen_args(cfg_path, out_dir))
    (meta,) = wf.data_dir(out_dir).glob("*/*_atlas.pkl")
    saved = load_pickle(meta)
    (frame, record), *_ = saved["frames"].items()
    for bad, message in [
        ([saved], r"expected a dict, as this tool writes it, got list"),
        ({**saved, "frames": list(saved["frames"])}, r"'frames' is a list, expected a dict"),
        (
            {**saved, "frames": {frame: list(record)}},
            rf"'frames'\[{re.escape(repr(frame))}\] is a list",
        ),
    ]:
        save_pickle(bad, meta)
        with pytest.raises(ValueError, match=rf"{re.escape(str(meta))}: {message}"):
            load_tool("data/generate_atlas").main(gen_args(cfg_path, out_dir))


def test_a_resumed_out_dir_with_planted_symlinks_writes_nothing_through_them(source, tmp_path):
    """A received ``--out_dir`` to resume: a symlink at a file name the tool writes is replaced
    (its target keeps its content); a sequence folder or ``ImageSets/`` that is a symlink
    leading out of ``--out_dir`` is refused, naming it, before anything is written there."""
    root, cfg_path = source
    out_dir = tmp_path / "out"
    victims = {name: tmp_path / f"victim_{name}" for name in ("split", "yaml")}
    for victim in victims.values():
        victim.write_text("IMPORTANT USER DATA\n")
    (out_dir / "ImageSets").mkdir(parents=True)
    (out_dir / "ImageSets" / "val.txt").symlink_to(victims["split"])
    (out_dir / "atlas_attack.yaml").symlink_to(victims["yaml"])
    load_tool("data/generate_atlas").main(gen_args(cfg_path, out_dir))
    assert [v.read_text() for v in victims.values()] == ["IMPORTANT USER DATA\n"] * 2
    assert not (out_dir / "ImageSets" / "val.txt").is_symlink()
    assert (out_dir / "ImageSets" / "val.txt").read_text().endswith(".tfrecord\n")
    assert not (out_dir / "atlas_attack.yaml").is_symlink()

    (seq_dir,) = wf.data_dir(out_dir).iterdir()
    elsewhere = tmp_path / "elsewhere"
    seq_dir.rename(elsewhere)  # the sequence folder now leads out of --out_dir
    seq_dir.symlink_to(elsewhere, target_is_directory=True)
    for path in elsewhere.iterdir():
        path.unlink()  # unfinished: the tool would write the sequence there again
    with pytest.raises(UnsafePathError, match=rf"{seq_dir.name} \(from --out_dir {out_dir}\) "
                       rf"resolves to {elsewhere}, outside its root"):  # fmt: skip
        load_tool("data/generate_atlas").main(gen_args(cfg_path, out_dir))
    assert list(elsewhere.iterdir()) == []
    seq_dir.unlink()
    (out_dir / "ImageSets" / "val.txt").unlink()
    (out_dir / "ImageSets").rmdir()
    (tmp_path / "sets").mkdir()
    (out_dir / "ImageSets").symlink_to(tmp_path / "sets", target_is_directory=True)
    with pytest.raises(UnsafePathError, match=r"ImageSets \(from --out_dir .*\) resolves to "
                       r".*/sets, outside its root"):  # fmt: skip
        load_tool("data/generate_atlas").main(gen_args(cfg_path, out_dir))
    assert list((tmp_path / "sets").iterdir()) == []
