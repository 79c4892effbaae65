"""tools/generate_atlas.py refuses an --out_dir that would overwrite its own source dataset."""

import hashlib

import pytest
from atlas_helpers import load_tool, write_tiny_waymo

from pcdet_atlas.config import REPO_ROOT

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
        load_tool("generate_atlas").main(gen_args(cfg_path, out_dir))
    assert tree_digest(root) == before
    assert not (root / "atlas").exists() and not (root / "atlas_attack.yaml").exists()


def test_out_dir_beside_the_source_is_written(source, tmp_path):
    root, cfg_path = source
    out_dir = tmp_path / "data" / "tiny_clean"  # a sibling whose name starts like the source's
    load_tool("generate_atlas").main(gen_args(cfg_path, out_dir))
    assert (out_dir / "atlas_attack_metadata.pkl").is_file()
    assert sorted(p.name for p in (out_dir / "ImageSets").iterdir()) == ["val.txt"]
