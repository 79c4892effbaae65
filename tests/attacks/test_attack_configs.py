"""Every attack YAML under cfgs/attacks builds and runs on a synthetic frame; configs are strict."""

from pathlib import Path

import numpy as np
import pytest
import torch
from atlas_helpers import synthetic_library

from pcdet_atlas.attacks.base import BaseAttack, FrameAttack, SequenceData, build_attack
from pcdet_atlas.attacks.metadata import validate_meta
from pcdet_atlas.config import REPO_ROOT, ConfigError, cfg_from_yaml_file
from pcdet_atlas.datasets.waymo_format import (
    frame_npy_path,
    load_frame_points,
    load_sequence_infos,
    read_image_set,
    sequence_pkl_path,
)
from pcdet_atlas.registry import ATTACKS

ATTACK_DIR = REPO_ROOT / "cfgs" / "attacks"
VARIANTS = sorted(p.stem for p in ATTACK_DIR.glob("*.yaml"))
EXPECTED = {"clean"} | {
    f"inj_{m}_{b}" for m in ("rel", "global") for b in ("easy", "medium", "hard")
}
EXPECTED |= {f"rem_{w}" for w in (10, 20, 30, 40, 50, 60)}


def test_the_twelve_variants_and_clean_are_shipped():
    assert set(VARIANTS) == EXPECTED


@pytest.fixture(scope="module")
def frame(synthetic_root, tmp_path_factory):
    lib_path = synthetic_library(synthetic_root, tmp_path_factory.mktemp("cfg_lib"))
    name = read_image_set(synthetic_root / "ImageSets" / "val.txt")[0]
    seq = SequenceData(name, load_sequence_infos(sequence_pkl_path(synthetic_root, name)))
    points = load_frame_points(frame_npy_path(synthetic_root, name, 40))[:, :5]
    return lib_path, seq, points


@pytest.mark.parametrize("variant", VARIANTS)
def test_every_yaml_builds_and_runs(variant, frame):
    lib_path, seq, points = frame
    cfg = cfg_from_yaml_file(ATTACK_DIR / f"{variant}.yaml")
    if "TRACE_LIBRARY" in cfg:
        cfg.TRACE_LIBRARY.PATH = str(lib_path)
    attack = build_attack(cfg)
    assert attack.variant == variant and type(attack).__name__ == cfg.NAME
    result = attack.simulate(points[:, :3], seq, 40)
    validate_meta(result.meta)
    out = result.apply(points)
    assert out.dtype == np.float32 and out.shape[1] == 5 and np.isfinite(out).all()
    meta = result.meta
    if variant == "clean":
        assert not meta["spoofed"] and result.keep is None and len(out) == len(points)
    elif variant.startswith("inj"):
        assert meta["family"] == "injection" and meta["num_visible"] > 0
        assert len(out) == len(points) - meta["num_removed"] + meta["num_visible"]
    else:
        assert meta["family"] == "removal" and meta["tracked"]
        assert len(out) == len(points) - meta["num_removed"]
    # an empty frame is legal input: it flows through (a phantom then stands on the fallback
    # ground, alone in its rays)
    empty = attack.simulate(np.zeros((0, 3), np.float32), seq, 40)
    validate_meta(empty.meta)
    assert empty.apply(np.zeros((0, 5), np.float32)).shape[1] == 5


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_unknown_keys_fail_naming_key_and_file(tmp_path):
    bad = _write(
        tmp_path / "rem_typo.yaml",
        f"_BASE_CONFIG_: {ATTACK_DIR / 'rem_10.yaml'}\nVARIANT: rem_typo\nP_REMOVAL: 0.5\n",
    )
    with pytest.raises(ConfigError, match=r"P_REMOVAL.*rem_typo\.yaml"):
        build_attack(cfg_from_yaml_file(bad))
    nested = _write(
        tmp_path / "inj_typo.yaml",
        f"_BASE_CONFIG_: {ATTACK_DIR / 'inj_rel_easy.yaml'}\nGROUND:\n  RADIUS_M: 2.0\n",
    )
    with pytest.raises(ConfigError, match=r"RADIUS_M.*inj_typo\.yaml"):
        build_attack(cfg_from_yaml_file(nested))
    with pytest.raises(KeyError, match="InjectionAttack"):
        build_attack(cfg_from_yaml_file(_write(tmp_path / "n.yaml", "NAME: InjectonAttack\n")))


BASE = ATTACK_DIR / "_base_"
MISSING_KEYS = [  # (YAML body without a required key, the key the error must name)
    (f"_BASE_CONFIG_: {BASE / 'removal.yaml'}\nAZIMUTH_WIDTH_DEG: 10.0\n", "P_REMOVE"),
    (f"_BASE_CONFIG_: {BASE / 'common.yaml'}\nNAME: InjectionAttack\n", "TRACE_LIBRARY"),
    (
        f"_BASE_CONFIG_: {BASE / 'common.yaml'}\nNAME: RemovalAttack\n"
        "AZIMUTH_WIDTH_DEG: 10.0\nP_REMOVE: 0.9\nP_DIST:\n  EDGES_M: [0.0, 10.0]\n",
        "PROB",
    ),
]  # fmt: skip


@pytest.mark.parametrize("body,key", MISSING_KEYS, ids=[key for _, key in MISSING_KEYS])
def test_missing_keys_fail_naming_key_and_file(tmp_path, body, key):
    bad = _write(tmp_path / "no_key.yaml", f"VARIANT: no_key\n{body}")
    with pytest.raises(ConfigError, match=rf"{key}.*no_key\.yaml"):
        build_attack(cfg_from_yaml_file(bad))


BAD_VALUES = [  # (base variant, YAML body, the key the error must name)
    ("clean", "SEED: abc\n", "SEED"),
    ("clean", "SCHEDULE:\n  WINDOW: many\n", "WINDOW"),
    ("rem_10", "SCHEDULE:\n  WINDOW: 0\n", "WINDOW"),
    ("rem_10", "AZIMUTH_WIDTH_DEG: wide\n", "AZIMUTH_WIDTH_DEG"),
    ("rem_10", "P_REMOVE: 1.5\n", "P_REMOVE"),
    ("rem_10", "TARGET:\n  MIN_POINTS: some\n", "MIN_POINTS"),
    ("rem_10", "TRACKING:\n  D_MAX: -1.0\n", "D_MAX"),
    ("rem_10", "P_DIST:\n  PROB: [0.5, 0.5, 0.5, 0.5, 2.0]\n", "PROB"),
    ("inj_rel_easy", "BUDGET: [a, 5]\n", "BUDGET"),
    ("inj_rel_easy", "POSITION_MODE: sideways\n", "POSITION_MODE"),
    ("inj_rel_easy", "P_DUAL: 2.0\n", "P_DUAL"),
    ("inj_rel_easy", "GROUND:\n  RADIUS: wide\n", "RADIUS"),
    ("inj_rel_easy", "INTENSITY:\n  MIN_RANGE: -1.0\n", "MIN_RANGE"),
    ("inj_rel_easy", "TRACE_LIBRARY:\n  MIN_POINTS: many\n", "MIN_POINTS"),
    ("inj_rel_easy", "LIDAR:\n  MAX_RANGE: far\n", "MAX_RANGE"),
    # non-finite floats anywhere (the key named with its path) and integer keys given floats
    ("inj_rel_easy", "INTENSITY:\n  INTENSITY_EXPONENT: .nan\n", "INTENSITY.INTENSITY_EXPONENT"),
    ("inj_rel_easy", "LIDAR:\n  ORIGIN: [.nan, 0.0, 2.0]\n", "LIDAR.ORIGIN[0]"),
    ("inj_rel_easy", "LIDAR:\n  INCLINATIONS_DEG: [-10.0, .inf]\n", "LIDAR.INCLINATIONS_DEG[1]"),
    ("inj_rel_easy", "OFFSET_X: [15.0, .inf]\n", "OFFSET_X[1]"),
    ("rem_10", "P_DIST:\n  PROB: [0.5, .nan, 0.5, 0.5, 0.5]\n", "P_DIST.PROB[1]"),
    ("rem_10", "TRACKING:\n  D_MAX: -.inf\n", "TRACKING.D_MAX"),
    ("clean", "SEED: 1.7\n", "SEED"),
    ("clean", "SEED: 2.0\n", "SEED"),
    ("rem_10", "SCHEDULE:\n  WINDOW: 32.5\n", "WINDOW"),
    # values that used to raise a bare error, or pass and change the attack silently
    ("inj_rel_easy", "TRACE_LIBRARY:\n  RANGE_M: [5.0, abc]\n", "TRACE_LIBRARY.RANGE_M"),
    ("inj_rel_easy", "TRACE_LIBRARY:\n  CLASSES: Vehicle\n", "TRACE_LIBRARY.CLASSES"),
    ("inj_rel_easy", "TRACE_LIBRARY:\n  CLASSES: [Car]\n", "TRACE_LIBRARY.CLASSES"),
    ("inj_rel_easy", "TRACE_LIBRARY:\n  MIN_POINTS_PER_FRAME: -3\n", "MIN_POINTS_PER_FRAME"),
    ("inj_rel_easy", "TRACE_LIBRARY:\n  MIN_FRAMES: -2\n", "TRACE_LIBRARY.MIN_FRAMES"),
    ("inj_rel_easy", "LIDAR:\n  INCLINATIONS: 0.1\n", "LIDAR.INCLINATIONS"),
    ("rem_10", "LIDAR:\n  INCLINATIONS_DEG: [0.0, -10.0]\n", "LIDAR.INCLINATIONS_DEG"),
    ("inj_rel_easy", "GROUND:\n  MAX_ABS_Z: -1\n", "GROUND.MAX_ABS_Z"),
    ("inj_rel_easy", "INTENSITY:\n  MAX_INTENSITY: -5\n", "INTENSITY.MAX_INTENSITY"),
]


@pytest.mark.parametrize("base,body,key", BAD_VALUES)
def test_bad_values_fail_naming_key_value_and_file(tmp_path, base, body, key):
    """A wrong value is a ConfigError that names the key, the value and the file it came from
    (never a bare ValueError/TypeError from deep inside a constructor)."""
    bad = _write(tmp_path / "bad_value.yaml", f"_BASE_CONFIG_: {ATTACK_DIR / base}.yaml\n{body}")
    items = [v.strip() for v in body.strip().rsplit(":", 1)[-1].strip().strip("[]").split(",")]
    value = next((v for v in items if ".nan" in v or ".inf" in v), items[-1])  # the bad item
    value = value.replace(".nan", "nan").replace(".inf", "inf")  # YAML's spelling -> Python's
    with pytest.raises(ConfigError) as info:
        build_attack(cfg_from_yaml_file(bad))
    message = str(info.value)
    assert key in message and "bad_value.yaml" in message, message
    assert value in message.replace(str(bad), ""), message  # the value, not the file's name


def test_device_cuda_without_a_gpu_is_one_clear_error(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for base in ("inj_rel_easy", "rem_10", "clean"):
        bad = _write(
            tmp_path / "gpu.yaml", f"_BASE_CONFIG_: {ATTACK_DIR / base}.yaml\nDEVICE: cuda\n"
        )
        with pytest.raises(ConfigError, match=r"DEVICE = 'cuda' \(from .*gpu\.yaml\).*no CUDA GPU"):
            build_attack(cfg_from_yaml_file(bad))
    bad = _write(
        tmp_path / "tpu.yaml", f"_BASE_CONFIG_: {ATTACK_DIR / 'clean'}.yaml\nDEVICE: tpu\n"
    )
    with pytest.raises(ConfigError, match=r"DEVICE = 'tpu' \(from .*tpu\.yaml\)"):
        build_attack(cfg_from_yaml_file(bad))


def test_new_variant_is_yaml_only(tmp_path, frame):
    _, seq, points = frame
    path = _write(
        tmp_path / "rem_15.yaml",
        f"_BASE_CONFIG_: {ATTACK_DIR / '_base_/removal.yaml'}\n"
        "VARIANT: rem_15\nAZIMUTH_WIDTH_DEG: 15.0\nP_REMOVE: 0.5\n",
    )
    attack = build_attack(cfg_from_yaml_file(path))
    assert attack.variant == "rem_15" and attack.p_remove == 0.5
    attack.simulate(points[:, :3], seq, 40)


class _DropEveryOther(BaseAttack):
    """A toy family: drops every other point on spoofed frames."""

    family = "drop_every_other"

    @classmethod
    def from_config(cls, cfg, data_root=None):
        return cls(**cls._common_kwargs(cfg))

    def prepare_run(self, seq, run_id):
        return run_id

    def attack_frame(self, scene_xyz, seq, frame_idx, run, state):
        keep = np.arange(len(scene_xyz)) % 2 == 0
        meta = self.meta(state, num_removed=int((~keep).sum()), fired=True)
        return FrameAttack(keep, np.zeros((0, 5), np.float32), meta)

    def shadow_meta(self, seq, frame_idx, run, state):
        return self.meta(state)  # no target, so no shadow target


def test_new_family_is_one_registered_class_plus_yaml(tmp_path, frame):
    _, seq, points = frame
    if "TestDropEveryOther" not in ATTACKS:
        ATTACKS.register("TestDropEveryOther")(_DropEveryOther)
    path = _write(
        tmp_path / "drop.yaml",
        f"_BASE_CONFIG_: {ATTACK_DIR / '_base_/common.yaml'}\n"
        "NAME: TestDropEveryOther\nVARIANT: drop\n",
    )
    attack = build_attack(cfg_from_yaml_file(path))
    res = attack.simulate(points[:, :3], seq, 40)
    assert (
        res.meta["family"] == "drop_every_other"
        and len(res.apply(points)) == (len(points) + 1) // 2
    )
    assert attack.simulate(None, seq, 10).keep is None  # clean frames untouched
    validate_meta(attack.frame_meta(seq, 64))
