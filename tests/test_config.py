import re
from pathlib import Path

import pytest
import yaml

from pcdet_atlas.config import (
    REPO_ROOT,
    ConfigError,
    cfg_from_list,
    cfg_from_yaml_file,
    check_known_keys,
    key_source,
    repo_relative,
    save_config,
)


def write(path: Path, data: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture
def tree(tmp_path):
    write(
        tmp_path / "cfgs" / "dataset_configs" / "base.yaml",
        {
            "DATASET": "WaymoDataset",
            "POINT_CLOUD_RANGE": [-75.2, -75.2, -2, 75.2, 75.2, 4],
            "SAMPLED_INTERVAL": {"train": 5, "test": 1},
            "FLAG": True,
        },
    )
    write(
        tmp_path / "cfgs" / "models" / "child.yaml",
        {
            "CLASS_NAMES": ["Vehicle"],
            "DATA_CONFIG": {
                "_BASE_CONFIG_": "../dataset_configs/base.yaml",
                "POINT_CLOUD_RANGE": [-10, -10, -2, 10, 10, 4],
                "SAMPLED_INTERVAL": {"train": 1},
            },
            "OPTIMIZATION": {"LR": 0.003, "NUM_EPOCHS": 30, "NAME": "adam", "NONE_KEY": None},
        },
    )
    return tmp_path


def test_relative_base_merge_and_list_replace(tree, monkeypatch):
    monkeypatch.chdir("/")  # resolution must not depend on the working directory
    cfg = cfg_from_yaml_file(tree / "cfgs" / "models" / "child.yaml")
    d = cfg.DATA_CONFIG
    assert d.DATASET == "WaymoDataset"
    assert d.POINT_CLOUD_RANGE == [-10, -10, -2, 10, 10, 4]  # list replaced wholesale
    assert d.SAMPLED_INTERVAL == {"train": 1, "test": 1}  # dict merged
    assert "_BASE_CONFIG_" not in d
    assert key_source(d, "DATASET").endswith("base.yaml")
    assert key_source(d, "POINT_CLOUD_RANGE").endswith("child.yaml")


def test_chained_bases_and_cycle(tmp_path):
    write(tmp_path / "a.yaml", {"A": 1, "B": {"x": 1}})
    write(tmp_path / "sub" / "b.yaml", {"_BASE_CONFIG_": "../a.yaml", "B": {"y": 2}})
    write(tmp_path / "sub" / "c.yaml", {"_BASE_CONFIG_": "b.yaml", "C": 3})
    cfg = cfg_from_yaml_file(tmp_path / "sub" / "c.yaml")
    assert cfg == {"A": 1, "B": {"x": 1, "y": 2}, "C": 3}
    write(tmp_path / "p.yaml", {"_BASE_CONFIG_": "q.yaml"})
    write(tmp_path / "q.yaml", {"_BASE_CONFIG_": "p.yaml"})
    with pytest.raises(ConfigError, match="cycle"):
        cfg_from_yaml_file(tmp_path / "p.yaml")


def test_missing_base_names_both_files(tmp_path):
    child = write(tmp_path / "child.yaml", {"_BASE_CONFIG_": "nope/missing.yaml"})
    with pytest.raises(ConfigError) as err:
        cfg_from_yaml_file(child)
    assert "child.yaml" in str(err.value) and "missing.yaml" in str(err.value)


def test_missing_file_and_bad_yaml(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        cfg_from_yaml_file(tmp_path / "absent.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("A: [1, 2\n")
    with pytest.raises(ConfigError, match="invalid YAML"):
        cfg_from_yaml_file(bad)


def test_unknown_key_error_names_key_and_file(tree):
    cfg = cfg_from_yaml_file(tree / "cfgs" / "models" / "child.yaml")
    cfg.DATA_CONFIG  # noqa: B018
    check_known_keys(
        cfg.DATA_CONFIG, {"DATASET", "POINT_CLOUD_RANGE", "SAMPLED_INTERVAL", "FLAG"}, "DATA_CONFIG"
    )
    with pytest.raises(ConfigError) as err:
        check_known_keys(
            cfg.DATA_CONFIG, {"DATASET", "POINT_CLOUD_RANGE", "SAMPLED_INTERVAL"}, "DATA_CONFIG"
        )
    msg = str(err.value)
    assert "'FLAG'" in msg and "base.yaml" in msg and "DATA_CONFIG" in msg


def test_set_overrides_typing(tree):
    cfg = cfg_from_yaml_file(tree / "cfgs" / "models" / "child.yaml")
    cfg_from_list(
        [
            "OPTIMIZATION.LR",
            "0.01",
            "OPTIMIZATION.NUM_EPOCHS",
            "5",
            "OPTIMIZATION.NAME",
            "sgd",
            "DATA_CONFIG.POINT_CLOUD_RANGE",
            "-5,-5,-1,5,5,1",
            "DATA_CONFIG.SAMPLED_INTERVAL",
            "train:2,test:3",
            "DATA_CONFIG.FLAG",
            "False",
            "OPTIMIZATION.NONE_KEY",
            "[1, 2]",
        ],
        cfg,
    )
    assert cfg.OPTIMIZATION.LR == 0.01 and cfg.OPTIMIZATION.NUM_EPOCHS == 5
    assert cfg.OPTIMIZATION.NAME == "sgd"
    assert cfg.DATA_CONFIG.POINT_CLOUD_RANGE == [-5, -5, -1, 5, 5, 1]
    assert cfg.DATA_CONFIG.SAMPLED_INTERVAL == {"train": 2, "test": 3}
    assert cfg.DATA_CONFIG.FLAG is False
    assert cfg.OPTIMIZATION.NONE_KEY == [1, 2]
    with pytest.raises(ConfigError, match="does not match the original type float"):
        cfg_from_list(["OPTIMIZATION.LR", "'fast'"], cfg)
    with pytest.raises(ConfigError, match="does not match the original type int"):
        cfg_from_list(["OPTIMIZATION.NUM_EPOCHS", "2.5"], cfg)
    with pytest.raises(ConfigError, match="not found"):
        cfg_from_list(["OPTIMIZATION.NOPE", "1"], cfg)
    with pytest.raises(ConfigError, match="odd number"):
        cfg_from_list(["OPTIMIZATION.LR"], cfg)


def test_save_config_roundtrip(tree, tmp_path):
    cfg = cfg_from_yaml_file(tree / "cfgs" / "models" / "child.yaml")
    out = save_config(cfg, tmp_path / "out" / "merged.yaml")
    again = cfg_from_yaml_file(out)
    assert again == cfg


def test_save_config_replaces_a_planted_symlink_instead_of_writing_through_it(tree, tmp_path):
    """A resumed output folder received with ``<TAG>.yaml -> ~/.bashrc``: the merged config
    replaces the link; the file it pointed at keeps its content."""
    victim = tmp_path / "victim"
    victim.write_text("IMPORTANT USER DATA\n")
    out = tmp_path / "out" / "child.yaml"
    out.parent.mkdir()
    out.symlink_to(victim)
    cfg = cfg_from_yaml_file(tree / "cfgs" / "models" / "child.yaml")
    save_config(cfg, out)
    assert victim.read_text() == "IMPORTANT USER DATA\n"
    assert not out.is_symlink() and cfg_from_yaml_file(out) == cfg


def test_repo_configs_load(tmp_path, monkeypatch):
    """Every shipped YAML loads with its whole _BASE_CONFIG_ chain, from any working directory."""
    root = Path(__file__).resolve().parent.parent / "cfgs"
    monkeypatch.chdir(tmp_path)
    for f in sorted(root.rglob("*.yaml")):
        cfg = cfg_from_yaml_file(f)
        assert isinstance(cfg, dict) and cfg, f


EXPERIMENT_BASE = REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "centerpoint.yaml"


@pytest.mark.parametrize(
    "body,key",
    [
        ("OPTIMISATION:\n  LR: 0.001\n", "unknown key 'OPTIMISATION' in the detector config"),
        ("DATA_CONFIG:\n  POINT_CLOUD_RANGE: big\n", "DATA_CONFIG.POINT_CLOUD_RANGE = 'big'"),
        ("DATA_CONFIG:\n  POINT_CLOUD_RANGE: bigbig\n", "DATA_CONFIG.POINT_CLOUD_RANGE = 'bigbig'"),
        ("DATA_CONFIG:\n  POINT_CLOUD_RANGE: [0, 0, 0, 10, 10, .nan]\n", "POINT_CLOUD_RANGE"),
        ("DATA_CONFIG:\n  POINT_CLOUD_RANGE: [10, 0, 0, 0, 10, 4]\n", "POINT_CLOUD_RANGE"),
        ("OPTIMIZATION:\n  BATCH_SIZE_PER_GPU: four\n", "BATCH_SIZE_PER_GPU = 'four'"),
        ("OPTIMIZATION:\n  NUM_EPOCHS: 2.5\n", "NUM_EPOCHS = 2.5"),
        ("OPTIMIZATION:\n  LR: .inf\n", "OPTIMIZATION.LR = inf"),
        ("CLASS_NAMES: Vehicle\n", "CLASS_NAMES = 'Vehicle'"),
        ("MODEL: centerpoint\n", "MODEL = 'centerpoint'"),
    ],
)
def test_detector_config_sections_and_value_types(tmp_path, body, key):
    """An unknown top-level section or a value of the wrong type is an error naming the key and
    the file, before anything is built."""
    from pcdet_atlas.train_utils.setup import load_cfg

    path = tmp_path / "mine.yaml"
    path.write_text(f"_BASE_CONFIG_: {EXPERIMENT_BASE}\n{body}")
    with pytest.raises(ConfigError, match=re.escape(key)) as info:
        load_cfg(str(path), None)
    assert "mine.yaml" in str(info.value)


def test_repo_relative_names_files_from_the_repository_root(tmp_path, monkeypatch):
    name = Path("cfgs/atlas/synthetic/cp4f.yaml")
    assert repo_relative(REPO_ROOT / name) == name
    monkeypatch.chdir(REPO_ROOT / "tools")  # a relative path resolves from the working folder
    assert repo_relative(Path("..") / name) == name
    outside = tmp_path / "results.json"
    assert repo_relative(outside) == outside.resolve()  # outside the clone: kept absolute
